// Internal Status -> grpc::Status, at the service edge only (the core never sees gRPC).
#pragma once

#include <grpcpp/support/status.h>

#include "common/core/result.hpp"

namespace cvislam::server {

grpc::StatusCode toGrpcCode(ErrorCode code);
// The message is the error's own, cut to 1 KiB (it travels in a header).
grpc::Status toGrpc(const Status& status);

}  // namespace cvislam::server
