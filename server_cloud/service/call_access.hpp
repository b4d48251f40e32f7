// What a call presented, read from its gRPC context for the access checks of ServerCore: the bearer token and a
// key naming the client for the rate limit. Only service/ includes it (gRPC headers).
#pragma once

#include <cstdint>
#include <cstdio>
#include <string>

#include <grpcpp/server_context.h>

#include "common/core/hash.hpp"
#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/core/server_core.hpp"

namespace cvislam::server {

// The bearer token of the call's "authorization" metadata; "" when it has none.
inline std::string presentedToken(const grpc::CallbackServerContext& context) {
  const auto& metadata = context.client_metadata();
  const auto it = metadata.find("authorization");
  if (it == metadata.end()) return {};
  return std::string(bearerToken(std::string_view(it->second.data(), it->second.size())));
}

// The client for the rate limit: the peer's address without its port (a client that reconnects keeps its
// budget) and a fingerprint of its token (clients behind one address with different missions are apart). The
// token itself never appears: the key goes into error messages.
inline std::string clientKey(const grpc::CallbackServerContext& context, const std::string& token) {
  std::string peer = context.peer();  // "ipv4:127.0.0.1:52814", "ipv6:[::1]:52814"
  if (const auto colon = peer.rfind(':'); colon != std::string::npos && colon > peer.find(':')) peer.resize(colon);
  if (token.empty()) return peer + " (no token)";
  char fingerprint[16];
  std::snprintf(fingerprint, sizeof(fingerprint), "%08x", static_cast<std::uint32_t>(fnv1a64(token)));
  return peer + " (token #" + fingerprint + ")";
}

// The rate limit, then the mission's token (`token`: presentedToken(context)): the status the call is refused
// with, or OK.
inline Status admitCall(ServerCore& core, const grpc::CallbackServerContext& context, const std::string& token,
                        const std::string& mission, const std::string& what) {
  if (Status s = core.admitRequest(clientKey(context, token), what); !s.ok()) return s;
  if (mission.empty()) return Status::Ok();
  return core.tokens().authorize(mission, token);
}
inline Status admitCall(ServerCore& core, const grpc::CallbackServerContext& context, const std::string& mission,
                        const std::string& what) {
  return admitCall(core, context, presentedToken(context), mission, what);
}

}  // namespace cvislam::server
