// GrpcServer over real loopback gRPC (port 0): health, Hello/Welcome, acknowledgements, statistics, and hostile
// inputs that each end their own stream with the right status while a second, well-behaved agent connected at
// the same time keeps being served and keeps everything it had. Every client call has a deadline.
#include "server_cloud/service/grpc_server.hpp"

#include <array>
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.grpc.pb.h"
#include "cvislam/v1/monitor.grpc.pb.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/store/sqlite_store.hpp"
#include "test/server_cloud/backend_corrections.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/store/faulty_stores.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using test::batchMessage;
using test::helloMessage;
using test::makeKeyframeBatch;
using ::testing::AllOf;
using ::testing::HasSubstr;

const std::string kMission = "loopback";
constexpr std::uint32_t kGoodAgent = 1;
constexpr std::uint32_t kHostileAgent = 2;
constexpr std::uint64_t kGoodSession = 0xa11ce;
constexpr std::uint64_t kHostileSession = 0xbad;
constexpr auto kCallDeadline = std::chrono::seconds(20);

std::chrono::system_clock::time_point deadline() {
  return std::chrono::system_clock::now() + kCallDeadline;
}

// One agent's link stream through the generated stub (sync API).
class AgentClient {
 public:
  explicit AgentClient(const std::shared_ptr<grpc::Channel>& channel) : stub_(v1::AgentLink::NewStub(channel)) {
    context_.set_deadline(deadline());
    stream_ = stub_->Connect(&context_);
  }

  bool write(const v1::AgentUplink& message) { return stream_->Write(message); }

  // Hello, then the Welcome; nothing when the stream ended instead.
  std::optional<v1::Welcome> greet(std::uint32_t agent_id, std::uint64_t session) {
    if (!write(helloMessage(kMission, agent_id, session))) return std::nullopt;
    v1::ServerDownlink down;
    if (!stream_->Read(&down) || !down.has_welcome()) return std::nullopt;
    return down.welcome();
  }

  // Sends the batch and reads downlinks until one acknowledges it; false when the stream ends first.
  bool sendAndAwaitAck(const v1::MapBatch& batch) {
    if (!write(batchMessage(batch))) return false;
    v1::ServerDownlink down;
    while (stream_->Read(&down)) {
      if (down.acked_sequence() >= batch.sequence()) return true;
    }
    return false;
  }

  // After the server ended the stream: drain what is left, then its status.
  grpc::Status awaitEnd() {
    v1::ServerDownlink down;
    while (stream_->Read(&down)) {
    }
    return stream_->Finish();
  }

  // The agent vanishes: its side of the stream is cancelled.
  void cancel() { context_.TryCancel(); }

  // The agent ends the stream itself.
  grpc::Status close() {
    stream_->WritesDone();
    return awaitEnd();
  }

 private:
  std::unique_ptr<v1::AgentLink::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::AgentUplink, v1::ServerDownlink>> stream_;
};

class GrpcServerTest : public ::testing::Test {
 protected:
  static ServerOptions defaultOptions() {
    ServerOptions o;
    o.listen = "127.0.0.1:0";
    o.session.downlink_rate_hz = 20.0;  // acknowledgements within 50 ms, so the tests wait little
    return o;
  }

  void start(const ServerOptions& options = defaultOptions(), std::unique_ptr<MapStore> store = nullptr) {
    core_ = std::make_unique<ServerCore>(options);
    if (store) {
      ASSERT_TRUE(core_->attachStore(std::move(store)).ok());
    }
    auto started = GrpcServer::start(*core_);
    ASSERT_TRUE(started.ok()) << started.error().toString();
    server_ = std::move(started).value();
    ASSERT_GT(server_->port(), 0);
    channel_ = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
  }

  void TearDown() override {
    if (server_) server_->shutdown(std::chrono::milliseconds(500));
  }

  v1::ServerStats stats() {
    auto stub = v1::Monitor::NewStub(channel_);
    grpc::ClientContext context;
    context.set_deadline(deadline());
    v1::GetStatsRequest request;
    request.set_mission(kMission);
    v1::ServerStats out;
    const grpc::Status status = stub->GetStats(&context, request, &out);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return out;
  }
  std::optional<v1::AgentStats> agentStats(std::uint32_t agent_id) {
    const v1::ServerStats all = stats();
    for (const auto& a : all.agents()) {
      if (a.agent_id() == agent_id) return a;
    }
    return std::nullopt;
  }

  // The well-behaved agent: connected, with batches 1 and 2 (keyframes 0-3) stored and acknowledged.
  void connectGoodAgent() {
    good_ = std::make_unique<AgentClient>(channel_);
    ASSERT_TRUE(good_->greet(kGoodAgent, kGoodSession).has_value());
    ASSERT_TRUE(good_->sendAndAwaitAck(makeKeyframeBatch(1, 0, 2)));
    ASSERT_TRUE(good_->sendAndAwaitAck(makeKeyframeBatch(2, 2, 2)));
  }

  // The good agent still has all it had (4 keyframes, sequence 2), is still connected, and its next batch is
  // stored and acknowledged.
  void expectGoodAgentUntouchedAndServed() {
    auto before = agentStats(kGoodAgent);
    ASSERT_TRUE(before.has_value());
    EXPECT_TRUE(before->connected());
    EXPECT_EQ(before->keyframes(), 4U);
    EXPECT_EQ(before->points(), 4U);
    EXPECT_EQ(before->stored_sequence(), 2U);
    EXPECT_EQ(before->refused_messages(), 0U);
    ASSERT_TRUE(good_->sendAndAwaitAck(makeKeyframeBatch(3, 4, 1)));
    auto after = agentStats(kGoodAgent);
    ASSERT_TRUE(after.has_value());
    EXPECT_EQ(after->keyframes(), 5U);
    EXPECT_EQ(after->stored_sequence(), 3U);
    EXPECT_TRUE(good_->close().ok());
  }

  // A hostile agent's stream: greeted as kHostileAgent, then `message`; returns the status that ended it.
  grpc::Status greetThenSend(const v1::AgentUplink& message) {
    AgentClient hostile(channel_);
    EXPECT_TRUE(hostile.greet(kHostileAgent, kHostileSession).has_value());
    hostile.write(message);  // may already fail if the server ended the stream
    return hostile.awaitEnd();
  }

  // A client that reads little ahead (a small HTTP/2 window): a server write of a downlink larger than the
  // window stays in flight until the client reads.
  [[nodiscard]] std::shared_ptr<grpc::Channel> narrowWindowChannel() const {
    grpc::ChannelArguments narrow_window;
    narrow_window.SetInt(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, 1024);
    narrow_window.SetInt(GRPC_ARG_HTTP2_BDP_PROBE, 0);
    return grpc::CreateCustomChannel(server_->address(), grpc::InsecureChannelCredentials(), narrow_window);
  }

  // Greeted as kHostileAgent, with kInFlightKeyframes keyframes stored and every one of them corrected by the
  // server, so that the next downlink (~100 kB of corrections) is being written and waits for `agent` to read.
  static constexpr std::uint32_t kInFlightKeyframes = 1000;
  void startLargeDownlink(AgentClient& agent) {
    ASSERT_TRUE(agent.greet(kHostileAgent, kHostileSession).has_value());
    ASSERT_TRUE(agent.sendAndAwaitAck(makeKeyframeBatch(1, 0, kInFlightKeyframes)));
    std::vector<test::KeyframeStateChange> changes(kInFlightKeyframes);
    for (std::uint32_t c = 0; c < kInFlightKeyframes; ++c) changes[c].id = KeyframeId{kHostileAgent, c};
    const auto applied = test::correctAsTheBackend(*core_, kMission, changes);
    ASSERT_TRUE(applied.ok()) << applied.error().toString();
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // the periodic thread starts writing them
  }

  std::unique_ptr<ServerCore> core_;
  std::unique_ptr<GrpcServer> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<AgentClient> good_;
};

// ---- The endpoint serves ----

TEST_F(GrpcServerTest, HealthCheckReportsServingForTheServerAndTheAgentLink) {
  start();
  auto health = grpc::health::v1::Health::NewStub(channel_);

  grpc::health::v1::HealthCheckResponse server;
  grpc::health::v1::HealthCheckResponse link;
  grpc::ClientContext server_context;
  grpc::ClientContext link_context;
  server_context.set_deadline(deadline());
  link_context.set_deadline(deadline());
  grpc::health::v1::HealthCheckRequest request;
  const grpc::Status server_status = health->Check(&server_context, request, &server);
  request.set_service("cvislam.v1.AgentLink");
  const grpc::Status link_status = health->Check(&link_context, request, &link);

  ASSERT_TRUE(server_status.ok()) << server_status.error_message();
  EXPECT_EQ(server.status(), grpc::health::v1::HealthCheckResponse::SERVING);
  ASSERT_TRUE(link_status.ok()) << link_status.error_message();
  EXPECT_EQ(link.status(), grpc::health::v1::HealthCheckResponse::SERVING);
}

TEST_F(GrpcServerTest, HelloGetsAWelcome) {
  start();
  AgentClient sut(channel_);

  auto welcome = sut.greet(kGoodAgent, kGoodSession);

  ASSERT_TRUE(welcome.has_value());
  EXPECT_EQ(welcome->stored_sequence(), 0U);
  EXPECT_DOUBLE_EQ(welcome->downlink_rate_hz(), 20.0);
  EXPECT_TRUE(sut.close().ok());
}

TEST_F(GrpcServerTest, BatchesAreStoredAndAcknowledged) {
  start();
  AgentClient sut(channel_);
  ASSERT_TRUE(sut.greet(kGoodAgent, kGoodSession).has_value());

  const bool first = sut.sendAndAwaitAck(makeKeyframeBatch(1, 0, 2));
  const bool second = sut.sendAndAwaitAck(makeKeyframeBatch(2, 2, 3));

  EXPECT_TRUE(first);
  EXPECT_TRUE(second);
  auto stats = agentStats(kGoodAgent);
  ASSERT_TRUE(stats.has_value());
  EXPECT_EQ(stats->stored_sequence(), 2U);
  EXPECT_EQ(stats->keyframes(), 5U);
  EXPECT_EQ(stats->server_keyframes(), 5U);     // no back-end here: nothing removed as redundant
  EXPECT_EQ(stats->ingest_ms().samples(), 2U);  // one ingest time per stored batch
  EXPECT_GT(stats->ingest_ms().max(), 0.0);
  EXPECT_LE(stats->ingest_ms().p50(), stats->ingest_ms().max());
  EXPECT_TRUE(sut.close().ok());
}

TEST_F(GrpcServerTest, ReconnectIsWelcomedWithWhatTheServerStored) {
  start();
  {
    AgentClient first(channel_);
    ASSERT_TRUE(first.greet(kGoodAgent, kGoodSession).has_value());
    ASSERT_TRUE(first.sendAndAwaitAck(makeKeyframeBatch(1, 0, 2)));
    ASSERT_TRUE(first.close().ok());
  }
  AgentClient sut(channel_);

  auto welcome = sut.greet(kGoodAgent, kGoodSession);

  ASSERT_TRUE(welcome.has_value());
  EXPECT_EQ(welcome->stored_sequence(), 1U);
  EXPECT_EQ(welcome->keyframes_held(), 2U);
  EXPECT_TRUE(sut.close().ok());
}

TEST_F(GrpcServerTest, ReconnectOfTheSameProcessTakesOverItsStaleStream) {
  start();
  AgentClient stale(channel_);
  ASSERT_TRUE(stale.greet(kGoodAgent, kGoodSession).has_value());
  ASSERT_TRUE(stale.sendAndAwaitAck(makeKeyframeBatch(1, 0, 2)));
  AgentClient sut(channel_);

  auto welcome = sut.greet(kGoodAgent, kGoodSession);  // the stale stream was never closed
  const grpc::Status stale_status = stale.awaitEnd();

  ASSERT_TRUE(welcome.has_value());
  EXPECT_EQ(welcome->stored_sequence(), 1U);
  EXPECT_EQ(stale_status.error_code(), grpc::StatusCode::CANCELLED) << stale_status.error_message();
  ASSERT_TRUE(sut.sendAndAwaitAck(makeKeyframeBatch(2, 2, 1)));
  auto stats = agentStats(kGoodAgent);
  ASSERT_TRUE(stats.has_value());
  EXPECT_TRUE(stats->connected());
  EXPECT_EQ(stats->connections(), 2U);
  EXPECT_EQ(stats->keyframes(), 3U);
  EXPECT_TRUE(sut.close().ok());
}

TEST_F(GrpcServerTest, GetStatsReportsKeyframesAndBytesByKind) {
  start();
  AgentClient sut(channel_);
  ASSERT_TRUE(sut.greet(kGoodAgent, kGoodSession).has_value());
  const v1::MapBatch batch = makeKeyframeBatch(1, 0, 3);
  std::uint64_t keyframe_bytes = 0;
  for (const auto& k : batch.keyframes()) keyframe_bytes += k.ByteSizeLong();
  std::uint64_t point_bytes = 0;
  for (const auto& p : batch.points()) point_bytes += p.ByteSizeLong();
  ASSERT_TRUE(sut.sendAndAwaitAck(batch));

  const v1::ServerStats out = stats();

  ASSERT_EQ(out.agents_size(), 1);
  const v1::AgentStats& a = out.agents(0);
  EXPECT_EQ(a.mission(), kMission);
  EXPECT_EQ(a.agent_id(), kGoodAgent);
  EXPECT_TRUE(a.connected());
  EXPECT_EQ(a.keyframes(), 3U);
  EXPECT_EQ(a.points(), 3U);
  EXPECT_EQ(a.maps(), 1U);
  ASSERT_EQ(a.up().count("keyframe"), 1U);
  EXPECT_EQ(a.up().at("keyframe").messages(), 3U);
  EXPECT_EQ(a.up().at("keyframe").bytes(), keyframe_bytes);
  EXPECT_EQ(a.up().at("point").bytes(), point_bytes);
  EXPECT_EQ(a.up().at("batch").bytes(), batchMessage(batch).ByteSizeLong());
  EXPECT_EQ(a.up().at("hello").messages(), 1U);
  EXPECT_EQ(a.up().at("message").messages(), 2U);
  ASSERT_EQ(a.down().count("welcome"), 1U);
  EXPECT_GT(a.down().at("welcome").bytes(), 0U);
  EXPECT_GE(a.down().at("message").messages(), 2U);  // the Welcome and at least one acknowledgement
  ASSERT_EQ(out.maps_size(), 1);
  EXPECT_EQ(out.maps(0).keyframes(), 3U);
  EXPECT_EQ(out.maps(0).covisibility_edges(), 2U);
  EXPECT_TRUE(sut.close().ok());
}

// ---- Hostile inputs: each ends its own stream; the good agent is served throughout ----

// Bytes that do not parse as an AgentUplink: the link's reactor reads raw bytes and parses them itself, so it can
// refuse them (a typed reactor would hear them like the client closing its side, and end with OK).
TEST_F(GrpcServerTest, MalformedBytesEndTheStreamAsInvalidArgumentAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  grpc::GenericStub generic(channel_);
  grpc::CompletionQueue cq;
  grpc::ClientContext context;
  context.set_deadline(deadline());
  // One operation at a time: start it, then wait for its completion. The tags are the steps' addresses.
  enum Step { kStart, kWrite, kRead, kFinish };
  std::array<Step, 4> steps = {kStart, kWrite, kRead, kFinish};
  const auto await = [&cq, &steps](Step step) {
    void* tag = nullptr;
    bool ok = false;
    EXPECT_TRUE(cq.Next(&tag, &ok));
    EXPECT_EQ(tag, &steps[step]);
    return ok;
  };
  // Field 1 (hello), length-delimited, says 200 bytes follow; 3 do.
  const std::string garbage("\x0a\xc8\x01\xff\xff\xff", 6);
  grpc::Slice slice(garbage);
  grpc::ByteBuffer request(&slice, 1);
  grpc::ByteBuffer response;
  grpc::Status status;

  auto call = generic.PrepareCall(&context, "/cvislam.v1.AgentLink/Connect", &cq);
  call->StartCall(&steps[kStart]);
  ASSERT_TRUE(await(kStart));
  call->Write(request, &steps[kWrite]);
  await(kWrite);
  call->Read(&response, &steps[kRead]);
  const bool got_a_reply = await(kRead);
  call->Finish(&status, &steps[kFinish]);
  ASSERT_TRUE(await(kFinish));
  cq.Shutdown();
  void* tag = nullptr;
  bool ok = false;
  while (cq.Next(&tag, &ok)) {
  }

  EXPECT_FALSE(got_a_reply);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_THAT(status.error_message(), ::testing::HasSubstr("6 bytes that does not parse as cvislam.v1.AgentUplink"));
  EXPECT_EQ(stats().agents_size(), 1);  // nothing was registered for the garbage
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, OversizedMessageEndsTheStreamAsResourceExhaustedAndTheOtherAgentIsServed) {
  ServerOptions options = defaultOptions();
  options.max_message_bytes = 64U << 10U;  // the smallest the options allow
  start(options);
  connectGoodAgent();
  const v1::AgentUplink oversized = batchMessage(makeKeyframeBatch(1, 0, 40));
  ASSERT_GT(oversized.ByteSizeLong(), options.max_message_bytes);

  const grpc::Status status = greetThenSend(oversized);

  EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << status.error_message();
  EXPECT_THAT(status.error_message(), HasSubstr("larger than max"));
  auto hostile = agentStats(kHostileAgent);
  ASSERT_TRUE(hostile.has_value());
  EXPECT_EQ(hostile->keyframes(), 0U);
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, NaNValuesEndTheStreamAsInvalidArgumentAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  v1::MapBatch batch = makeKeyframeBatch(1, 0, 2);
  batch.mutable_keyframes(1)->mutable_state()->set_v_w(0, std::numeric_limits<float>::quiet_NaN());

  const grpc::Status status = greetThenSend(batchMessage(batch));

  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_THAT(status.error_message(), AllOf(HasSubstr("keyframe 2:1 v_w"), HasSubstr("non-finite")));
  auto hostile = agentStats(kHostileAgent);
  ASSERT_TRUE(hostile.has_value());
  EXPECT_EQ(hostile->keyframes(), 0U);  // the batch's valid keyframe 0 was not stored either
  EXPECT_EQ(hostile->refused_messages(), 1U);
  EXPECT_THAT(hostile->last_error(), HasSubstr("non-finite"));
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, UpdateOfAnUnknownKeyframeEndsTheStreamAsInvalidArgumentAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  v1::MapBatch batch;
  batch.set_sequence(1);
  *batch.add_keyframe_updates() = test::makeState(3);  // the good agent's keyframe 3, not this agent's

  const grpc::Status status = greetThenSend(batchMessage(batch));

  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_THAT(status.error_message(),
              HasSubstr("update of keyframe 2:3 refers to keyframe 2:3, which the server never received"));
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, PointOfAnUnknownKeyframeEndsTheStreamAsInvalidArgumentAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  v1::MapBatch batch;
  batch.set_sequence(1);
  *batch.add_points() = test::makePoint(0, 1);  // keyframe 1 of this agent was never sent

  const grpc::Status status = greetThenSend(batchMessage(batch));

  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_THAT(status.error_message(),
              HasSubstr("map point 2:0 refers to keyframe 2:1, which the server never received"));
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, SequenceGoingBackEndsTheStreamAsInvalidArgumentAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  AgentClient hostile(channel_);
  ASSERT_TRUE(hostile.greet(kHostileAgent, kHostileSession).has_value());
  ASSERT_TRUE(hostile.sendAndAwaitAck(makeKeyframeBatch(1, 0, 1)));
  ASSERT_TRUE(hostile.sendAndAwaitAck(makeKeyframeBatch(2, 1, 1)));

  hostile.write(batchMessage(makeKeyframeBatch(1, 0, 1)));
  const grpc::Status status = hostile.awaitEnd();

  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_THAT(status.error_message(), HasSubstr("batch sequence went back from 2 to 1"));
  auto stats = agentStats(kHostileAgent);
  ASSERT_TRUE(stats.has_value());
  EXPECT_EQ(stats->stored_sequence(), 2U);  // what it stored before stays
  EXPECT_EQ(stats->keyframes(), 2U);
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, SecondProcessClaimingAConnectedAgentIdEndsAsAlreadyExistsAndTheFirstIsServed) {
  start();
  connectGoodAgent();
  AgentClient intruder(channel_);

  const bool welcomed = intruder.greet(kGoodAgent, kHostileSession).has_value();
  const grpc::Status status = intruder.awaitEnd();

  EXPECT_FALSE(welcomed);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::ALREADY_EXISTS) << status.error_message();
  EXPECT_THAT(status.error_message(), AllOf(HasSubstr("agent 1 of mission 'loopback'"), HasSubstr("another process")));
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, HelloOfAnotherProtocolVersionEndsAsFailedPreconditionAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  AgentClient old_agent(channel_);
  v1::AgentUplink hello = helloMessage(kMission, kHostileAgent, kHostileSession);
  hello.mutable_hello()->set_protocol_version(0);

  old_agent.write(hello);
  const grpc::Status status = old_agent.awaitEnd();

  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << status.error_message();
  EXPECT_THAT(status.error_message(), HasSubstr("protocol version 0 is not supported"));
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, BatchBeforeHelloEndsAsFailedPreconditionAndTheOtherAgentIsServed) {
  start();
  connectGoodAgent();
  AgentClient rude(channel_);

  rude.write(batchMessage(makeKeyframeBatch(1, 0, 1)));
  const grpc::Status status = rude.awaitEnd();

  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << status.error_message();
  EXPECT_THAT(status.error_message(), HasSubstr("must be a Hello"));
  expectGoodAgentUntouchedAndServed();
}

TEST_F(GrpcServerTest, ErrorWhileADownlinkIsInFlightEndsTheStreamWithItsMessageIntact) {
  // The error arrives while a write is pending, so the status goes out only after that write completes.
  start();
  AgentClient sut(narrowWindowChannel());
  startLargeDownlink(sut);

  sut.write(batchMessage(makeKeyframeBatch(1, 0, 1)));          // sequence 1 again on this stream
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // refused while the write is pending
  const grpc::Status status = sut.awaitEnd();

  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message(), "batch sequence 1 sent twice on one stream");
}

TEST_F(GrpcServerTest, AgentVanishingWhileADownlinkIsInFlightIsDisconnectedAndCanComeBack) {
  start();
  AgentClient vanishing(narrowWindowChannel());
  startLargeDownlink(vanishing);

  vanishing.cancel();
  EXPECT_EQ(vanishing.awaitEnd().error_code(), grpc::StatusCode::CANCELLED);

  // The server notices: the agent is no longer connected (its stream ended on the server too)...
  bool connected = true;
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (connected && std::chrono::steady_clock::now() < give_up) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    connected = agentStats(kHostileAgent)->connected();
  }
  EXPECT_FALSE(connected);
  // ...so the same process coming back is welcomed with what it stored, and another process claiming the agent is
  // refused because its ids would clash (FAILED_PRECONDITION), not as a second live process (ALREADY_EXISTS).
  AgentClient restarted(channel_);
  EXPECT_FALSE(restarted.greet(kHostileAgent, kHostileSession + 1).has_value());
  EXPECT_EQ(restarted.awaitEnd().error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  AgentClient back(channel_);
  auto welcome = back.greet(kHostileAgent, kHostileSession);
  ASSERT_TRUE(welcome.has_value());
  EXPECT_EQ(welcome->stored_sequence(), 1U);
  EXPECT_TRUE(back.close().ok());
}

TEST_F(GrpcServerTest, AgentVanishingAfterARefusalWhileADownlinkIsInFlightIsDisconnected) {
  // The refusal waits for the pending write; the agent goes before reading it, so that write fails.
  start();
  AgentClient vanishing(narrowWindowChannel());
  startLargeDownlink(vanishing);
  vanishing.write(batchMessage(makeKeyframeBatch(1, 0, 1)));    // refused: sequence 1 again
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // refused while the write is pending

  vanishing.cancel();
  EXPECT_EQ(vanishing.awaitEnd().error_code(), grpc::StatusCode::CANCELLED);

  bool connected = true;
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (connected && std::chrono::steady_clock::now() < give_up) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    connected = agentStats(kHostileAgent)->connected();
  }
  EXPECT_FALSE(connected);
  AgentClient restarted(channel_);
  EXPECT_FALSE(restarted.greet(kHostileAgent, kHostileSession + 1).has_value());
  EXPECT_EQ(restarted.awaitEnd().error_code(), grpc::StatusCode::FAILED_PRECONDITION);  // not ALREADY_EXISTS
}

// A store whose appends of one agent take 2 s (its disk or database connection stalls): that agent's stream waits,
// and nobody else does. The other agent's batches are acknowledged as usual, and a new stream is welcomed.
class SlowAgentStore final : public test::ForwardingStore {
 public:
  SlowAgentStore(std::unique_ptr<MapStore> inner, std::uint32_t slow_agent)
      : ForwardingStore(std::move(inner)), slow_agent_(slow_agent) {}
  Status append(const StoreRecord& r) override {
    if (r.kind == StoreRecord::Kind::kBatch && r.agent == slow_agent_) {
      std::this_thread::sleep_for(std::chrono::seconds(2));
    }
    return ForwardingStore::append(r);
  }

 private:
  std::uint32_t slow_agent_;
};

TEST_F(GrpcServerTest, ASlowAppendOfOneAgentDelaysNoOtherAgentsAcknowledgementsNorNewStreams) {
  cvislam::test::TempDir dir;
  SqliteStoreOptions o;
  o.path = dir.path() / "maps.db";
  o.sync = SqliteStoreOptions::Sync::kOff;
  auto sqlite = openSqliteStore(o);
  ASSERT_TRUE(sqlite.ok()) << sqlite.error().toString();
  start(defaultOptions(), std::make_unique<SlowAgentStore>(std::move(sqlite).value(), kHostileAgent));
  AgentClient good(channel_);
  AgentClient slow(channel_);
  ASSERT_TRUE(good.greet(kGoodAgent, kGoodSession).has_value());
  ASSERT_TRUE(slow.greet(kHostileAgent, kHostileSession).has_value());
  ASSERT_TRUE(good.sendAndAwaitAck(makeKeyframeBatch(1, 0, 2)));

  ASSERT_TRUE(slow.write(batchMessage(makeKeyframeBatch(1, 0, 2))));  // its append now takes 2 s
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const auto start = std::chrono::steady_clock::now();
  ASSERT_TRUE(good.sendAndAwaitAck(makeKeyframeBatch(2, 2, 2)));
  const double acked_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  AgentClient newcomer(channel_);
  ASSERT_TRUE(newcomer.greet(7, 0x7777).has_value());
  const double welcomed_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  EXPECT_LT(acked_s, 1.0) << "the good agent's acknowledgement waited for the slow agent's append";
  EXPECT_LT(welcomed_s, 1.0) << "a new stream waited for the slow agent's append";
  EXPECT_TRUE(slow.sendAndAwaitAck(makeKeyframeBatch(2, 2, 2)));  // the slow agent is served in the end
}

// Streams that never send a Hello are ended after hello_timeout_s, and stop counting against their address.
TEST_F(GrpcServerTest, StreamsWithoutAHelloAreEndedAfterTheHelloTimeout) {
  ServerOptions options = defaultOptions();
  options.session.hello_timeout_s = 0.5;
  start(options);
  std::vector<std::unique_ptr<AgentClient>> silent;
  for (int i = 0; i < 20; ++i) silent.push_back(std::make_unique<AgentClient>(channel_));
  for (auto& client : silent) {
    const grpc::Status status = client->awaitEnd();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
    EXPECT_THAT(status.error_message(), HasSubstr("no Hello within 0.5 s"));
  }
  for (int i = 0; i < 100 && core_->streamLimits().openStreams() > 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_EQ(core_->streamLimits().openStreams(), 0U);
  AgentClient agent(channel_);  // and a real agent is still welcome
  EXPECT_TRUE(agent.greet(kGoodAgent, kGoodSession).has_value());
}

// One address may hold only so many streams at once; one more is refused, and a closed one frees its place.
TEST_F(GrpcServerTest, StreamsBeyondTheLimitPerAddressAreRefusedAsResourceExhausted) {
  ServerOptions options = defaultOptions();
  options.stream_limits.per_address = 4;
  start(options);
  std::vector<std::unique_ptr<AgentClient>> agents;
  for (std::uint32_t id = 1; id <= 4; ++id) {
    agents.push_back(std::make_unique<AgentClient>(channel_));
    ASSERT_TRUE(agents.back()->greet(id, 0x1000 + id).has_value()) << "agent " << id;
  }
  AgentClient fifth(channel_);
  EXPECT_FALSE(fifth.greet(5, 0x1005).has_value());
  const grpc::Status refused = fifth.awaitEnd();
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(refused.error_message(), HasSubstr("limits.max_streams_per_address"));
  EXPECT_TRUE(agents.back()->close().ok());
  agents.pop_back();
  for (int i = 0; i < 100 && core_->streamLimits().openStreams() > 3; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  AgentClient again(channel_);
  EXPECT_TRUE(again.greet(4, 0x1004).has_value());
}

TEST_F(GrpcServerTest, StartOnAPortInUseFailsNamingTheAddress) {
  start();
  ServerOptions taken = defaultOptions();
  taken.listen = server_->address();
  ServerCore second_core(taken);

  auto second = GrpcServer::start(second_core);

  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.error().code(), ErrorCode::kUnavailable);
  EXPECT_THAT(second.error().message(), HasSubstr("cannot listen on " + server_->address()));
}

TEST_F(GrpcServerTest, ShutdownEndsOpenStreamsAndTheAgentIsNoLongerConnected) {
  start();
  AgentClient agent(channel_);
  ASSERT_TRUE(agent.greet(kGoodAgent, kGoodSession).has_value());
  ASSERT_TRUE(agent.sendAndAwaitAck(makeKeyframeBatch(1, 0, 2)));

  server_->shutdown(std::chrono::milliseconds(200));
  const grpc::Status status = agent.awaitEnd();

  EXPECT_FALSE(status.ok());
  v1::ServerStats after;
  core_->fillStats(kMission, after);
  ASSERT_EQ(after.agents_size(), 1);
  EXPECT_FALSE(after.agents(0).connected());
  EXPECT_EQ(after.agents(0).keyframes(), 2U);
}

// ---- Outputs ----

TEST_F(GrpcServerTest, WriteOutputsAfterShutdownWritesOneLinePerKeyframe) {
  start();
  AgentClient agent(channel_);
  ASSERT_TRUE(agent.greet(kGoodAgent, kGoodSession).has_value());
  ASSERT_TRUE(agent.sendAndAwaitAck(makeKeyframeBatch(1, 0, 3)));
  ASSERT_TRUE(agent.sendAndAwaitAck(makeKeyframeBatch(2, 3, 2)));
  ASSERT_TRUE(agent.close().ok());
  server_->shutdown(std::chrono::milliseconds(500));
  const cvislam::test::TempDir dir;

  const Status written = core_->writeOutputs(dir.path());

  ASSERT_TRUE(written.ok()) << written.error().toString();
  std::ifstream file(dir.path() / kMission / "keyframes_agent1.txt");
  ASSERT_TRUE(file.good());
  std::vector<std::pair<double, double>> rows;  // time [s], x
  for (std::string line; std::getline(file, line);) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream fields(line);
    double t_s = 0;
    double x = 0;
    fields >> t_s >> x;
    ASSERT_FALSE(fields.fail()) << line;
    rows.emplace_back(t_s, x);
  }
  ASSERT_EQ(rows.size(), 5U);
  for (std::uint32_t c = 0; c < 5; ++c) {  // in time order, at the times and places they were sent
    EXPECT_NEAR(rows[c].first, static_cast<double>(test::keyframeTime(c)) * 1e-9, 1e-9) << c;
    EXPECT_NEAR(rows[c].second, test::makeState(c).t_w_s().px(), 1e-9) << c;
  }
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "stats.json"));
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "timeline.csv"));
}

}  // namespace
}  // namespace cvislam::server
