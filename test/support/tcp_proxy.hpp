// A TCP forwarder on loopback that a test can cut: every connection to it is joined to the target port, and
// cutAll() closes all of them at once while the target lives on (a network that drops the agent's stream).
#pragma once

#include <atomic>
#include <mutex>
#include <thread>
#include <vector>

namespace cvislam::test {

class TcpProxy {
 public:
  // Listens on 127.0.0.1 (a free port) and forwards to 127.0.0.1:target_port. port() is -1 if it could not listen.
  explicit TcpProxy(int target_port);
  ~TcpProxy();
  TcpProxy(const TcpProxy&) = delete;
  TcpProxy& operator=(const TcpProxy&) = delete;

  [[nodiscard]] int port() const { return port_; }
  // Closes every open connection (both sides); new connections are accepted as before.
  void cutAll();
  [[nodiscard]] int connectionsAccepted() const { return accepted_.load(); }

 private:
  void run();

  int target_port_;
  int listen_fd_ = -1;
  int port_ = -1;
  std::atomic<bool> stop_{false};
  std::atomic<bool> cut_{false};
  std::atomic<int> accepted_{0};
  std::thread thread_;
};

}  // namespace cvislam::test
