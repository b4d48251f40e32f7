// The viewer's network side: one port that serves the browser viewer's files over HTTP(S) and the Foxglove
// WebSocket protocol on upgrade, checking each upgrade's mission and token (viewer_hub.hpp decides; this file only
// moves bytes). websocketpp stays inside viewer_endpoint.cpp: its headers are heavy, and the build compiles them
// from a copy made C++20-clean (toolchains/cmake/CvislamDependencies.cmake).
//
// Per client, at most `socket_buffer_bytes` wait to be written to the socket (whose kernel buffer is fixed at
// `kernel_send_buffer_bytes`); the rest waits in the hub's bounded queue, which drops the oldest. A client that stops
// reading costs that much memory and no more.
#pragma once

#include <cstddef>
#include <filesystem>
#include <memory>
#include <string>

#include "common/core/result.hpp"

namespace cvislam::server {
class MissionTokens;
}

namespace cvislam::server::viewer {

class ViewerHub;

struct EndpointOptions {
  std::string listen;                // host:port; port 0 takes a free port
  std::filesystem::path static_dir;  // served at / (index.html for /)
  std::filesystem::path three_dir;   // three.js' build/ folder, served at /three/
  std::filesystem::path tls_cert;    // with tls_key: https and wss only
  std::filesystem::path tls_key;
  std::size_t socket_buffer_bytes = std::size_t{1} << 20U;  // handed to the socket and not yet sent, per client
  std::size_t kernel_send_buffer_bytes = 64U << 10U;        // the kernel's send buffer of each client's socket
  std::size_t max_client_message_bytes = 64U << 10U;        // subscribe messages are small; anything larger is refused

  [[nodiscard]] Status validate() const;
};

class ViewerEndpoint {
 public:
  // Binds and starts serving on a thread of its own. The error names the address, or the TLS file, that failed.
  // `hub` and `tokens` must outlive the endpoint.
  static Result<std::unique_ptr<ViewerEndpoint>> start(ViewerHub& hub, const MissionTokens& tokens,
                                                       const EndpointOptions& options);
  ~ViewerEndpoint();  // closes every connection and stops
  ViewerEndpoint(const ViewerEndpoint&) = delete;
  ViewerEndpoint& operator=(const ViewerEndpoint&) = delete;

  [[nodiscard]] int port() const;
  [[nodiscard]] bool tls() const;

  struct Impl;

 private:
  explicit ViewerEndpoint(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::server::viewer
