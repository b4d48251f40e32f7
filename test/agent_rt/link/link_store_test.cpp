// The link's store: what goes to the server, when, and again after reconnections. Every batch it builds is
// delivered to the server's real core (AgentSession, without gRPC), so these tests also prove that the agent
// only ever sends what the server accepts.
#include "agent_rt/link/link_store.hpp"

#include <gtest/gtest.h>

#include "test/agent_rt/link/link_test_support.hpp"

namespace cvislam::agent {
namespace {

using test::DeltaWriter;
using test::ServerSide;

constexpr std::size_t kLargeBatch = 8U << 20U;

class LinkStoreTest : public ::testing::Test {
 protected:
  // Builds the next batch and delivers it; false when there was nothing to send.
  bool sendNext(std::size_t max_bytes = kLargeBatch) {
    if (!sut.buildBatch(next_sequence, 0, max_bytes, batch)) return false;
    const Status s = server.deliver(batch);
    EXPECT_TRUE(s.ok()) << "the server refused batch " << next_sequence << ": " << s.error().toString();
    ++next_sequence;
    return true;
  }
  // A reconnection: the server's Welcome tells what it holds.
  void reconnect() {
    const std::uint64_t stored = server.connect(sut.acked());
    sut.onWelcome(stored);
    next_sequence = stored + 1;
  }
  void ackAll() { sut.onAck(server.stored()); }

  LinkStore sut{test::kAgent, LinkStoreOptions{}};
  DeltaWriter map;
  ServerSide server;
  v1::MapBatch batch;
  std::uint64_t next_sequence = 1;
};

TEST_F(LinkStoreTest, NothingLeavesTheAgentBeforeItsMapIsReadyThenEverythingGoesInFullOnce) {
  reconnect();
  map.addKeyframe(0, {}, {100, 101, 102});
  sut.onDelta(map.finish());
  map.addKeyframe(1, {100, 101}, {103});
  sut.onDelta(map.finish());
  EXPECT_FALSE(sendNext());  // the IMU is not initialised: the frame may still change

  map.ready = true;
  map.addKeyframe(2, {100, 103}, {104});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  EXPECT_EQ(batch.keyframes_size(), 3);
  EXPECT_EQ(batch.points_size(), 5);
  EXPECT_EQ(batch.keyframe_updates_size(), 0);
  EXPECT_EQ(server.keyframes(), 3U);
  EXPECT_EQ(server.points(), 5U);
  // Keyframe 2 observes points 100, 103 and 104; keyframe 1 is linked to keyframe 0 by the IMU.
  ASSERT_NE(server.keyframe(2), nullptr);
  EXPECT_EQ(server.keyframe(2)->observationCount(), 3);
  ASSERT_TRUE(server.keyframe(1)->preintegration.has_value());
  EXPECT_NEAR(server.keyframe(1)->preintegration->dt(), 0.25, 1e-9);
  EXPECT_EQ(server.point(100)->observations.size(), 3U);
  EXPECT_TRUE(server.consistent().ok());
  EXPECT_FALSE(sendNext());  // nothing changed since
}

TEST_F(LinkStoreTest, AfterTheFirstTimeOnlyCompactUpdatesOfWhatMovedBeyondTheThresholds) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100, 101, 102});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  const std::size_t full_bytes = batch.ByteSizeLong();

  map.keyframes[0].p_w.x() += 0.02;  // 2 cm: goes
  map.points[100].p_w.z() += 0.01;   // 1 cm: goes (threshold 5 mm)
  map.points[101].p_w.z() += 0.001;  // 1 mm: stays
  sut.onDelta((map.change(), map.finish()));
  ASSERT_TRUE(sendNext());
  EXPECT_EQ(batch.keyframes_size(), 0);
  EXPECT_EQ(batch.points_size(), 0);
  ASSERT_EQ(batch.keyframe_updates_size(), 1);
  ASSERT_EQ(batch.point_updates().point_size(), 1);
  EXPECT_EQ(batch.point_updates().point(0), 100U);
  EXPECT_LT(batch.ByteSizeLong(), full_bytes / 10);
  EXPECT_NEAR(server.keyframe(0)->T_w_s.translation().x(), map.keyframes[0].p_w.x(), 1e-9);
  EXPECT_NEAR(server.point(100)->p_w.z(), map.points[100].p_w.z(), 1e-6);
}

TEST_F(LinkStoreTest, WhatWasSentAfterTheServersStoredSequenceIsSentAgainAndNothingTwice) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100, 101});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());  // batch 1: stored
  map.addKeyframe(1, {100}, {102});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sut.buildBatch(next_sequence++, 0, kLargeBatch, batch));  // batch 2: lost with the stream

  reconnect();  // the server holds batch 1 only
  EXPECT_EQ(next_sequence, 2U);
  EXPECT_EQ(sut.counters().acked_batches_lost, 0U);  // batch 2 was never acknowledged
  ASSERT_TRUE(sendNext());
  ASSERT_EQ(batch.keyframes_size(), 1);
  EXPECT_EQ(batch.keyframes(0).counter(), 1U);
  EXPECT_EQ(batch.points_size(), 1);
  EXPECT_EQ(server.keyframes(), 2U);
  EXPECT_EQ(server.points(), 3U);
  EXPECT_EQ(server.keyframe(1)->observationCount(), 2);
  ackAll();
  EXPECT_TRUE(sut.allAcknowledged());
  EXPECT_TRUE(server.consistent().ok());
}

TEST_F(LinkStoreTest, AServerThatLostEverythingGetsTheCurrentMapInFull) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100, 101});
  sut.onDelta(map.finish());
  map.addKeyframe(1, {100, 101}, {102});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  ackAll();
  // Keyframe 0 leaves the bounded local map; it was acknowledged, so the store forgets it.
  map.keyframes.erase(0);
  sut.onDelta((map.change(), map.event(MapEventType::kKeyframeRemoved, MapEventReason::kEvicted, 0, 0), map.finish()));
  EXPECT_EQ(sut.backlog().keyframes_held, 1U);

  server.restart();  // empty
  reconnect();
  EXPECT_EQ(next_sequence, 1U);
  EXPECT_EQ(sut.counters().acked_batches_lost, 1U);  // batch 1 was acknowledged, and the server lost it
  ASSERT_TRUE(sendNext());
  ASSERT_EQ(batch.keyframes_size(), 1);
  EXPECT_EQ(batch.keyframes(0).counter(), 1U);
  // Its points now hang from keyframe 1, which observes them; its IMU predecessor is gone.
  EXPECT_EQ(server.points(), 3U);
  EXPECT_EQ(server.point(100)->reference, (KeyframeId{test::kAgent, 1}));
  EXPECT_FALSE(server.keyframe(1)->preintegration.has_value());
  EXPECT_TRUE(server.consistent().ok());
}

TEST_F(LinkStoreTest, ACulledPointTheServerHoldsIsRemovedThereAndOneItNeverGotIsNotMentioned) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100, 101});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  map.addKeyframe(1, {100}, {102});
  map.points.erase(101);
  map.points.erase(102);
  map.event(MapEventType::kPointRemoved, MapEventReason::kCulled, 0, 101);
  map.event(MapEventType::kPointRemoved, MapEventReason::kCulled, 0, 102);  // made and culled before sending
  map.keyframes[1].observations.erase(1);
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  ASSERT_EQ(batch.removed_points_size(), 1);
  EXPECT_EQ(batch.removed_points(0), 101U);
  EXPECT_EQ(server.points(), 1U);
  EXPECT_EQ(server.point(101), nullptr);
  EXPECT_TRUE(server.consistent().ok());
}

TEST_F(LinkStoreTest, AMergeReachesTheServerAfterTheKeptPointAndMovesItsObservations) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  // Keyframe 1 makes point 101, a duplicate of 100, then mapping merges 100 into 101 at once.
  map.addKeyframe(1, {}, {101});
  map.event(MapEventType::kPointsMerged, MapEventReason::kNone, 0, 100, 101);
  map.points.erase(100);
  map.keyframes[0].observations[0] = 101;
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  ASSERT_EQ(batch.merges().drop_size(), 1);
  EXPECT_EQ(batch.merges().drop(0), 100U);
  EXPECT_EQ(batch.merges().keep(0), 101U);
  EXPECT_EQ(server.point(100), nullptr);
  ASSERT_NE(server.point(101), nullptr);
  EXPECT_EQ(server.point(101)->observations.size(), 2U);  // keyframe 0's link moved over
  EXPECT_TRUE(server.consistent().ok());
}

TEST_F(LinkStoreTest, WhatLeavesTheLocalMapBeforeTheMapIsReadyIsForgotten) {
  map.addKeyframe(0, {}, {100});
  sut.onDelta(map.finish());
  map.keyframes.erase(0);
  map.points.erase(100);
  sut.onDelta((map.change(), map.event(MapEventType::kKeyframeRemoved, MapEventReason::kRemoved, 0, 0),
               map.event(MapEventType::kPointRemoved, MapEventReason::kRemoved, 0, 100), map.finish()));
  EXPECT_EQ(sut.backlog().keyframes_held, 0U);
  EXPECT_EQ(sut.backlog().points_held, 0U);
}

TEST_F(LinkStoreTest, ABacklogIsSplitIntoBatchesNearTheByteBudget) {
  map.ready = true;
  for (std::uint32_t k = 0; k < 20; ++k) {
    map.addKeyframe(k, {}, {1000 + k});
    sut.onDelta(map.finish());
  }
  reconnect();
  int batches = 0;
  std::size_t largest = 0;
  while (sendNext(16U << 10U)) {
    ++batches;
    largest = std::max(largest, batch.ByteSizeLong());
  }
  EXPECT_GT(batches, 3);
  EXPECT_LT(largest, 2 * (16U << 10U));  // one keyframe (about 5 KB here) over the budget at most
  EXPECT_EQ(server.keyframes(), 20U);
  EXPECT_EQ(server.points(), 20U);
}

TEST_F(LinkStoreTest, AFullStoreDropsTheOldestUnsentKeyframesThatLeftTheLocalMapAndCountsThem) {
  map.ready = true;
  const std::uint32_t total = kLinkMaxKeyframes + 10;
  for (std::uint32_t k = 0; k < total; ++k) {
    map.addKeyframe(k, {}, {});
    if (map.keyframes.size() > 5) {  // a local map of 5 keyframes; the server is away all along
      const std::uint32_t oldest = map.keyframes.begin()->first;
      map.keyframes.erase(oldest);
      map.event(MapEventType::kKeyframeRemoved, MapEventReason::kEvicted, oldest, 0);
    }
    sut.onDelta(map.finish());
  }
  EXPECT_EQ(sut.counters().keyframes_dropped, 10U);
  EXPECT_EQ(sut.backlog().keyframes_held, kLinkMaxKeyframes);
  reconnect();
  while (sendNext()) {
  }
  EXPECT_EQ(server.keyframes(), kLinkMaxKeyframes);
  EXPECT_EQ(server.keyframe(9), nullptr);  // the oldest went
  EXPECT_NE(server.keyframe(10), nullptr);
}

TEST_F(LinkStoreTest, ANewMapOfTheAgentBecomesASecondServerMapAndTheFirstStays) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100});
  sut.onDelta(map.finish());
  map.addKeyframe(1, {100}, {101});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  // Tracking was lost: mapping clears its local map and starts map 1, not ready until its IMU is initialised.
  map.keyframes.clear();
  map.points.clear();
  map.map_id = 1;
  map.ready = false;
  map.change();
  for (std::uint32_t k : {0U, 1U}) map.event(MapEventType::kKeyframeRemoved, MapEventReason::kRemoved, k, 0);
  for (std::uint32_t p : {100U, 101U}) map.event(MapEventType::kPointRemoved, MapEventReason::kRemoved, 0, p);
  sut.onDelta(map.finish());
  map.addKeyframe(2, {}, {102});
  sut.onDelta(map.finish());
  EXPECT_FALSE(sendNext());
  map.ready = true;
  map.addKeyframe(3, {102}, {103});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  EXPECT_EQ(batch.keyframes_size(), 2);
  EXPECT_EQ(batch.keyframes(0).agent_map(), 1U);
  // Two server maps: the first with its two keyframes as they were, the second with the new ones.
  int maps = 0;
  server.forEachMap([&](const server::MapContent& m) {
    ++maps;
    EXPECT_EQ(m.keyframes().size(), 2U);
  });
  EXPECT_EQ(maps, 2);
  EXPECT_NE(server.keyframe(0), nullptr);
  EXPECT_NE(server.point(100), nullptr);
  EXPECT_TRUE(server.consistent().ok());
}

TEST_F(LinkStoreTest, APointThatLeftTheLocalMapStaysUntilTheObservationsOfItAreAcknowledged) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  ackAll();
  // Keyframe 1 observes point 100, which then leaves the bounded local map.
  map.addKeyframe(1, {100}, {101});
  map.points.erase(100);
  map.event(MapEventType::kPointRemoved, MapEventReason::kEvicted, 0, 100);
  sut.onDelta(map.finish());
  // A small budget: the keyframe goes in one batch, its observations in the next.
  ASSERT_TRUE(sendNext(1024));
  EXPECT_EQ(batch.observations_size(), 0);
  ackAll();  // point 100 is acknowledged and out of the local map, but keyframe 1's link to it is not sent yet
  while (sendNext()) {
  }
  ASSERT_NE(server.keyframe(1), nullptr);
  EXPECT_EQ(server.keyframe(1)->observationCount(), 2);
  EXPECT_EQ(server.point(100)->observations.size(), 2U);
}

TEST_F(LinkStoreTest, AMergeIntoAPointThatLeftTheLocalMapIsStillAMergeOnTheServer) {
  reconnect();
  map.ready = true;
  map.addKeyframe(0, {}, {100, 101});
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  ackAll();
  // The server is away: mapping merges 101 into 100, then 100 leaves the local map.
  map.change();
  map.event(MapEventType::kPointsMerged, MapEventReason::kNone, 0, 101, 100);
  map.points.erase(101);
  map.points.erase(100);
  map.event(MapEventType::kPointRemoved, MapEventReason::kEvicted, 0, 100);
  sut.onDelta(map.finish());
  sut.onAck(server.stored());  // a late acknowledgement while the merge is still unsent
  ASSERT_TRUE(sendNext());
  ASSERT_EQ(batch.merges().drop_size(), 1);
  EXPECT_EQ(batch.removed_points_size(), 0);
  EXPECT_EQ(server.point(101), nullptr);
  ASSERT_NE(server.point(100), nullptr);
  EXPECT_EQ(server.keyframe(0)->observationCount(), 1);  // its link to 101 went with the merge (it saw both)
}

TEST_F(LinkStoreTest, AKeyframeThatLeavesInTheDeltaThatMakesTheMapReadyIsForgotten) {
  reconnect();
  map.addKeyframe(0, {}, {100});
  sut.onDelta(map.finish());
  map.addKeyframe(1, {}, {101});
  sut.onDelta(map.finish());
  // In the keyframe whose IMU initialisation succeeds, keyframe 0 is evicted first: its state is still in the
  // frame before the initialisation, so it must not go up.
  map.ready = true;
  map.keyframes.erase(0);
  map.points.erase(100);
  map.addKeyframe(2, {101}, {102});
  map.event(MapEventType::kKeyframeRemoved, MapEventReason::kEvicted, 0, 0);
  map.event(MapEventType::kPointRemoved, MapEventReason::kEvicted, 0, 100);
  sut.onDelta(map.finish());
  ASSERT_TRUE(sendNext());
  EXPECT_EQ(server.keyframe(0), nullptr);
  EXPECT_EQ(server.point(100), nullptr);
  EXPECT_NE(server.keyframe(1), nullptr);
  EXPECT_NE(server.keyframe(2), nullptr);
}

// With link.keyframe_before_local_ba, mapping writes a keyframe's delta before its local BA and another after it.
// The server stores the keyframe at once, but place recognition and the back-end wait for its refined state.
TEST_F(LinkStoreTest, AKeyframeSentBeforeItsLocalBaWaitsOnTheServerForItsRefinedState) {
  const auto workers = ServerSide::withWorkers();
  ServerSide& side = *workers;
  const auto send = [&] {
    EXPECT_TRUE(sut.buildBatch(next_sequence, 0, kLargeBatch, batch));
    const Status s = side.deliver(batch);
    ASSERT_TRUE(s.ok()) << s.error().toString();
    ++next_sequence;
    side.core().drainWorkers(false);
  };
  const auto recognised = [&] { return side.core().recognition()->counters("link-test").keyframes; };
  next_sequence = side.connect(0) + 1;
  map.ready = true;
  map.addKeyframe(0, {}, {100, 101, 102});
  sut.onDelta(map.finish());
  map.addKeyframe(1, {100, 101}, {103}).keyframe_before_local_ba = 1;
  sut.onDelta(map.finish());
  send();
  ASSERT_EQ(batch.keyframes_size(), 2);
  EXPECT_FALSE(batch.keyframes(0).before_local_ba());
  EXPECT_TRUE(batch.keyframes(1).before_local_ba());
  ASSERT_NE(side.keyframe(1), nullptr);
  EXPECT_TRUE(side.keyframe(1)->awaiting_local_ba);
  EXPECT_FALSE(side.keyframe(0)->awaiting_local_ba);
  EXPECT_EQ(recognised(), 1U);

  // Its local BA did not move it: its state still goes, since the server waits for it.
  sut.onDelta((map.change(), map.finish()));
  send();
  ASSERT_EQ(batch.keyframe_updates_size(), 1);
  EXPECT_EQ(batch.keyframe_updates(0).counter(), 1U);
  EXPECT_FALSE(side.keyframe(1)->awaiting_local_ba);
  EXPECT_EQ(recognised(), 2U);

  // Both deltas before the next batch: the keyframe goes once, with its refined state, and nothing waits.
  map.addKeyframe(2, {103}, {104}).keyframe_before_local_ba = 1;
  sut.onDelta(map.finish());
  map.keyframes[2].p_w.y() += 0.01;
  sut.onDelta((map.change(), map.finish()));
  send();
  ASSERT_EQ(batch.keyframes_size(), 1);
  EXPECT_FALSE(batch.keyframes(0).before_local_ba());
  EXPECT_EQ(batch.keyframe_updates_size(), 0);
  EXPECT_NEAR(side.keyframe(2)->T_w_s.translation().y(), 0.01, 1e-9);
  EXPECT_FALSE(side.keyframe(2)->awaiting_local_ba);
  EXPECT_EQ(recognised(), 3U);
  EXPECT_FALSE(sut.buildBatch(next_sequence, 0, kLargeBatch, batch));  // nothing due
}

TEST_F(LinkStoreTest, AGapInMappingsDeltasIsCounted) {
  map.addKeyframe(0, {}, {});
  sut.onDelta(map.finish());
  map.change();
  map.addKeyframe(1, {}, {});  // the delta before this one never arrived
  sut.onDelta(map.finish());
  EXPECT_EQ(sut.counters().deltas_lost, 1U);
}

}  // namespace
}  // namespace cvislam::agent
