// Tracking's side of the camera-IMU time offset: when mapping re-times the newest keyframe (the IMU initialisation
// moves the keyframes made before the estimate to their images' times), the IMU since that keyframe is integrated
// again from its new time, so the frames' inertial prediction starts where the keyframe's state now is; and the
// frames take a new estimate at once, a step back bounded so that their times stay in order.
#include <cmath>
#include <cstdint>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/tracking/tracker_state.hpp"

namespace cvislam::agent {
namespace {

constexpr std::int64_t kMs = 1'000'000;
constexpr std::int64_t kT0 = 1'000'000'000'000;  // the keyframe's time as tracking published it

class TrackerRetime : public ::testing::Test {
 protected:
  TrackerRetime() : s_(options_, makeOrb(), makeCamera(), nullptr, {}) {
    s_.has_keyframe = true;
    s_.keyframe.t_ns = kT0;
    // IMU at 200 Hz from 300 ms before the keyframe to 300 ms after it, turning and speeding up.
    for (std::int64_t t = kT0 - 300 * kMs; t <= kT0 + 300 * kMs; t += 5 * kMs) {
      const double s = static_cast<double>(t - kT0) * 1e-9;
      imu_.push_back({t, Eigen::Vector3d(0.3, -0.2 + s, 0.5), Eigen::Vector3d(1.0 + 2.0 * s, 0.1, 9.81)});
    }
    s_.appendImu(imu_);
    s_.restartKeyframeImu(kT0);
    // Tracked up to a frame 100 ms after the keyframe.
    s_.last_t_ns = kT0 + 100 * kMs;
    s_.pre_keyframe.reset(s_.bias);
    EXPECT_TRUE(s_.pre_keyframe.integrateInterval(imu_, kT0, s_.last_t_ns).ok());
    s_.pre_keyframe_end_ns = s_.last_t_ns;
  }

  static camera::CameraModel makeCamera() {
    auto camera = camera::CameraModel::create(dataset::CameraCalibration{});
    EXPECT_TRUE(camera.ok());
    return std::move(camera.value());
  }

  static features::OrbExtractor makeOrb() {
    auto orb = features::OrbExtractor::create(features::OrbOptions{}.forImageSize(752, 480));
    EXPECT_TRUE(orb.ok());
    return std::move(orb.value());
  }

  // What the IMU between t0 and t1 integrates to, from the samples directly.
  imu::Preintegration expected(std::int64_t t0_ns, std::int64_t t1_ns) const {
    imu::Preintegration p(s_.bias, options_.noise);
    EXPECT_TRUE(p.integrateInterval(imu_, t0_ns, t1_ns).ok());
    return p;
  }

  TrackerOptions options_;
  std::vector<dataset::ImuSample> imu_;
  Tracker::State s_;
};

TEST_F(TrackerRetime, AKeyframeMovedEarlierIsIntegratedAgainFromItsNewTime) {
  s_.retimeNewestKeyframe(kT0 - 20 * kMs);
  const imu::Preintegration want = expected(kT0 - 20 * kMs, kT0 + 100 * kMs);
  EXPECT_TRUE(s_.imu_ok_since_keyframe);
  EXPECT_EQ(s_.keyframe.t_ns, kT0 - 20 * kMs);
  EXPECT_EQ(s_.pre_keyframe_end_ns, kT0 + 100 * kMs);
  EXPECT_NEAR(s_.pre_keyframe.dt(), 0.120, 1e-12);
  EXPECT_LT((s_.pre_keyframe.deltaP() - want.deltaP()).norm(), 1e-12);
  EXPECT_LT((s_.pre_keyframe.deltaV() - want.deltaV()).norm(), 1e-12);
  EXPECT_LT((s_.pre_keyframe.deltaR().inverse() * want.deltaR()).log().norm(), 1e-12);
  // The next keyframe message carries the IMU from the new time on.
  EXPECT_LE(s_.keyframe_imu[s_.keyframe_imu_first].t_ns, kT0 - 20 * kMs);
}

TEST_F(TrackerRetime, AKeyframeMovedLaterIsIntegratedAgainFromItsNewTime) {
  s_.retimeNewestKeyframe(kT0 + 30 * kMs);
  const imu::Preintegration want = expected(kT0 + 30 * kMs, kT0 + 100 * kMs);
  EXPECT_TRUE(s_.imu_ok_since_keyframe);
  EXPECT_NEAR(s_.pre_keyframe.dt(), 0.070, 1e-12);
  EXPECT_LT((s_.pre_keyframe.deltaP() - want.deltaP()).norm(), 1e-12);
}

TEST_F(TrackerRetime, AKeyframeMovedPastTheLastFrameWaitsForTheNextFrame) {
  s_.retimeNewestKeyframe(kT0 + 130 * kMs);
  EXPECT_TRUE(s_.imu_ok_since_keyframe);
  EXPECT_EQ(s_.pre_keyframe.dt(), 0.0);
  EXPECT_EQ(s_.pre_keyframe_end_ns, kT0 + 130 * kMs);  // the next frame integrates from here
}

TEST_F(TrackerRetime, AKeyframeMovedBeforeTheKeptImuGoesWithoutIt) {
  // 100 ms of IMU are kept before a keyframe; 150 ms earlier is beyond them.
  s_.retimeNewestKeyframe(kT0 - 150 * kMs);
  EXPECT_FALSE(s_.imu_ok_since_keyframe);
}

TEST_F(TrackerRetime, FramesTakeANewEstimateAtOnceAndStepBackAtMostHalfAFrameInterval) {
  s_.camera_interval_ns = 50 * kMs;
  s_.time_correction_target_ns = 30 * kMs;
  EXPECT_EQ(s_.nextTimeCorrectionNs(), 30 * kMs);
  s_.time_correction_target_ns = -20 * kMs;
  EXPECT_EQ(s_.nextTimeCorrectionNs(), 5 * kMs);  // 25 ms back, half of 50
  EXPECT_EQ(s_.nextTimeCorrectionNs(), -20 * kMs);
  // Before any frame interval is known: the fixed bound.
  s_.camera_interval_ns = 0;
  s_.time_correction_target_ns = -40 * kMs;
  EXPECT_EQ(s_.nextTimeCorrectionNs(), -20 * kMs - Tracker::kMaxTimeCorrectionStepBackNs);
}

}  // namespace
}  // namespace cvislam::agent
