// The agent's end of the link stream, over gRPC. One stream at a time; a reader thread keeps a Read pending so
// that acknowledgements arrive while the link thread writes (and so that gRPC notices a broken connection).
// gRPC headers stay in link_client.cpp.
//
// Scale-out: `server` may list several replicas ("a:50051,b:50051"). A replica that does not serve the mission
// refuses the Hello and names the one that does (trailing metadata, wire::kOwnerMetadataKey); connect() goes
// there at once. When a replica cannot be reached the next connect() tries the next one in the list.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::v1 {
class AgentUplink;
class ServerDownlink;
}  // namespace cvislam::v1

namespace cvislam::agent {

struct LinkClientOptions {
  std::string server;  // host:port, or several, comma-separated (replicas)
  int keepalive_ms = 1000;
  int keepalive_timeout_ms = 5000;
  std::chrono::milliseconds connect_timeout{1000};
  std::size_t max_message_bytes = 16U << 20U;
  std::string token;         // the mission's token, sent as "authorization: Bearer <token>"; empty: none
  std::string tls_root_pem;  // PEM of the CA that signed the server's certificate; empty: plaintext
};

class LinkClient {
 public:
  explicit LinkClient(const LinkClientOptions& options);
  ~LinkClient();
  LinkClient(const LinkClient&) = delete;
  LinkClient& operator=(const LinkClient&) = delete;

  // Opens a stream, sends `hello` and waits for the server's first message (the Welcome), which it returns.
  // Fails, with the server's own reason when it gave one, when the server is unreachable or refuses.
  Result<std::unique_ptr<v1::ServerDownlink>> connect(const v1::AgentUplink& hello);

  [[nodiscard]] bool connected() const;
  // Writes one message; false when the stream broke (the client is then disconnected: call connect again).
  bool send(const v1::AgentUplink& message);
  // The next message from the server, if one has arrived; never blocks.
  bool poll(v1::ServerDownlink& out);
  // Half-closes the stream and waits up to `timeout` for the server to end it; returns the final status.
  Status close(std::chrono::milliseconds timeout);
  // Ends the stream without a half-close (for a server that is away or not reading).
  void abandon();
  // Safe from any thread: cancels the open stream, so that a blocked write returns false.
  void cancel();
  // Why the last stream ended ("" while it is open).
  [[nodiscard]] std::string lastError() const;
  // The replica the last connect() reached (or tried last).
  [[nodiscard]] std::string target() const;
  // Redirects followed so far.
  [[nodiscard]] std::uint64_t redirects() const;

  struct Impl;

 private:
  Result<std::unique_ptr<v1::ServerDownlink>> connectTo(const std::string& address, const v1::AgentUplink& hello);
  std::unique_ptr<Impl> impl_;
};

// "a:1,b:2" -> {"a:1", "b:2"} (empty entries dropped).
std::vector<std::string> splitServerList(const std::string& servers);

}  // namespace cvislam::agent
