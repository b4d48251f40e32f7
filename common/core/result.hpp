// Result<T> and Status: how expected failures travel in cvislam.
//
// A bug is an assertion; an expected failure (a missing file, a malformed line, a degenerate input) is a
// returned value that names the problem. Exceptions do not cross module boundaries.
#pragma once

#include <string>
#include <string_view>
#include <type_traits>
#include <utility>
#include <variant>

#include "common/core/check.hpp"

namespace cvislam {

enum class ErrorCode {
  kInvalidArgument,   // a value the caller passed, or a config value, is wrong
  kNotFound,          // a file, folder, key or id does not exist
  kParseError,        // text that does not have the expected form
  kIoError,           // the file system or a device failed
  kDataError,         // well-formed input whose content is unusable (e.g. time going backwards)
  kDegenerate,        // the maths has no unique answer for this input (e.g. collinear points)
  kCapacityExceeded,  // a fixed-capacity container is full
  kInternal,          // a failure that indicates a bug somewhere else
  // Peers across the network (server <-> agent, API clients):
  kAlreadyExists,       // the object or the role (an agent id already connected) is taken
  kFailedPrecondition,  // the request is well formed but not valid in this state (another protocol version)
  kResourceExhausted,   // a limit was reached (message size, agents per mission)
  kUnavailable,         // the peer cannot be reached now; trying again later may work
  kUnauthenticated,     // the caller presented no credentials, or the wrong ones, for what it asked
  kAborted,             // a conflict with what another attempt did (a resent batch unlike the stored one): retry
};

std::string_view toString(ErrorCode code) noexcept;

class Error {
 public:
  Error(ErrorCode code, std::string message) : code_(code), message_(std::move(message)) {}

  [[nodiscard]] ErrorCode code() const noexcept { return code_; }
  [[nodiscard]] const std::string& message() const noexcept { return message_; }
  // "parse error: <message>"
  [[nodiscard]] std::string toString() const;

  // Prepends context, e.g. error.withContext("reading imu0") -> "reading imu0: <message>".
  [[nodiscard]] Error withContext(std::string_view context) const;

 private:
  ErrorCode code_;
  std::string message_;
};

template <typename T>
class [[nodiscard]] Result {
 public:
  // Implicit on purpose: `return value;` and `return Error{...};` both read naturally.
  Result(T value) : storage_(std::in_place_index<0>, std::move(value)) {}      // NOLINT(google-explicit-constructor)
  Result(Error error) : storage_(std::in_place_index<1>, std::move(error)) {}  // NOLINT(google-explicit-constructor)

  [[nodiscard]] bool ok() const noexcept { return storage_.index() == 0; }
  explicit operator bool() const noexcept { return ok(); }

  [[nodiscard]] T& value() & {
    CVISLAM_CHECK(ok(), "Result::value() on an error");
    return std::get<0>(storage_);
  }
  [[nodiscard]] const T& value() const& {
    CVISLAM_CHECK(ok(), "Result::value() on an error");
    return std::get<0>(storage_);
  }
  [[nodiscard]] T&& value() && {
    CVISLAM_CHECK(ok(), "Result::value() on an error");
    return std::get<0>(std::move(storage_));
  }
  [[nodiscard]] const Error& error() const& {
    CVISLAM_CHECK(!ok(), "Result::error() on a value");
    return std::get<1>(storage_);
  }

  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }

 private:
  std::variant<T, Error> storage_;
};

// Status is Result<void>: either OK or an Error.
class [[nodiscard]] Status {
 public:
  Status() = default;
  Status(Error error) : error_(std::move(error)), ok_(false) {}  // NOLINT(google-explicit-constructor)
  static Status Ok() { return {}; }

  [[nodiscard]] bool ok() const noexcept { return ok_; }
  explicit operator bool() const noexcept { return ok_; }
  [[nodiscard]] const Error& error() const {
    CVISLAM_CHECK(!ok_, "Status::error() on OK");
    return error_;
  }

 private:
  Error error_{ErrorCode::kInternal, {}};
  bool ok_ = true;
};

}  // namespace cvislam
