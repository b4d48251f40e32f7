// MissionEventLog: events are numbered from 1 in the order appended; a reader gets pages from any number on,
// learns how many it asked for that the log no longer holds, and resumes with the page's `next`.
#include "server_cloud/stack/mission_events.hpp"

#include <gtest/gtest.h>

namespace cvislam::server {
namespace {

MissionEvent added(std::uint32_t counter) {
  MissionEvent e;
  e.kind = MissionEvent::Kind::kKeyframeAdded;
  e.keyframe = KeyframeId{4, counter};
  e.agent = 4;
  return e;
}

TEST(MissionEventLog, EventsAreNumberedFromOneInOrderAndStamped) {
  MissionEventLog log;
  EXPECT_EQ(log.nextNumber(), 1U);

  EXPECT_EQ(log.append(added(10)), 1U);
  EXPECT_EQ(log.append(added(11)), 2U);
  const auto page = log.read(1, 10);

  ASSERT_EQ(page.events.size(), 2U);
  EXPECT_EQ(page.events[0].number, 1U);
  EXPECT_EQ(page.events[1].keyframe.counter, 11U);
  EXPECT_GT(page.events[0].t_unix_ns, 1'700'000'000'000'000'000);  // after 2023: a wall-clock stamp
  EXPECT_LE(page.events[0].t_unix_ns, page.events[1].t_unix_ns);
  EXPECT_EQ(page.skipped, 0U);
  EXPECT_EQ(page.next, 3U);
  EXPECT_EQ(log.nextNumber(), 3U);
}

TEST(MissionEventLog, PagesResumeWhereTheLastEndedAndStopAtTheNewest) {
  MissionEventLog log;
  for (std::uint32_t c = 0; c < 10; ++c) log.append(added(c));

  const auto first = log.read(1, 4);
  const auto second = log.read(first.next, 4);
  const auto third = log.read(second.next, 4);
  const auto none = log.read(third.next, 4);

  EXPECT_EQ(first.events.size(), 4U);
  EXPECT_EQ(second.events.front().number, 5U);
  ASSERT_EQ(third.events.size(), 2U);
  EXPECT_EQ(third.events.back().number, 10U);
  EXPECT_TRUE(none.events.empty());
  EXPECT_EQ(none.next, 11U);
  log.append(added(99));
  const auto later = log.read(none.next, 4);
  ASSERT_EQ(later.events.size(), 1U);
  EXPECT_EQ(later.events[0].keyframe.counter, 99U);
}

TEST(MissionEventLog, AReaderBehindTheOldestHeldLearnsHowManyItMissed) {
  MissionEventLog log(5);
  for (std::uint32_t c = 0; c < 12; ++c) log.append(added(c));  // holds 8..12

  const auto page = log.read(3, 100);
  const auto from_zero = log.read(0, 100);

  EXPECT_EQ(page.skipped, 5U);  // 3, 4, 5, 6, 7
  ASSERT_EQ(page.events.size(), 5U);
  EXPECT_EQ(page.events.front().number, 8U);
  EXPECT_EQ(page.next, 13U);
  EXPECT_EQ(from_zero.skipped, 7U);  // 0 reads as 1
}

TEST(MissionEventLog, AskingBeyondTheNewestWaitsThereForThatNumber) {
  MissionEventLog log;
  log.append(added(0));

  const auto page = log.read(7, 10);

  EXPECT_TRUE(page.events.empty());
  EXPECT_EQ(page.skipped, 0U);
  EXPECT_EQ(page.next, 7U);
}

}  // namespace
}  // namespace cvislam::server
