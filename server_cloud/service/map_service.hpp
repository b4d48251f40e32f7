// The map service's gRPC adapter (cvislam.v1.MapService): each call asks server_cloud/maps for its answer and
// turns the internal status into a grpc::Status. Streams (GetMap, ExportMap) write one chunk at a time, each made
// only when the previous one left, from a copy of the map taken when the call started. WatchMission streams
// read the mission's event log: after each write, and on the server's periodic tick.
#pragma once

#include <memory>

#include "server_cloud/core/server_core.hpp"

namespace grpc {
class ChannelCredentials;
class Service;
}  // namespace grpc

namespace cvislam::server {

class MapService {
 public:
  explicit MapService(ServerCore& core);
  ~MapService();
  MapService(const MapService&) = delete;
  MapService& operator=(const MapService&) = delete;

  [[nodiscard]] grpc::Service* service();
  // Scale-out: reads of a mission that another replica serves are passed to it, over a channel with these
  // credentials (read_forwarding.hpp). Before the server starts.
  void forwardWith(std::shared_ptr<grpc::ChannelCredentials> peer_credentials);
  // From the server's periodic thread: each WatchMission stream sends what its mission's log gained.
  void tick();
  // Ends every WatchMission stream with UNAVAILABLE (the server is stopping); later ones are refused.
  void stopWatches();

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::server
