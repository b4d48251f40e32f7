// Drives an AgentSession as the link adapter does, without gRPC: one message in, its status out, and the reply it
// made at once (the Welcome) when the caller wants it. Shared by the session, admission, store and reuse tests.
#pragma once

#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/ingest/agent_session.hpp"

namespace cvislam::server::test {

inline Status sendTo(AgentSession& session, const v1::AgentUplink& message, v1::ServerDownlink* reply = nullptr,
                     bool* reply_due = nullptr) {
  v1::ServerDownlink unused_reply;
  bool unused_due = false;
  v1::ServerDownlink& out = reply != nullptr ? *reply : unused_reply;
  out.Clear();
  return session.handle(message, message.ByteSizeLong(), out, reply_due != nullptr ? *reply_due : unused_due);
}

}  // namespace cvislam::server::test
