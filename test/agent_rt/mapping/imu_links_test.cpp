// Mapping's IMU links around the camera-IMU time offset, on the mapper's own state with a ramp of IMU readings:
// a keyframe whose previous one was stamped before the first sample is linked with that sample held back to it, and
// a link that the IMU did not cover (a keyframe re-timed past the samples that had come) is integrated again once
// the kept samples cover it.
#include <cmath>
#include <cstdint>
#include <memory>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/mapping/imu_initialisation.hpp"
#include "agent_rt/mapping/mapper_state.hpp"
#include "common/dataset/euroc_calibration.hpp"

namespace cvislam::agent {
namespace {

constexpr std::int64_t kMs = 1'000'000;

// 200 Hz from t0_ns up to t1_ns, turning and speeding up, the acceleration not linear in time (so that an
// extrapolation of it is not exact).
std::vector<dataset::ImuSample> ramp(std::int64_t t0_ns, std::int64_t t1_ns) {
  std::vector<dataset::ImuSample> out;
  for (std::int64_t t = t0_ns; t <= t1_ns; t += 5 * kMs) {
    const double s = static_cast<double>(t) * 1e-9;
    out.push_back(
        {t, Eigen::Vector3d(0.3, -0.2 + s, 0.5), Eigen::Vector3d(1.0 + 8.0 * s + 60.0 * s * s, 0.1 - 3.0 * s, 9.81)});
  }
  return out;
}

class MapperImuLinks : public ::testing::Test {
 protected:
  MapperImuLinks() : camera_(makeCamera()) {
    options_.use_imu = true;
    options_.ba.estimate_time_offset = true;
    state_ = std::make_unique<Mapper::State>(options_, camera_, nullptr, geometry::SE3d(), geometry::SE3d());
  }

  static camera::CameraModel makeCamera() {
    auto camera = camera::CameraModel::create(dataset::eurocCam0());
    EXPECT_TRUE(camera.ok());
    return std::move(camera.value());
  }

  PoolHandle insert(std::uint32_t counter, std::int64_t t_ns) {
    auto kf = std::make_unique<KeyframeData>();
    kf->id = KeyframeId{0, counter};
    kf->t_ns = t_ns;
    auto h = state_->map.insertKeyframe(*kf);
    EXPECT_TRUE(h.ok());
    return *h;
  }

  KeyframeData& keyframe(PoolHandle h) { return *state_->map.keyframes().get(h); }

  imu::Preintegration integrated(std::int64_t t0_ns, std::int64_t t1_ns, const std::vector<dataset::ImuSample>& s) {
    imu::Preintegration p(imu::ImuBias{}, options_.ba.noise);
    EXPECT_TRUE(p.integrateInterval(s, t0_ns, t1_ns).ok());
    return p;
  }

  MapperOptions options_;
  camera::CameraModel camera_;
  std::unique_ptr<Mapper::State> state_;
};

TEST_F(MapperImuLinks, ALinkThatEndedPastTheSamplesIsIntegratedAgainOnceTheyCome) {
  const PoolHandle a = insert(1, 100 * kMs);
  const PoolHandle b = insert(2, 300 * kMs);
  // B was re-timed 25 ms past the newest sample it came with; its link so far ends on extrapolated IMU.
  state_->imu_history = ramp(0, 275 * kMs);
  std::vector<dataset::ImuSample> extended = state_->imu_history;
  extended.push_back(imu::extrapolateImu(state_->imu_history, 300 * kMs));
  keyframe(b).preintegration = integrated(100 * kMs, 300 * kMs, extended);
  keyframe(b).has_preintegration = true;
  keyframe(b).preintegration_from = keyframe(a).id;
  keyframe(b).preintegration_incomplete = true;
  const double first_dv = keyframe(b).preintegration.deltaV().x();

  completeImuLinks(*state_, state_->keyframesBySequence());  // the samples have not come: nothing to do
  EXPECT_TRUE(keyframe(b).preintegration_incomplete);
  EXPECT_EQ(keyframe(b).preintegration.deltaV().x(), first_dv);

  state_->imu_history = ramp(0, 500 * kMs);  // the next keyframe brought them
  completeImuLinks(*state_, state_->keyframesBySequence());
  const imu::Preintegration want = integrated(100 * kMs, 300 * kMs, state_->imu_history);
  ASSERT_GT(std::abs(want.deltaV().x() - first_dv), 1e-6);  // the extrapolation was not the truth
  EXPECT_FALSE(keyframe(b).preintegration_incomplete);
  EXPECT_TRUE(keyframe(b).has_preintegration);
  EXPECT_NEAR(keyframe(b).preintegration.dt(), 0.2, 1e-12);
  EXPECT_LT((keyframe(b).preintegration.deltaV() - want.deltaV()).norm(), 1e-12);
  EXPECT_LT((keyframe(b).preintegration.deltaP() - want.deltaP()).norm(), 1e-12);
  EXPECT_NEAR(keyframe(b).gyro_s.y(), -0.2 + 0.3, 1e-9);  // the reading at B's time
}

TEST_F(MapperImuLinks, AMissingLinkIsMadeOnceTheKeptSamplesCoverIt) {
  const PoolHandle a = insert(1, 100 * kMs);
  const PoolHandle b = insert(2, 300 * kMs);
  keyframe(b).preintegration_from = keyframe(a).id;
  keyframe(b).preintegration_incomplete = true;  // the IMU did not reach back to A when B came
  state_->imu_history = ramp(150 * kMs, 500 * kMs);
  completeImuLinks(*state_, state_->keyframesBySequence());
  EXPECT_FALSE(keyframe(b).has_preintegration);  // still not: the history starts after A
  EXPECT_TRUE(keyframe(b).preintegration_incomplete);
  state_->imu_history = ramp(0, 500 * kMs);
  completeImuLinks(*state_, state_->keyframesBySequence());
  EXPECT_TRUE(keyframe(b).has_preintegration);
  EXPECT_FALSE(keyframe(b).preintegration_incomplete);
}

TEST_F(MapperImuLinks, AKeyframeStampedBeforeTheFirstSampleIsLinkedWithinTheOffsetsBound) {
  state_->imu_history = ramp(100 * kMs, 500 * kMs);
  auto previous = std::make_unique<KeyframeData>();
  auto kf = std::make_unique<KeyframeData>();
  kf->t_ns = 300 * kMs;
  previous->t_ns = 70 * kMs;  // 30 ms before the first sample, within max_time_offset_s (100 ms)
  ASSERT_TRUE(linkFromBeforeFirstSample(*state_, *previous, *kf));
  EXPECT_NEAR(kf->preintegration.dt(), 0.230, 1e-12);  // the 30 ms before the first sample included
  previous->t_ns = -10 * kMs;                          // 110 ms before
  EXPECT_FALSE(linkFromBeforeFirstSample(*state_, *previous, *kf));
  previous->t_ns = 100 * kMs;  // covered: not this function's case
  EXPECT_FALSE(linkFromBeforeFirstSample(*state_, *previous, *kf));
}

}  // namespace
}  // namespace cvislam::agent
