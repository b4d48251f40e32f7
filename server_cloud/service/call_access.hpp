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

// The peer's address without its port ("ipv4:127.0.0.1" of "ipv4:127.0.0.1:52814"): a client that reconnects
// stays the same client.
inline std::string peerAddress(const grpc::CallbackServerContext& context) {
  std::string peer = context.peer();  // "ipv4:127.0.0.1:52814", "ipv6:[::1]:52814"
  if (const auto colon = peer.rfind(':'); colon != std::string::npos && colon > peer.find(':')) peer.resize(colon);
  return peer;
}

// The client for the rate limit once its token is known to be good: its address and a fingerprint of the token
// (clients behind one address with different missions are apart). The token itself never appears: the key goes
// into error messages.
inline std::string clientKey(const grpc::CallbackServerContext& context, const std::string& token) {
  const std::string peer = peerAddress(context);
  if (token.empty()) return peer + " (no token)";
  char fingerprint[16];
  std::snprintf(fingerprint, sizeof(fingerprint), "%08x", static_cast<std::uint32_t>(fnv1a64(token)));
  return peer + " (token #" + fingerprint + ")";
}

// The client for the rate limit while nothing it presented is known to be good (a stream before its Hello, a
// token that opens nothing): its address alone. Keyed by the token too, every made-up token would get a full
// bucket of its own.
inline std::string unauthenticatedKey(const grpc::CallbackServerContext& context) {
  return peerAddress(context) + " (unauthenticated)";
}

// The mission's token (`token`: presentedToken(context)), then the rate limit: the status the call is refused
// with, or OK. A call whose token does not open its mission is charged to its address alone, and refused; so is
// a call that names no mission with a token that opens nothing (calls without a token on a server without tokens
// count as the address's too).
inline Status admitCall(ServerCore& core, const grpc::CallbackServerContext& context, const std::string& token,
                        const std::string& mission, const std::string& what) {
  const MissionTokens& tokens = core.tokens();
  if (!mission.empty()) {
    if (Status authorized = tokens.authorize(mission, token); !authorized.ok()) {
      if (Status s = core.admitRequest(unauthenticatedKey(context), what); !s.ok()) return s;
      return authorized;
    }
    return core.admitRequest(clientKey(context, token), what);
  }
  const bool known = tokens.enabled() && tokens.opensAny(token);
  return core.admitRequest(known ? clientKey(context, token) : unauthenticatedKey(context), what);
}
inline Status admitCall(ServerCore& core, const grpc::CallbackServerContext& context, const std::string& mission,
                        const std::string& what) {
  return admitCall(core, context, presentedToken(context), mission, what);
}

}  // namespace cvislam::server
