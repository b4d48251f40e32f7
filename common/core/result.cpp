#include "common/core/result.hpp"

namespace cvislam {

std::string_view toString(ErrorCode code) noexcept {
  switch (code) {
    case ErrorCode::kInvalidArgument:
      return "invalid argument";
    case ErrorCode::kNotFound:
      return "not found";
    case ErrorCode::kParseError:
      return "parse error";
    case ErrorCode::kIoError:
      return "I/O error";
    case ErrorCode::kDataError:
      return "data error";
    case ErrorCode::kDegenerate:
      return "degenerate input";
    case ErrorCode::kCapacityExceeded:
      return "capacity exceeded";
    case ErrorCode::kInternal:
      return "internal error";
    case ErrorCode::kAlreadyExists:
      return "already exists";
    case ErrorCode::kFailedPrecondition:
      return "failed precondition";
    case ErrorCode::kResourceExhausted:
      return "resource exhausted";
    case ErrorCode::kUnavailable:
      return "unavailable";
    case ErrorCode::kUnauthenticated:
      return "unauthenticated";
    case ErrorCode::kAborted:
      return "aborted";
  }
  return "unknown error";
}

std::string Error::toString() const {
  std::string out(cvislam::toString(code_));
  out += ": ";
  out += message_;
  return out;
}

Error Error::withContext(std::string_view context) const {
  std::string message(context);
  message += ": ";
  message += message_;
  return {code_, std::move(message)};
}

}  // namespace cvislam
