// Fuzzes what an agent sends: bytes from the network, parsed as cvislam.v1.AgentUplink (as the link adapter
// does) and handed to a fresh AgentSession (over a fresh registry, with a mission token and small limits), message
// after message, so the protocol's state machine, the Hello's checks and batch ingest's validation all see hostile
// input. The input is a sequence of framed messages (fuzz_target.hpp); its first byte's low bit puts a valid Hello
// first, so that mutated batches get past the greeting.
#include <memory>

#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/ingest/agent_session.hpp"
#include "server_cloud/stack/map_stack.hpp"
#include "test/fuzz/fuzz_target.hpp"
#include "test/server_cloud/link_messages.hpp"

namespace {

using namespace cvislam;

const char* const kToken = "fuzz-mission-token-0001";

server::SessionOptions options() {
  server::SessionOptions o;
  o.max_missions = 4;
  o.max_agents_per_mission = 4;
  o.ingest.max_keypoints_per_keyframe = 512;
  o.ingest.max_imu_samples_per_keyframe = 512;
  o.ingest.max_maps_per_agent = 8;
  return o;
}

const server::MissionTokens& tokens() {
  static const server::MissionTokens parsed = [] {
    auto t = server::MissionTokens::parse(std::string("fuzz ") + kToken + "\n", "fuzz tokens");
    if (!t) __builtin_trap();
    return std::move(t).value();
  }();
  return parsed;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const bool greet_first = (data[0] & 1U) != 0;
  auto parts = fuzz::frames(data + 1, size - 1, 64);

  server::MissionRegistry missions;
  auto session = std::make_unique<server::AgentSession>(missions, options(), std::function<void()>{},
                                                        server::AgentSession::StoredListener{}, nullptr,
                                                        server::SessionCredentials{&tokens(), kToken});

  v1::AgentUplink message;
  v1::ServerDownlink reply;
  bool reply_due = false;
  if (greet_first) {
    const v1::AgentUplink hello = server::test::helloMessage("fuzz", 3, 77);
    if (!session->handle(hello, hello.ByteSizeLong(), reply, reply_due).ok()) __builtin_trap();
  }
  for (const std::string& part : parts) {
    if (!message.ParseFromString(part)) {
      session->countRefused(Error{ErrorCode::kInvalidArgument, "does not parse"});
      break;  // the adapter ends the stream here
    }
    reply.Clear();
    const Status s = session->handle(message, part.size(), reply, reply_due);
    if (!s.ok()) break;  // so does a refused message
    (void)session->nextDownlink(server::AgentSession::Clock::now() + std::chrono::hours(1), reply);
  }
  session->close(Status::Ok());
  return 0;
}

std::vector<std::string> cvislam::fuzz::seeds() {
  std::vector<std::string> out;
  const std::string hello = server::test::helloMessage("fuzz", 3, 77).SerializeAsString();
  const std::string stereo_hello = [] {
    v1::AgentUplink m;
    *m.mutable_hello() = server::test::makeHello("fuzz", 2, 78, true);
    return m.SerializeAsString();
  }();
  const std::string b1 = server::test::batchMessage(server::test::makeKeyframeBatch(1, 0, 2)).SerializeAsString();
  const std::string b2 = server::test::batchMessage(server::test::makeKeyframeBatch(2, 2, 3)).SerializeAsString();
  const std::string bye = server::test::goodbyeMessage(true).SerializeAsString();
  out.push_back(std::string(1, '\0') + fuzz::frame(hello) + fuzz::frame(b1) + fuzz::frame(b2) + fuzz::frame(bye));
  out.push_back(std::string(1, '\0') + fuzz::frame(stereo_hello) + fuzz::frame(b1));
  out.push_back(std::string(1, '\1') + fuzz::frame(b1) + fuzz::frame(b2));
  out.push_back(std::string(1, '\1') + fuzz::frame(b2) + fuzz::frame(b1) + fuzz::frame(b1));
  out.push_back(std::string(1, '\1') + fuzz::frame(hello) + fuzz::frame(b1));
  return out;
}
