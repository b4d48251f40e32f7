// The map service's gRPC adapter (cvislam.v1.MapService): each call asks server_cloud/maps for its answer and
// turns the internal status into a grpc::Status. Streams (GetMap, ExportMap) write one chunk at a time, each made
// only when the previous one left, from a copy of the map taken when the call started.
#pragma once

#include <memory>

#include "server_cloud/core/server_core.hpp"

namespace grpc {
class Service;
}

namespace cvislam::server {

std::unique_ptr<grpc::Service> makeMapService(ServerCore& core);

}  // namespace cvislam::server
