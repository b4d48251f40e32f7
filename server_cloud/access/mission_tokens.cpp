#include "server_cloud/access/mission_tokens.hpp"

#include <cctype>
#include <sstream>

#include "common/core/text.hpp"

namespace cvislam::server {

namespace {

// Compares without stopping at the first difference, so that the time taken says nothing about how much of a
// guess was right.
bool sameToken(std::string_view a, std::string_view b) {
  if (a.size() != b.size() || a.empty()) return false;
  unsigned char diff = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    diff |= static_cast<unsigned char>(static_cast<unsigned char>(a[i]) ^ static_cast<unsigned char>(b[i]));
  }
  return diff == 0;
}

}  // namespace

Result<MissionTokens> MissionTokens::load(const std::filesystem::path& file) {
  auto text = text::readTextFile(file, "tokens file");
  if (!text) return text.error();
  return parse(*text, file.string());
}

Result<MissionTokens> MissionTokens::parse(std::string_view text, const std::string& source) {
  MissionTokens tokens;
  tokens.enabled_ = true;
  std::istringstream lines{std::string(text)};
  std::string line;
  int number = 0;
  const auto bad = [&](const std::string& what) {
    return Error{ErrorCode::kParseError, source + " line " + std::to_string(number) + ": " + what};
  };
  while (std::getline(lines, line)) {
    ++number;
    if (const auto hash = line.find('#'); hash != std::string::npos) line.resize(hash);
    std::istringstream fields(line);
    std::string mission;
    std::string token;
    std::string extra;
    if (!(fields >> mission)) continue;  // blank or comment
    if (!(fields >> token)) return bad("'" + mission + "' has no token: write 'MISSION TOKEN'");
    if (fields >> extra) return bad("more than 'MISSION TOKEN' ('" + extra + "')");
    if (token.size() < kMinTokenChars || !text::isPrintableToken(token)) {
      return bad("the token of '" + mission + "' has " + std::to_string(token.size()) + " characters; use at least " +
                 std::to_string(kMinTokenChars) + " (e.g. openssl rand -hex 16)");
    }
    if (mission == "*") {
      if (!tokens.operator_token_.empty()) return bad("a second operator token ('*')");
      tokens.operator_token_ = token;
      continue;
    }
    if (!tokens.by_mission_.emplace(mission, token).second) return bad("mission '" + mission + "' is listed twice");
  }
  if (tokens.by_mission_.empty() && tokens.operator_token_.empty()) {
    return Error{ErrorCode::kParseError,
                 source + " lists no mission: write one 'MISSION TOKEN' line per mission (or leave tokens off)"};
  }
  return tokens;
}

Status MissionTokens::authorize(std::string_view mission, std::string_view presented) const {
  if (!enabled_) return Status::Ok();
  const std::string name(mission);
  if (presented.empty()) {
    return Error{ErrorCode::kUnauthenticated,
                 "mission '" + name +
                     "' needs its token: send gRPC metadata 'authorization: Bearer <token>' (--token, or "
                     "CVISLAM_TOKEN)"};
  }
  if (sameToken(presented, operator_token_)) return Status::Ok();
  const auto it = by_mission_.find(name);
  // One answer for a mission the file does not list and a token that is not the mission's, so that no one learns
  // which missions exist by trying names.
  if (it == by_mission_.end() || !sameToken(presented, it->second)) {
    return Error{ErrorCode::kUnauthenticated,
                 "the token presented does not open mission '" + name +
                     "' (check the token, and that the server's tokens file lists the mission)"};
  }
  return Status::Ok();
}

bool MissionTokens::opensAny(std::string_view presented) const {
  if (!enabled_ || presented.empty()) return false;
  if (sameToken(presented, operator_token_)) return true;
  bool any = false;
  for (const auto& [mission, token] : by_mission_) any = sameToken(presented, token) || any;  // every one compared
  return any;
}

std::string_view bearerToken(std::string_view authorization) {
  constexpr std::string_view kScheme = "bearer ";
  if (authorization.size() <= kScheme.size()) return {};
  for (std::size_t i = 0; i < kScheme.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(authorization[i])) != kScheme[i]) return {};
  }
  std::string_view token = authorization.substr(kScheme.size());
  while (!token.empty() && token.front() == ' ') token.remove_prefix(1);
  while (!token.empty() && token.back() == ' ') token.remove_suffix(1);
  return token;
}

}  // namespace cvislam::server
