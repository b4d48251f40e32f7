// The server's gRPC endpoint, on one port: the agent link (cvislam.v1.AgentLink), monitoring
// (cvislam.v1.Monitor), the map service for API clients (cvislam.v1.MapService) and grpc.health.v1. The adapters are
// thin: they turn wire messages into calls on ServerCore and internal statuses into grpc::Status. gRPC headers stay in
// the .cpp files.
#pragma once

#include <chrono>
#include <memory>
#include <string>

#include "common/core/result.hpp"
#include "server_cloud/core/server_core.hpp"

namespace cvislam::server {

class GrpcServer {
 public:
  // Binds core.options().listen and starts serving; a periodic thread sends the downlinks and samples the
  // timeline. Fails, naming the address, when it cannot listen (e.g. the port is taken).
  static Result<std::unique_ptr<GrpcServer>> start(ServerCore& core);
  ~GrpcServer();
  GrpcServer(const GrpcServer&) = delete;
  GrpcServer& operator=(const GrpcServer&) = delete;

  [[nodiscard]] int port() const;
  [[nodiscard]] int healthPort() const;       // the plaintext health port as bound; 0 without health_listen
  [[nodiscard]] std::string address() const;  // host:port as bound

  // Stops accepting; open streams get `grace` to end, then are cancelled. Idempotent.
  void shutdown(std::chrono::milliseconds grace = std::chrono::milliseconds(2000));

  struct Impl;

 private:
  explicit GrpcServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::server
