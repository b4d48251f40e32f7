#include "server_cloud/service/grpc_status.hpp"

namespace cvislam::server {

grpc::StatusCode toGrpcCode(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument:
    case ErrorCode::kParseError:
    case ErrorCode::kDataError:
      return grpc::StatusCode::INVALID_ARGUMENT;
    case ErrorCode::kNotFound:
      return grpc::StatusCode::NOT_FOUND;
    case ErrorCode::kAlreadyExists:
      return grpc::StatusCode::ALREADY_EXISTS;
    case ErrorCode::kFailedPrecondition:
      return grpc::StatusCode::FAILED_PRECONDITION;
    case ErrorCode::kCapacityExceeded:
    case ErrorCode::kResourceExhausted:
      return grpc::StatusCode::RESOURCE_EXHAUSTED;
    case ErrorCode::kUnavailable:
      return grpc::StatusCode::UNAVAILABLE;
    case ErrorCode::kUnauthenticated:
      return grpc::StatusCode::UNAUTHENTICATED;
    case ErrorCode::kAborted:
      return grpc::StatusCode::ABORTED;
    case ErrorCode::kIoError:
    case ErrorCode::kDegenerate:
    case ErrorCode::kInternal:
      return grpc::StatusCode::INTERNAL;
  }
  return grpc::StatusCode::UNKNOWN;
}

grpc::Status toGrpc(const Status& status) {
  if (status.ok()) return grpc::Status::OK;
  std::string message = status.error().message();
  constexpr std::size_t kMaxMessage = 1024;
  if (message.size() > kMaxMessage) message = message.substr(0, kMaxMessage - 3) + "...";
  return {toGrpcCode(status.error().code()), message};
}

}  // namespace cvislam::server
