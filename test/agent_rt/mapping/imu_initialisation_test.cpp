// The monocular IMU initialisation's timing, on the mapper's own state: keyframes of a simulated flight, their poses
// up to a visual scale, linked by the simulated IMU. From imu_init_min_keyframes on it is tried at every keyframe and
// made once three attempts in a row agree on the scale; at imu_init_keyframes it is made whatever they said. An
// attempt that waits says why in the keyframe's mapper note.
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/mapping/imu_initialisation.hpp"
#include "agent_rt/mapping/mapper_state.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "test/sim/imu_simulator.hpp"
#include "test/sim/presets.hpp"

namespace cvislam::agent {
namespace {

constexpr double kVisualScale = 0.37;                      // visual = metric * kVisualScale
constexpr std::int64_t kKeyframeIntervalNs = 150'000'000;  // 3 frames at 20 Hz, as before the IMU initialisation
constexpr std::int64_t kImuPeriodNs = 5'000'000;
constexpr std::int64_t kStartNs = 500'000'000;

class ImuInitialisationTiming : public ::testing::Test {
 protected:
  ImuInitialisationTiming() : camera_(makeCamera()) {
    options_.use_imu = true;
    options_.imu_init_keyframes = 15;
    options_.imu_init_min_keyframes = 10;
  }

  static camera::CameraModel makeCamera() {
    auto camera = camera::CameraModel::create(dataset::eurocCam0());
    EXPECT_TRUE(camera.ok());
    return std::move(camera.value());
  }

  // The flight's IMU (EuRoC-grade noise when `noise`) and its true states, 4 s from kStartNs on.
  void simulate(bool noise, bool stereo = false) {
    auto plan = sim::planPreset("loop", 3, 5.0);
    ASSERT_TRUE(plan.ok()) << plan.error().toString();
    sim::ImuSimulatorOptions imu_options;
    imu_options.noise = noise;
    simulated_ = sim::simulateImu(plan->agents.front().trajectory, 4.5, dataset::eurocImu(), imu_options, 3);
    visual_scale_ = stereo ? 1.0 : kVisualScale;
    state_ = std::make_unique<Mapper::State>(options_, camera_, stereo ? &camera_ : nullptr, dataset::eurocCam0().T_b_c,
                                             geometry::SE3d());
  }

  // Keyframe `counter` as the map has it: its pose in the first keyframe's frame with the visual scale, and
  // its IMU link from the keyframe before.
  void addKeyframe(std::uint32_t counter) {
    const std::int64_t t_ns = kStartNs + static_cast<std::int64_t>(counter) * kKeyframeIntervalNs;
    const auto state_at = [&](std::int64_t t) {
      return simulated_.ground_truth[static_cast<std::size_t>(t / kImuPeriodNs)];
    };
    const geometry::SE3d T_v_w = state_at(kStartNs).T_w_b.inverse();
    const geometry::SE3d T_v_s = T_v_w * state_at(t_ns).T_w_b;
    auto kf = std::make_unique<KeyframeData>();
    kf->id = KeyframeId{0, counter};
    kf->t_ns = t_ns;
    kf->T_w_s = geometry::SE3d(T_v_s.so3(), visual_scale_ * T_v_s.translation());
    kf->gyro_s = simulated_.imu[static_cast<std::size_t>(t_ns / kImuPeriodNs)].gyro_s;
    if (counter > 0) {
      kf->has_preintegration = true;
      kf->preintegration_from = KeyframeId{0, counter - 1};
      kf->preintegration = imu::Preintegration(imu::ImuBias{}, options_.ba.noise);
      ASSERT_TRUE(kf->preintegration.integrateInterval(simulated_.imu, t_ns - kKeyframeIntervalNs, t_ns).ok());
    }
    ASSERT_TRUE(state_->map.insertKeyframe(*kf).ok());
  }

  // Adds keyframes and tries the initialisation after each, as mapping does; returns the count it succeeded at
  // (0: not by 15).
  int keyframesAtInitialisation() {
    for (std::uint32_t counter = 0; counter < 15; ++counter) {
      addKeyframe(counter);
      MapperReport report;
      const Status status = initialiseImu(*state_, report);
      if (status.ok()) return static_cast<int>(counter) + 1;
      EXPECT_EQ(status.error().code(), ErrorCode::kNotFound) << status.error().toString();
      EXPECT_FALSE(report.imu_initialisation_failed);
    }
    return 0;
  }

  MapperOptions options_;
  camera::CameraModel camera_;
  sim::SimulatedImu simulated_;
  double visual_scale_ = kVisualScale;
  std::unique_ptr<Mapper::State> state_;
};

TEST_F(ImuInitialisationTiming, ASettledScaleInitialisesAfterThreeAgreeingAttempts) {
  simulate(/*noise=*/false);
  EXPECT_EQ(keyframesAtInitialisation(), 12);
  EXPECT_TRUE(state_->imu_initialised);
}

TEST_F(ImuInitialisationTiming, AScaleThatStillMovesWaitsForTheFullCount) {
  // With EuRoC-grade noise the attempts' scales differ by a little: no agreement asked for that closely is met.
  options_.imu_init_scale_agreement = 1e-6;
  simulate(/*noise=*/true);
  EXPECT_EQ(keyframesAtInitialisation(), 15);
}

TEST_F(ImuInitialisationTiming, AnAttemptThatWaitsSaysWhyInTheKeyframesNote) {
  options_.imu_init_scale_agreement = 1e-6;
  simulate(/*noise=*/true);
  for (std::uint32_t counter = 0; counter < 12; ++counter) {
    addKeyframe(counter);
    MapperReport report;
    ASSERT_EQ(initialiseImu(*state_, report).error().code(), ErrorCode::kNotFound);
    const std::string& note = report.note;
    if (counter < 9) {
      EXPECT_TRUE(note.empty()) << "too few keyframes to try: " << note;
    } else if (counter == 9) {
      EXPECT_NE(note.find("IMU initialisation over 10 keyframes waits: scale "), std::string::npos) << note;
      EXPECT_NE(note.find("the two attempts before none and none"), std::string::npos) << note;
    } else if (counter == 11) {
      EXPECT_NE(note.find("IMU initialisation over 12 keyframes waits: scale "), std::string::npos) << note;
      EXPECT_EQ(note.find("none"), std::string::npos) << "both earlier attempts are there: " << note;
    }
  }
}

TEST_F(ImuInitialisationTiming, AnEarlyAttemptTheAlignmentRefusesSaysSoInTheKeyframesNote) {
  options_.alignment.min_scale_observability = 1e12;  // no motion shows the scale that well
  simulate(/*noise=*/false);
  for (std::uint32_t counter = 0; counter < 11; ++counter) {
    addKeyframe(counter);
    MapperReport report;
    ASSERT_EQ(initialiseImu(*state_, report).error().code(), ErrorCode::kNotFound);
    if (counter == 10) {
      EXPECT_NE(report.note.find("IMU initialisation over 11 keyframes refused ("), std::string::npos) << report.note;
      EXPECT_NE(report.note.find("tried again at the next keyframe"), std::string::npos) << report.note;
    }
  }
}

TEST_F(ImuInitialisationTiming, NoEarlierAttemptsWhenTheFirstIsAtTheFullCount) {
  options_.imu_init_min_keyframes = 15;
  simulate(/*noise=*/false);
  EXPECT_EQ(keyframesAtInitialisation(), 15);
}

TEST_F(ImuInitialisationTiming, AStereoMapKnowsItsScaleAndInitialisesAtItsCount) {
  options_.imu_init_keyframes = 13;
  simulate(/*noise=*/false, /*stereo=*/true);
  EXPECT_EQ(keyframesAtInitialisation(), 13);
}

}  // namespace
}  // namespace cvislam::agent
