// The pushed feed (the embedding API's input) as tracking sees it: frame times on the IMU's clock, with the
// calibrated offset and the estimated correction tracking hands it, and each frame's IMU interval ending there.
#include "agent_rt/runtime/push_feed.hpp"

#include <array>
#include <cstdint>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

constexpr int kWidth = 8;
constexpr int kHeight = 4;

PushFeedOptions smallFeed() {
  PushFeedOptions o;
  o.width = kWidth;
  o.height = kHeight;
  o.timeshift_cam_imu_ns = 2'000'000;  // calibrated: t_imu = t_cam + 2 ms
  o.imu_wait_s = 0.0;
  return o;
}

void pushImuEvery5Ms(PushFeed& feed, std::int64_t from_ns, std::int64_t to_ns) {
  for (std::int64_t t = from_ns; t <= to_ns; t += 5'000'000) {
    dataset::ImuSample s;
    s.t_ns = t;
    ASSERT_TRUE(feed.pushImu(s));
  }
}

TEST(PushFeed, FrameTimesCarryTheCalibratedOffsetAndTheCorrectionAndTheirImuEndsThere) {
  PushFeed feed(smallFeed());
  const std::array<std::uint8_t, kWidth * kHeight> pixels{};
  pushImuEvery5Ms(feed, 0, 200'000'000);
  ASSERT_TRUE(feed.pushFrame(50'000'000, pixels.data(), nullptr));
  ASSERT_TRUE(feed.pushFrame(100'000'000, pixels.data(), nullptr));

  const FeedFrame* first = feed.next();
  ASSERT_NE(first, nullptr);
  EXPECT_EQ(first->t_ns, 52'000'000);
  EXPECT_EQ(first->time_correction_ns, 0);
  feed.release();

  feed.setTimeCorrection(13'000'000);  // the estimate says the camera is 13 ms further behind
  const FeedFrame* second = feed.next();
  ASSERT_NE(second, nullptr);
  EXPECT_EQ(second->t_ns, 115'000'000);
  EXPECT_EQ(second->time_correction_ns, 13'000'000);
  // From the last sample at or before the previous frame (52 ms: 50) to the first at or after this one (115 ms).
  ASSERT_FALSE(second->imu.empty());
  EXPECT_EQ(second->imu.front().t_ns, 50'000'000);
  EXPECT_EQ(second->imu.back().t_ns, 115'000'000);
  feed.release();
}

}  // namespace
}  // namespace cvislam::agent
