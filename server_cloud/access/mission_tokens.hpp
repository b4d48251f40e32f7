// Who may touch which mission: every mission has a token, and agents and API clients present it with each call
// (gRPC metadata "authorization: Bearer <token>"; the adapters read it, this class decides). Plain C++.
//
// The tokens file (cvislam_server --tokens FILE, or server.tokens in the config; a Kubernetes Secret mounted as a
// file) has one mission per line:
//
//   # mission   token
//   mh-survey   4f1c0a57c2a04b2e9d7e1f3b8a6c5d40
//   *           9b2e...                       # the operator's token: reads and writes every mission
//
// With no tokens file every mission is open to every client (a development server on loopback). With one, a
// mission the file does not list cannot be opened at all: missions are declared, not made up by clients.
#pragma once

#include <filesystem>
#include <string>
#include <string_view>
#include <unordered_map>

#include "common/core/result.hpp"

namespace cvislam::server {

class MissionTokens {
 public:
  static constexpr std::size_t kMinTokenChars = 16;  // a guessable token is refused when the file is read

  MissionTokens() = default;  // open: no tokens, every mission admitted

  // Reads a tokens file; the error names the file, the line and what is wrong with it.
  static Result<MissionTokens> load(const std::filesystem::path& file);
  // The same from text; `source` names it in errors.
  static Result<MissionTokens> parse(std::string_view text, const std::string& source);

  // Whether tokens are required at all.
  [[nodiscard]] bool enabled() const { return enabled_; }
  [[nodiscard]] std::size_t missions() const { return by_mission_.size(); }

  // OK when `presented` (the bearer token, "" when the call carried none) opens `mission`; UNAUTHENTICATED
  // naming the mission and what to do otherwise. The comparison takes the same time for every wrong token of
  // a given length.
  [[nodiscard]] Status authorize(std::string_view mission, std::string_view presented) const;
  [[nodiscard]] bool admits(std::string_view mission, std::string_view presented) const {
    return authorize(mission, presented).ok();
  }
  // Whether `presented` opens at least one mission (false when tokens are off).
  [[nodiscard]] bool opensAny(std::string_view presented) const;

 private:
  bool enabled_ = false;
  std::unordered_map<std::string, std::string> by_mission_;
  std::string operator_token_;  // "*": every mission; empty when the file names none
};

// The bearer token in an "authorization" metadata value ("Bearer <token>", the scheme in any case); "" when the
// value is not of that form.
std::string_view bearerToken(std::string_view authorization);

}  // namespace cvislam::server
