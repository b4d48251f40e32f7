// AgentSession, driven directly (no gRPC): the Hello/Welcome exchange, batch sequences (in order, resent,
// going back, skipping ahead), acknowledgements at the downlink rate, reconnects and a second process claiming
// the same agent, the server's corrections sent down once, and every refusal with its code and its words.
#include "server_cloud/ingest/agent_session.hpp"

#include <chrono>
#include <cstdint>
#include <future>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <gmock/gmock.h>

#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "test/server_cloud/backend_corrections.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/session_driver.hpp"

namespace cvislam::server {
namespace {

using test::batchMessage;
using test::helloMessage;
using test::makeKeyframeBatch;
using ::testing::AllOf;
using ::testing::HasSubstr;
using Clock = AgentSession::Clock;
using std::chrono::milliseconds;

const std::string kMission = "hall-1";
constexpr std::uint32_t kAgent = 4;
constexpr std::uint64_t kSession = 0x5eed'0001;
constexpr std::uint64_t kOtherProcess = 0x5eed'0002;

class AgentSessionTest : public ::testing::Test {
 protected:
  AgentSessionTest() : core_(options()), sut(openSession()) {}

  static ServerOptions options() {
    ServerOptions o;
    o.session.downlink_rate_hz = 2.0;  // a message every 500 ms at most
    return o;
  }
  std::unique_ptr<AgentSession> openSession(int* cancelled = nullptr) {
    return core_.openSession([cancelled] {
      if (cancelled != nullptr) ++*cancelled;
    });
  }

  // Sends one message; returns its status, and the immediate reply in `reply_` when one is due.
  Status send(AgentSession& session, const v1::AgentUplink& message) {
    return test::sendTo(session, message, &reply_, &reply_due_);
  }
  void sendOk(AgentSession& session, const v1::AgentUplink& message) {
    const Status s = send(session, message);
    ASSERT_TRUE(s.ok()) << s.error().toString();
  }
  void greet(AgentSession& session, std::uint64_t process = kSession) {
    sendOk(session, helloMessage(kMission, kAgent, process));
    ASSERT_TRUE(reply_due_);
  }
  void sendBatch(AgentSession& session, std::uint64_t sequence, std::uint32_t first, std::uint32_t count) {
    sendOk(session, batchMessage(makeKeyframeBatch(sequence, first, count)));
  }

  [[nodiscard]] SharedAgentRecord record() {
    auto mission = core_.missions().find(kMission);
    EXPECT_NE(mission, nullptr);
    return mission->agent(kAgent);
  }
  [[nodiscard]] std::size_t keyframesInMaps() {
    std::size_t n = 0;
    for (const auto& map : core_.missions().find(kMission)->stack().maps()) n += map->read()->keyframes().size();
    return n;
  }
  // A time at which a periodic message is due again (the Welcome went out at about Clock::now()).
  static Clock::time_point later(int periods) { return Clock::now() + periods * milliseconds(600); }

  ServerCore core_;
  std::unique_ptr<AgentSession> sut;
  v1::ServerDownlink reply_;
  bool reply_due_ = false;
};

// ---- Hello and Welcome ----

TEST_F(AgentSessionTest, HelloIsAnsweredAtOnceWithAWelcomeOfNothingStored) {
  const Status s = send(*sut, helloMessage(kMission, kAgent, kSession));

  ASSERT_TRUE(s.ok()) << s.error().toString();
  EXPECT_TRUE(reply_due_);
  ASSERT_TRUE(reply_.has_welcome());
  EXPECT_EQ(reply_.sequence(), 1U);
  EXPECT_EQ(reply_.welcome().stored_sequence(), 0U);
  EXPECT_EQ(reply_.welcome().keyframes_held(), 0U);
  EXPECT_DOUBLE_EQ(reply_.welcome().downlink_rate_hz(), 2.0);
  EXPECT_TRUE(sut->greeted());
  EXPECT_EQ(sut->agent(), kAgent);
  auto r = record()->read();
  EXPECT_TRUE(r->connected);
  EXPECT_EQ(r->connections, 1U);
  EXPECT_EQ(r->software, "server test");
  ASSERT_TRUE(r->sensors.has_value());
  EXPECT_EQ(r->sensors->cam0.width(), 752);
}

TEST_F(AgentSessionTest, HelloWithAnotherProtocolVersionIsRefusedAsFailedPrecondition) {
  v1::AgentUplink hello = helloMessage(kMission, kAgent, kSession);
  hello.mutable_hello()->set_protocol_version(2);

  const Status s = send(*sut, hello);

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(s.error().message(), AllOf(HasSubstr("protocol version 2"), HasSubstr("speaks version 1")));
  EXPECT_FALSE(reply_due_);
  EXPECT_FALSE(sut->greeted());
  EXPECT_EQ(core_.missions().find(kMission), nullptr);
}

TEST_F(AgentSessionTest, SecondHelloOnOneStreamIsRefusedAsFailedPrecondition) {
  greet(*sut);

  const Status s = send(*sut, helloMessage(kMission, kAgent, kSession));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(s.error().message(), HasSubstr("a second Hello"));
  EXPECT_FALSE(reply_due_);
  EXPECT_EQ(record()->read()->refused_messages, 1U);
  EXPECT_THAT(record()->read()->last_error, HasSubstr("a second Hello"));
}

TEST_F(AgentSessionTest, BatchBeforeHelloIsRefusedAsFailedPrecondition) {
  const Status s = send(*sut, batchMessage(makeKeyframeBatch(1, 0, 1)));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(s.error().message(), HasSubstr("first message of a stream must be a Hello"));
  EXPECT_TRUE(core_.missions().missions().empty());
}

TEST_F(AgentSessionTest, HelloWithABadMissionNameIsRefusedNamingTheRule) {
  for (const std::string& mission : {std::string(), std::string("../etc"), std::string("two words"),
                                     std::string(129, 'a'), std::string("."), std::string("hall/1")}) {
    auto session = openSession();

    const Status s = send(*session, helloMessage(mission, kAgent, kSession));

    ASSERT_FALSE(s.ok()) << "'" << mission << "'";
    EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument) << mission;
    EXPECT_THAT(s.error().message(), HasSubstr("mission name")) << mission;
  }
  EXPECT_TRUE(core_.missions().missions().empty());
}

TEST_F(AgentSessionTest, HelloWithAnAgentIdOver16BitsIsRefused) {
  const Status s = send(*sut, helloMessage(kMission, 70000, kSession));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), HasSubstr("agent id 70000 is over 65535"));
}

TEST_F(AgentSessionTest, HelloWithoutTheCalibrationsTheSensorsNeedIsRefused) {
  v1::AgentUplink no_cam0 = helloMessage(kMission, kAgent, kSession);
  no_cam0.mutable_hello()->clear_cam0();
  v1::AgentUplink stereo_without_cam1 = helloMessage(kMission, kAgent, kSession);
  stereo_without_cam1.mutable_hello()->set_mode(v1::SENSOR_MODE_STEREO);
  v1::AgentUplink imu_without_calibration = helloMessage(kMission, kAgent, kSession);
  imu_without_calibration.mutable_hello()->clear_imu();
  v1::AgentUplink bad_quaternion = helloMessage(kMission, kAgent, kSession);
  v1::Pose& bad = *bad_quaternion.mutable_hello()->mutable_cam0()->mutable_t_s_c();
  bad.set_qx(0.0F);
  bad.set_qy(0.0F);
  bad.set_qz(0.0F);
  bad.set_qw(0.5F);  // norm 0.5

  const Status a = send(*openSession(), no_cam0);
  const Status b = send(*openSession(), stereo_without_cam1);
  const Status c = send(*openSession(), imu_without_calibration);
  const Status d = send(*openSession(), bad_quaternion);

  for (const Status* s : {&a, &b, &c, &d}) {
    ASSERT_FALSE(s->ok());
    EXPECT_EQ(s->error().code(), ErrorCode::kInvalidArgument);
  }
  EXPECT_THAT(a.error().message(), HasSubstr("no cam0 calibration"));
  EXPECT_THAT(b.error().message(), HasSubstr("stereo agent without cam1"));
  EXPECT_THAT(c.error().message(), HasSubstr("sent no IMU calibration"));
  EXPECT_THAT(d.error().message(), AllOf(HasSubstr("hello cam0 T_s_c"), HasSubstr("norm 0.5")));
}

TEST_F(AgentSessionTest, EmptyMessageIsRefused) {
  greet(*sut);

  const Status s = send(*sut, v1::AgentUplink{});

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), HasSubstr("empty message"));
}

// ---- Batches and their sequence ----

TEST_F(AgentSessionTest, BatchesInOrderAreStoredAndAcknowledgedByTheNextDownlink) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  sendBatch(*sut, 2, 2, 2);
  v1::ServerDownlink down;

  const bool sent = sut->nextDownlink(later(1), down);

  ASSERT_TRUE(sent);
  EXPECT_EQ(down.acked_sequence(), 2U);
  EXPECT_EQ(down.sequence(), 2U);  // the Welcome was 1
  EXPECT_FALSE(down.has_welcome());
  EXPECT_EQ(down.corrected_keyframes_size(), 0);
  EXPECT_EQ(record()->read()->stored_sequence, 2U);
  EXPECT_EQ(record()->read()->keyframes.size(), 4U);
  EXPECT_EQ(keyframesInMaps(), 4U);
}

TEST_F(AgentSessionTest, ConnectionsKeyframesAddedAndRemovalsGoIntoTheMissionsEventLog) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  v1::MapBatch removal;
  removal.set_sequence(2);
  removal.add_removed_keyframes(1);
  sendOk(*sut, batchMessage(removal));
  sut->close(Status::Ok());

  const auto page = core_.missions().find(kMission)->events().read(1, 100);

  ASSERT_EQ(page.events.size(), 5U);
  EXPECT_EQ(page.events[0].kind, MissionEvent::Kind::kAgentConnected);
  EXPECT_EQ(page.events[0].agent, kAgent);
  EXPECT_EQ(page.events[1].kind, MissionEvent::Kind::kKeyframeAdded);
  EXPECT_EQ(page.events[2].keyframe, (KeyframeId{kAgent, 1}));
  EXPECT_EQ(page.events[3].kind, MissionEvent::Kind::kKeyframeRemoved);
  EXPECT_EQ(page.events[3].keyframe, (KeyframeId{kAgent, 1}));
  EXPECT_EQ(page.events[3].cause, "agent");
  EXPECT_EQ(page.events[3].map, page.events[2].map);
  EXPECT_EQ(page.events[4].kind, MissionEvent::Kind::kAgentDisconnected);
}

TEST_F(AgentSessionTest, EveryStoredBatchIsTimedAndThoseThatMetAGlobalBaAlsoApart) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  core_.missions().find(kMission)->gbaStarted();  // as the back-end does from its snapshot to its result
  sendBatch(*sut, 2, 2, 2);
  sendBatch(*sut, 3, 4, 2);
  core_.missions().find(kMission)->gbaEnded();
  sendBatch(*sut, 4, 6, 2);

  const auto r = record()->read();
  EXPECT_EQ(r->ingest_ms.size(), 4U);
  EXPECT_EQ(r->ingest_during_gba_ms.size(), 2U);
  EXPECT_GT(r->ingest_during_gba_ms.percentile(1.0), 0.0);
  EXPECT_FALSE(core_.missions().find(kMission)->gbaRunning());
}

TEST_F(AgentSessionTest, ABatchThatWaitsForItsMapsLockCountsTheWaitApartFromItsCpuTime) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  auto mission = core_.missions().find(kMission);
  const std::shared_ptr<ServerMap> map = mission->stack().find(record()->read()->agent_maps.at(0).map);
  ASSERT_NE(map, nullptr);

  // Another thread (as the back-end's fusion would) holds the map's write lock while the next batch arrives.
  std::promise<void> holding;
  std::thread holder([&] {
    auto content = map->write();
    holding.set_value();
    std::this_thread::sleep_for(std::chrono::milliseconds(80));
  });
  holding.get_future().wait();
  sendBatch(*sut, 2, 2, 2);
  holder.join();

  const auto r = record()->read();
  ASSERT_EQ(r->ingest_ms.size(), 2U);
  ASSERT_EQ(r->ingest_record_wait_ms.size(), 2U);
  ASSERT_EQ(r->ingest_map_wait_ms.size(), 2U);
  ASSERT_EQ(r->ingest_cpu_ms.size(), 2U);
  const double waited_ms = r->ingest_map_wait_ms.samples()[1];
  EXPECT_GE(waited_ms, 40.0);
  EXPECT_LE(waited_ms + r->ingest_record_wait_ms.samples()[1], r->ingest_ms.samples()[1]);
  EXPECT_LT(r->ingest_record_wait_ms.samples()[1], 40.0);  // the record's lock was free
  EXPECT_LT(r->ingest_cpu_ms.samples()[1], 40.0);          // waiting for a lock costs no CPU
  EXPECT_GT(r->ingest_cpu_ms.samples()[0], 0.0);
  EXPECT_LE(r->ingest_map_wait_ms.samples()[0], r->ingest_ms.samples()[0]);
}

TEST_F(AgentSessionTest, TheServerMapOpenedForAnAgentMapRemembersItsOriginAfterItIsGone) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  auto mission = core_.missions().find(kMission);
  const MapId map = record()->read()->agent_maps.at(0).map;
  mission->stack().remove(map);  // as a merge does

  const std::optional<MapOrigin> origin = mission->stack().origin(map);
  ASSERT_TRUE(origin.has_value());
  EXPECT_EQ(origin->agent, kAgent);
  EXPECT_EQ(origin->agent_map, 0U);
  EXPECT_FALSE(mission->stack().origin(map + 100).has_value());
}

TEST_F(AgentSessionTest, DownlinkIsSentAtMostAtTheDownlinkRate) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);
  const Clock::time_point t = later(1);
  v1::ServerDownlink first;
  v1::ServerDownlink second;
  v1::ServerDownlink third;
  ASSERT_TRUE(sut->nextDownlink(t, first));
  sendBatch(*sut, 2, 1, 1);

  const bool sent_100ms_later = sut->nextDownlink(t + milliseconds(100), second);
  const bool sent_one_period_later = sut->nextDownlink(t + milliseconds(500), third);

  EXPECT_EQ(first.acked_sequence(), 1U);
  EXPECT_FALSE(sent_100ms_later);
  ASSERT_TRUE(sent_one_period_later);
  EXPECT_EQ(third.acked_sequence(), 2U);
}

TEST_F(AgentSessionTest, NoDownlinkIsSentWhenThereIsNothingNew) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);
  v1::ServerDownlink down;
  ASSERT_TRUE(sut->nextDownlink(later(1), down));

  const bool sent = sut->nextDownlink(later(5), down);

  EXPECT_FALSE(sent);
}

TEST_F(AgentSessionTest, ResentBatchesAfterAReconnectAreDroppedCountedAndStoredOnce) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  sendBatch(*sut, 2, 2, 2);
  sut->close(Status::Ok());
  auto reconnected = openSession();
  greet(*reconnected);
  ASSERT_EQ(reply_.welcome().stored_sequence(), 2U);

  // The agent had not seen the acknowledgement of 1 and 2, so it sends them again, then 3.
  sendBatch(*reconnected, 1, 0, 2);
  sendBatch(*reconnected, 2, 2, 2);
  sendBatch(*reconnected, 3, 4, 1);

  auto r = record()->read();
  EXPECT_EQ(r->duplicate_batches, 2U);
  EXPECT_EQ(r->stored_sequence, 3U);
  EXPECT_EQ(r->keyframes.size(), 5U);
  EXPECT_EQ(r->duplicate_objects, 0U);  // dropped whole, not object by object
  EXPECT_EQ(r->up.at("batch").messages, 5U);
  EXPECT_EQ(r->up.at("keyframe").messages, 5U);  // parts are counted for stored batches only
  EXPECT_EQ(keyframesInMaps(), 5U);
}

TEST_F(AgentSessionTest, SequenceGoingBackWithinAStreamIsRefused) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);
  sendBatch(*sut, 2, 1, 1);

  const Status s = send(*sut, batchMessage(makeKeyframeBatch(1, 0, 1)));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), HasSubstr("batch sequence went back from 2 to 1"));
  EXPECT_EQ(record()->read()->duplicate_batches, 0U);
}

TEST_F(AgentSessionTest, SameSequenceTwiceWithinAStreamIsRefused) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);

  const Status s = send(*sut, batchMessage(makeKeyframeBatch(1, 0, 1)));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), HasSubstr("batch sequence 1 sent twice on one stream"));
}

TEST_F(AgentSessionTest, SequenceSkippingAheadIsRefusedNamingTheNextExpected) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);

  const Status s = send(*sut, batchMessage(makeKeyframeBatch(3, 1, 1)));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), AllOf(HasSubstr("batch sequence 3 skips ahead"), HasSubstr("the next is 2")));
  EXPECT_EQ(record()->read()->stored_sequence, 1U);
  EXPECT_EQ(keyframesInMaps(), 1U);
}

TEST_F(AgentSessionTest, SequenceZeroIsRefused) {
  greet(*sut);

  const Status s = send(*sut, batchMessage(makeKeyframeBatch(0, 0, 1)));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), HasSubstr("sequences start at 1"));
}

TEST_F(AgentSessionTest, BatchThatFailsValidationIsRefusedAndChangesNothing) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  v1::MapBatch bad = makeKeyframeBatch(2, 2, 2);
  bad.mutable_points(1)->set_reference_keyframe(99);  // the last part is bad; the rest would be valid
  const std::size_t maps_before = core_.missions().find(kMission)->stack().maps().size();
  const std::size_t keyframes_before = keyframesInMaps();

  const Status s = send(*sut, batchMessage(bad));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(s.error().message(), AllOf(HasSubstr("batch 2"), HasSubstr("map point 4:3"),
                                         HasSubstr("keyframe 4:99, which the server never received")));
  EXPECT_EQ(core_.missions().find(kMission)->stack().maps().size(), maps_before);
  EXPECT_EQ(keyframesInMaps(), keyframes_before);
  auto r = record()->read();
  EXPECT_EQ(r->stored_sequence, 1U);
  EXPECT_EQ(r->keyframes.size(), 2U);
  EXPECT_EQ(r->points.size(), 2U);
  EXPECT_EQ(r->refused_messages, 1U);
  EXPECT_THAT(r->last_error, HasSubstr("keyframe 4:99"));
}

TEST_F(AgentSessionTest, StoredBatchIsCountedByKindWithItsSerializedBytes) {
  greet(*sut);
  const v1::MapBatch batch = makeKeyframeBatch(1, 0, 3);
  std::uint64_t keyframe_bytes = 0;
  for (const auto& k : batch.keyframes()) keyframe_bytes += k.ByteSizeLong();
  std::uint64_t observation_bytes = 0;
  for (const auto& o : batch.observations()) observation_bytes += o.ByteSizeLong();
  const v1::AgentUplink message = batchMessage(batch);

  sendOk(*sut, message);

  auto r = record()->read();
  EXPECT_EQ(r->up.at("keyframe").messages, 3U);
  EXPECT_EQ(r->up.at("keyframe").bytes, keyframe_bytes);
  EXPECT_EQ(r->up.at("point").messages, 3U);
  EXPECT_EQ(r->up.at("observation").messages, 5U);
  EXPECT_EQ(r->up.at("observation").bytes, observation_bytes);
  EXPECT_EQ(r->up.at("batch").bytes, message.ByteSizeLong());
  EXPECT_EQ(r->up.at("message").messages, 2U);  // the Hello and the batch
  EXPECT_EQ(r->down.at("welcome").messages, 1U);
}

TEST_F(AgentSessionTest, GoodbyeAtTheEndOfTheMissionMarksTheAgentFinished) {
  greet(*sut);

  sendOk(*sut, test::goodbyeMessage(true));

  EXPECT_TRUE(record()->read()->finished);
  EXPECT_EQ(record()->read()->up.at("goodbye").messages, 1U);
}

// ---- Reconnects and a second process ----

TEST_F(AgentSessionTest, AMissionDroppedFromThisReplicaEndsItsStreamsAndRefusesWhatStillComes) {
  int cancelled = 0;
  auto session = openSession(&cancelled);
  greet(*session);
  sendBatch(*session, 1, 0, 2);

  core_.dropMission(kMission);  // its lease went to another replica

  EXPECT_EQ(cancelled, 1);
  EXPECT_EQ(core_.missions().find(kMission), nullptr);
  const Status late = send(*session, batchMessage(makeKeyframeBatch(2, 2, 2)));
  ASSERT_FALSE(late.ok());
  EXPECT_EQ(late.error().code(), ErrorCode::kUnavailable);
  EXPECT_THAT(late.error().message(), HasSubstr("moved to another replica"));
  v1::ServerDownlink down;
  EXPECT_FALSE(session->nextDownlink(later(2), down));
}

// A server that exits without writing outputs (no drain) while place recognition and the back-end still work
// through queued keyframes: the core stops the workers in an order in which neither calls the other after it went
// (run under the asan preset to see it).
TEST(ServerCoreShutdown, ACoreDestroyedWhileItsWorkersAreBusyStopsThemInOrder) {
  for (int round = 0; round < 3; ++round) {
    ServerOptions o;
    o.recognition.delay_keyframes = 0;  // every keyframe queued for a query at once
    auto core = std::make_unique<ServerCore>(o);
    ASSERT_TRUE(core->startWorkers().ok());
    for (std::uint32_t agent = 1; agent <= 2; ++agent) {
      auto session = core->openSession({});
      ASSERT_TRUE(test::sendTo(*session, helloMessage(kMission, agent, 100 + agent)).ok());
      for (std::uint64_t s = 1; s <= 8; ++s) {
        ASSERT_TRUE(
            test::sendTo(*session, batchMessage(makeKeyframeBatch(s, static_cast<std::uint32_t>(4 * (s - 1)), 4)))
                .ok());
      }
    }
    ASSERT_NE(core->recognition(), nullptr);
    core.reset();  // no drainWorkers(): the queues still hold work
  }
}

TEST_F(AgentSessionTest, CloseMarksTheAgentDisconnectedAndKeepsWhatItStored) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);

  sut->close(Status::Ok());

  auto r = record()->read();
  EXPECT_FALSE(r->connected);
  EXPECT_EQ(r->stored_sequence, 1U);
  EXPECT_EQ(r->keyframes.size(), 2U);
}

TEST_F(AgentSessionTest, ReconnectGetsTheStoredSequenceInItsWelcome) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 2);
  sendBatch(*sut, 2, 2, 1);
  sut->close(Status::Ok());
  auto reconnected = openSession();

  const Status s = send(*reconnected, helloMessage(kMission, kAgent, kSession));

  ASSERT_TRUE(s.ok()) << s.error().toString();
  ASSERT_TRUE(reply_.has_welcome());
  EXPECT_EQ(reply_.welcome().stored_sequence(), 2U);
  EXPECT_EQ(reply_.welcome().keyframes_held(), 3U);
  EXPECT_EQ(reply_.welcome().points_held(), 3U);
  EXPECT_EQ(reply_.acked_sequence(), 2U);
  EXPECT_EQ(record()->read()->connections, 2U);
}

TEST_F(AgentSessionTest, ReconnectOfTheSameProcessTakesOverItsLingeringStream) {
  int old_stream_cancelled = 0;
  auto old_stream = openSession(&old_stream_cancelled);
  greet(*old_stream);
  sendBatch(*old_stream, 1, 0, 1);
  auto reconnected = openSession();

  const Status s = send(*reconnected, helloMessage(kMission, kAgent, kSession));  // the old one never closed

  ASSERT_TRUE(s.ok()) << s.error().toString();
  EXPECT_EQ(reply_.welcome().stored_sequence(), 1U);
  EXPECT_EQ(old_stream_cancelled, 1);
  const Status late = send(*old_stream, batchMessage(makeKeyframeBatch(2, 1, 1)));
  ASSERT_FALSE(late.ok());
  EXPECT_EQ(late.error().code(), ErrorCode::kAlreadyExists);
  EXPECT_THAT(late.error().message(), HasSubstr("a newer stream of this agent took over"));
  old_stream->close(late);  // the old stream ending must not disconnect the new one
  EXPECT_TRUE(record()->read()->connected);
  sendBatch(*reconnected, 2, 1, 1);
  EXPECT_EQ(record()->read()->stored_sequence, 2U);
}

TEST_F(AgentSessionTest, SecondProcessClaimingAConnectedAgentIsRefusedAsAlreadyExists) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);
  auto intruder = openSession();

  const Status s = send(*intruder, helloMessage(kMission, kAgent, kOtherProcess));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kAlreadyExists);
  EXPECT_THAT(s.error().message(), AllOf(HasSubstr("agent 4 of mission 'hall-1'"), HasSubstr("another process")));
  intruder->close(s);
  // The first process is untouched: still connected, and its next batch is stored.
  EXPECT_TRUE(record()->read()->connected);
  EXPECT_EQ(record()->read()->connections, 1U);
  sendBatch(*sut, 2, 1, 1);
  EXPECT_EQ(record()->read()->stored_sequence, 2U);
}

TEST_F(AgentSessionTest, ANewProcessAfterOneThatStoredDataIsRefusedBecauseItsIdsWouldClash) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 1);
  sut->close(Status::Ok());
  auto restarted = openSession();

  const Status s = send(*restarted, helloMessage(kMission, kAgent, kOtherProcess));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(s.error().message(), HasSubstr("streamed by another process before"));
  EXPECT_THAT(s.error().message(), HasSubstr("another --agent-id or --mission"));
  EXPECT_EQ(record()->read()->stored_sequence, 1U);  // what the first process sent stays
}

TEST_F(AgentSessionTest, ANewProcessIsWelcomedWhenTheOneBeforeStoredNothing) {
  greet(*sut);
  sut->close(Status::Ok());
  auto restarted = openSession();

  const Status s = send(*restarted, helloMessage(kMission, kAgent, kOtherProcess));

  ASSERT_TRUE(s.ok()) << s.error().toString();
  EXPECT_EQ(reply_.welcome().stored_sequence(), 0U);
}

// ---- The server's corrections ----

// A correction as the back-end applies it: the corrected keyframe and those it carries along are sent down once
// each, in the agent's world frame (the agent map's T_m_w, which followed the newest corrected keyframe), and
// again only after the next correction.
TEST_F(AgentSessionTest, CorrectedKeyframesAreSentDownOnceInTheAgentsFrameUntilCorrectedAgain) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 3);
  v1::ServerDownlink down;
  ASSERT_TRUE(sut->nextDownlink(later(1), down));
  ASSERT_EQ(down.corrected_keyframes_size(), 0);
  test::KeyframeStateChange change;
  change.id = KeyframeId{kAgent, 1};
  change.T_m_s = geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0.1, -0.2, 0.3)), Eigen::Vector3d(1.5, -2.5, 0.25));
  change.v_m = Eigen::Vector3d(0.5, 0.25, -0.125);
  change.bias.gyro = Eigen::Vector3d(0.01, 0.02, 0.03);
  change.bias.accel = Eigen::Vector3d(-0.1, -0.2, -0.3);

  const auto applied = test::correctAsTheBackend(core_, kMission, {change});
  ASSERT_TRUE(applied.ok()) << applied.error().toString();
  v1::ServerDownlink corrected;
  v1::ServerDownlink after;
  const bool sent = sut->nextDownlink(later(2), corrected);
  const bool sent_again = sut->nextDownlink(later(4), after);

  ASSERT_TRUE(sent);
  ASSERT_EQ(corrected.corrected_keyframes_size(), static_cast<int>(applied->changed.size()));
  EXPECT_EQ(applied->changed.size(), 3U) << "keyframe 1 corrected, 0 and 2 carried along";
  {  // read locks, released before the next correction takes the stack's write locks
    const auto r = record()->read();
    const geometry::SE3d T_w_m = r->agent_maps.begin()->second.T_m_w.inverse();
    const auto map = core_.missions().find(kMission)->stack().find(r->keyframes.at(1).map)->read();
    for (const v1::KeyframeState& state : corrected.corrected_keyframes()) {
      const ServerKeyframe* kf = map->keyframe(KeyframeId{kAgent, state.counter()});
      ASSERT_NE(kf, nullptr);
      const geometry::SE3d T_w_s = T_w_m * kf->T_w_s;
      EXPECT_NEAR(state.t_w_s().px(), T_w_s.translation().x(), 1e-6) << "keyframe " << state.counter();
      EXPECT_NEAR(state.t_w_s().pz(), T_w_s.translation().z(), 1e-6);
      EXPECT_NEAR(std::abs(state.t_w_s().qw()), std::abs(T_w_s.so3().quaternion().w()), 1e-6);
      if (state.counter() == 1) {
        EXPECT_NEAR(kf->T_w_s.translation().x(), 1.5, 1e-12) << "the server map holds the corrected state";
        EXPECT_FLOAT_EQ(state.bias_accel(1), -0.2F);
        EXPECT_NEAR(state.v_w(2), (T_w_m.so3() * change.v_m).z(), 1e-6);
      }
    }
  }
  EXPECT_EQ(corrected.acked_sequence(), 1U);
  EXPECT_FALSE(sent_again);  // sent once

  change.T_m_s = geometry::SE3d(change.T_m_s.so3(), Eigen::Vector3d(1.6, -2.5, 0.25));
  ASSERT_TRUE(test::correctAsTheBackend(core_, kMission, {change}).ok());
  v1::ServerDownlink again;
  ASSERT_TRUE(sut->nextDownlink(later(6), again));
  EXPECT_EQ(again.corrected_keyframes_size(), 3);
  EXPECT_EQ(record()->read()->down.at("correction").messages, 6U);
}

TEST_F(AgentSessionTest, AKeyframeRemovedAsRedundantIsSentDownOnce) {
  greet(*sut);
  sendBatch(*sut, 1, 0, 3);
  v1::ServerDownlink ack;
  ASSERT_TRUE(sut->nextDownlink(later(1), ack));
  ASSERT_EQ(ack.removed_keyframes_size(), 0);
  {
    // What the back-end's redundancy removal leaves in the record (BackendWorker::removeRedundant).
    auto r = record()->write();
    r->server_removed_keyframes.insert(2);
    r->removals_to_send.insert(2);
  }
  v1::ServerDownlink down;
  v1::ServerDownlink after;
  const bool sent = sut->nextDownlink(later(2), down);
  const bool sent_again = sut->nextDownlink(later(4), after);

  ASSERT_TRUE(sent);
  ASSERT_EQ(down.removed_keyframes_size(), 1);
  EXPECT_EQ(down.removed_keyframes(0), 2U);
  EXPECT_FALSE(sent_again);  // sent once
  const auto r = record()->read();
  EXPECT_EQ(r->down.at("removal").messages, 1U);
  EXPECT_GT(r->down.at("removal").bytes, 0U);
  EXPECT_EQ(r->serverKeyframes(), 2U);
}

TEST_F(AgentSessionTest, AnAgentBackWhereItStartedIsSentItsOldKeyframesWithTheirPointsOnce) {
  greet(*sut);
  for (std::uint32_t b = 0; b < 6; ++b) sendBatch(*sut, b + 1, 10 * b, 10);  // keyframes 0..59
  v1::ServerDownlink before;
  ASSERT_TRUE(sut->nextDownlink(later(1), before));
  EXPECT_FALSE(before.has_covisible()) << "nothing beyond the agent's own local map shares a point yet";
  // Keyframes 60 and 61 see the points of keyframes 2 to 5 again (the agent is back at its start).
  v1::MapBatch back = makeKeyframeBatch(7, 60, 2);
  test::addObservations(back, 61, {10, 11, 12, 13}, {2, 3, 4, 5});
  sendOk(*sut, batchMessage(back));

  v1::ServerDownlink down;
  v1::ServerDownlink again;
  ASSERT_TRUE(sut->nextDownlink(later(2), down));
  const bool sent_again = sut->nextDownlink(later(3), again);

  ASSERT_TRUE(down.has_covisible());
  const v1::CovisibleMap& covisible = down.covisible();
  std::set<std::uint32_t> sent;
  for (const auto& kf : covisible.keyframes()) {
    EXPECT_EQ(kf.agent(), kAgent);
    sent.insert(kf.counter());
  }
  // Keyframes 1..5 observe points 2..5 (each point is seen by its keyframe and the one before).
  EXPECT_EQ(sent, (std::set<std::uint32_t>{1, 2, 3, 4, 5}));
  EXPECT_EQ(covisible.points_size(), 6) << "points 1..6: keyframe c sees points c and c + 1";
  EXPECT_FALSE(sent_again) << "sent once; nothing changed since";
  const auto r = record()->read();
  EXPECT_EQ(r->down.at("covisible_keyframe").messages, 5U);
  EXPECT_EQ(r->down.at("covisible_point").messages, 6U);
}

// Scale-out: a replica takes a mission's lease for a Hello only once the Hello is one it would serve. A Hello
// refused for what it says (an absurd calibration) or for the replica's mission limit claims nothing, so it cannot
// take a mission over from nobody, nor hold a lease for a mission it then refuses to serve.
class CountingOwnership final : public MissionOwnership {
 public:
  int claims = 0;
  Result<MissionOwner> claim(const std::string& /*mission*/) override {
    ++claims;
    return MissionOwner{};
  }
  Result<MissionOwner> owner(const std::string& /*mission*/) override { return MissionOwner{}; }
  Result<std::vector<MissionOwner>> others() override { return std::vector<MissionOwner>{}; }
};

TEST(AgentSessionOwnership, AHelloRefusedForWhatItSaysOrForTheMissionLimitClaimsNoLease) {
  MissionRegistry missions;
  SessionOptions options;
  options.max_missions = 1;
  missions.getOrCreate("held");  // the replica's one mission
  CountingOwnership ownership;
  v1::ServerDownlink reply;
  bool reply_due = false;

  AgentSession absurd(
      missions, options, [] {}, {}, nullptr, {}, &ownership);
  v1::AgentUplink hello = helloMessage("held", kAgent, kSession);
  hello.mutable_hello()->mutable_cam0()->set_fx(1e300);
  EXPECT_FALSE(test::sendTo(absurd, hello, &reply, &reply_due).ok());

  AgentSession over_limit(
      missions, options, [] {}, {}, nullptr, {}, &ownership);
  const Status refused = test::sendTo(over_limit, helloMessage("another", kAgent, kSession), &reply, &reply_due);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code(), ErrorCode::kResourceExhausted);
  EXPECT_EQ(ownership.claims, 0);

  AgentSession served(
      missions, options, [] {}, {}, nullptr, {}, &ownership);
  const Status welcomed = test::sendTo(served, helloMessage("held", kAgent, kSession), &reply, &reply_due);
  EXPECT_TRUE(welcomed.ok()) << welcomed.error().toString();
  EXPECT_EQ(ownership.claims, 1);  // and a Hello it serves does claim
}

}  // namespace
}  // namespace cvislam::server
