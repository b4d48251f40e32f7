#include "agent_rt/tracking/mapping_backlog.hpp"

#include <limits>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

constexpr std::int64_t kMs = 1'000'000;

TEST(MappingBacklog, KeyframesArePendingFromPublicationUntilASnapshotCountsThem) {
  MappingBacklog backlog{MappingLagOptions{}};
  EXPECT_EQ(backlog.pending(0), 0);
  EXPECT_EQ(backlog.publish(10 * kMs), 0U);
  EXPECT_EQ(backlog.publish(20 * kMs), 1U);
  EXPECT_EQ(backlog.publish(30 * kMs), 2U);
  EXPECT_EQ(backlog.published(), 3U);
  EXPECT_EQ(backlog.pending(40 * kMs), 3);

  backlog.taken(2);  // mapping answered the first two
  EXPECT_EQ(backlog.pending(40 * kMs), 1);
  backlog.taken(1);  // an older snapshot arriving late does not bring them back
  EXPECT_EQ(backlog.pending(40 * kMs), 1);
  backlog.taken(3);
  EXPECT_EQ(backlog.pending(40 * kMs), 0);
  EXPECT_EQ(backlog.publish(50 * kMs), 3U);  // numbering goes on
  EXPECT_EQ(backlog.pending(50 * kMs), 1);
}

TEST(MappingBacklog, AnUnansweredKeyframeStopsCountingAfterTheAnswerTimeout) {
  MappingLagOptions options;
  options.answer_timeout_s = 0.5;
  MappingBacklog backlog{options};
  backlog.publish(0);
  backlog.publish(300 * kMs);
  EXPECT_EQ(backlog.pending(499 * kMs), 2);
  EXPECT_EQ(backlog.pending(500 * kMs), 1);  // the first has waited 0.5 s: mapping refused it or stopped
  EXPECT_EQ(backlog.pending(799 * kMs), 1);
  EXPECT_EQ(backlog.pending(800 * kMs), 0);
}

TEST(MappingBacklog, PendingNeverCountsMoreThanTheRingHolds) {
  MappingBacklog backlog{MappingLagOptions{}};
  for (std::size_t i = 0; i < 3 * MappingBacklog::kCapacity; ++i) backlog.publish(static_cast<std::int64_t>(i));
  EXPECT_EQ(backlog.pending(1000), static_cast<int>(MappingBacklog::kCapacity));
  backlog.taken(3 * MappingBacklog::kCapacity - 5);
  EXPECT_EQ(backlog.pending(1000), 5);
}

TEST(MappingBacklog, BusyWithOnePendingAndFullAtTheBound) {
  MappingLagOptions options;
  options.max_pending_keyframes = 2;
  MappingBacklog backlog{options};
  MappingPressure p = backlog.pressure(0);
  EXPECT_FALSE(p.busy);
  EXPECT_FALSE(p.full);
  backlog.publish(0);
  p = backlog.pressure(kMs);
  EXPECT_EQ(p.pending, 1);
  EXPECT_TRUE(p.busy);
  EXPECT_FALSE(p.full);
  backlog.publish(kMs);
  p = backlog.pressure(2 * kMs);
  EXPECT_EQ(p.pending, 2);
  EXPECT_TRUE(p.busy);
  EXPECT_TRUE(p.full);

  options.back_off = false;  // the rules ignore mapping, but the count is still reported
  MappingBacklog ignoring{options};
  ignoring.publish(0);
  ignoring.publish(kMs);
  p = ignoring.pressure(2 * kMs);
  EXPECT_EQ(p.pending, 2);
  EXPECT_FALSE(p.busy);
  EXPECT_FALSE(p.full);
}

TEST(MappingBacklog, WhileBusyAKeyframeOnlyWhenTrackingWouldOtherwiseBeLost) {
  MappingLagOptions options;
  options.min_tracked_points_when_busy = 15;
  const MappingBacklog backlog{options};

  const MappingPressure idle{0, false, false};
  EXPECT_TRUE(backlog.gate(idle, 200).publish);
  EXPECT_TRUE(backlog.gate(idle, 3).publish);

  const MappingPressure busy{1, true, false};
  KeyframeGate g = backlog.gate(busy, 15);  // enough points: wait for mapping
  EXPECT_FALSE(g.publish);
  EXPECT_FALSE(g.needs_mapping);
  g = backlog.gate(busy, 14);  // about to be lost: take it although mapping is busy
  EXPECT_TRUE(g.publish);

  const MappingPressure full{2, true, true};
  g = backlog.gate(full, 14);  // the bound holds even then, and says mapping is needed
  EXPECT_FALSE(g.publish);
  EXPECT_TRUE(g.needs_mapping);
  g = backlog.gate(full, 100);
  EXPECT_FALSE(g.publish);
  EXPECT_FALSE(g.needs_mapping);
}

constexpr std::int64_t kFrame = 50 * kMs;  // 20 Hz, sequence time

// A keyframe held back is overdue once keyframes have been held back for yield_request_after_s of sequence time,
// counted from the first one held back since the last keyframe published; publishing one starts the count again.
TEST(MappingBacklog, KeyframesHeldBackForLongAreOverdueUntilOneIsPublished) {
  MappingLagOptions options;
  options.yield_request_after_s = 0.1;
  MappingBacklog backlog{options};
  const std::int64_t t0 = 1'000'000 * kMs;
  EXPECT_FALSE(backlog.heldBack(t0));
  EXPECT_FALSE(backlog.heldBack(t0 + kFrame));
  EXPECT_TRUE(backlog.heldBack(t0 + 2 * kFrame));  // 0.1 s since the first
  EXPECT_TRUE(backlog.heldBack(t0 + 5 * kFrame));
  (void)backlog.publish(0);  // a keyframe went out: the next one held back starts a new count
  EXPECT_FALSE(backlog.heldBack(t0 + 6 * kFrame));
  EXPECT_FALSE(backlog.heldBack(t0 + 7 * kFrame));
  EXPECT_TRUE(backlog.heldBack(t0 + 8 * kFrame));
}

TEST(MappingBacklog, WithNoDelayTheFirstKeyframeHeldBackIsOverdue) {
  MappingLagOptions options;
  options.yield_request_after_s = 0.0;
  MappingBacklog backlog{options};
  EXPECT_TRUE(backlog.heldBack(7 * kFrame));
  (void)backlog.publish(0);
  EXPECT_TRUE(backlog.heldBack(9 * kFrame));
}

TEST(MappingLagOptions, RefusesValuesThatWouldBreakTheBoundOrTheTimeout) {
  EXPECT_TRUE(MappingLagOptions{}.validate().ok());
  MappingLagOptions o;
  o.max_pending_keyframes = 0;
  Status s = o.validate();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message().find("lag.max_pending_keyframes = 0"), std::string::npos) << s.error().toString();
  o.max_pending_keyframes = static_cast<int>(MappingBacklog::kCapacity) / 2 + 1;
  EXPECT_FALSE(o.validate().ok());
  o.max_pending_keyframes = static_cast<int>(MappingBacklog::kCapacity) / 2;
  EXPECT_TRUE(o.validate().ok());

  o = MappingLagOptions{};
  o.min_tracked_points_when_busy = -1;
  EXPECT_FALSE(o.validate().ok());
  o = MappingLagOptions{};
  o.answer_timeout_s = std::numeric_limits<double>::quiet_NaN();
  EXPECT_FALSE(o.validate().ok());
  o.answer_timeout_s = std::numeric_limits<double>::infinity();
  EXPECT_FALSE(o.validate().ok());
  o.answer_timeout_s = 0.0;
  EXPECT_FALSE(o.validate().ok());

  o = MappingLagOptions{};
  o.yield_request_after_s = 0.0;
  EXPECT_TRUE(o.validate().ok());
  for (const double bad : {-0.1, std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity()}) {
    o.yield_request_after_s = bad;
    s = o.validate();
    ASSERT_FALSE(s.ok()) << bad;
    EXPECT_NE(s.error().message().find("lag.yield_request_after_s"), std::string::npos) << s.error().toString();
  }
}

}  // namespace
}  // namespace cvislam::agent
