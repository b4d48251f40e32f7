// IMU initialisation on the simulator's flights: up-to-scale camera poses in the first camera's frame plus
// the simulated IMU must give back the scale, gravity, velocities and gyroscope bias.
#include "common/imu/visual_inertial_alignment.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/euroc_calibration.hpp"
#include "test/sim/imu_simulator.hpp"
#include "test/sim/presets.hpp"

namespace cvislam::imu {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

constexpr double kTrueScale = 0.37;  // visual = metric * kTrueScale, as a monocular start would have it
constexpr int kKeyframes = 15;
constexpr std::int64_t kKeyframeIntervalNs = 150'000'000;  // 3 frames at 20 Hz, as the paper initialises

struct Scenario {
  std::vector<VisualKeyframe> keyframes;
  std::vector<Preintegration> preintegrations;
  SE3d T_s_c;
  std::vector<Vector3d> v_v_true;  // true velocities in the visual frame (first camera's axes)
  Vector3d g_v_true;
  Vector3d gyro_bias_true;
};

// `camera_delay_ns`: the images are taken this long after the keyframes' (IMU) times, as by a camera whose clock
// runs behind the IMU's; each keyframe carries the gyro at its time.
Scenario makeScenario(const std::string& preset, bool noise, double start_s, std::uint64_t seed,
                      std::int64_t camera_delay_ns = 0) {
  sim::MissionPlanOptions plan_options;
  plan_options.preset = preset;
  plan_options.seed = seed;
  plan_options.duration_s = start_s + 4.0;
  auto plan = sim::planMission(plan_options);
  EXPECT_TRUE(plan.ok()) << plan.error().toString();
  Scenario s;
  if (!plan.ok()) return s;
  const dataset::CameraCalibration cam0 = dataset::eurocCam0();
  s.T_s_c = cam0.T_b_c;
  sim::ImuSimulatorOptions imu_options;
  imu_options.noise = noise;
  constexpr std::int64_t kPeriodNs = 5'000'000;  // EuRoC's 200 Hz
  const auto start_ns = static_cast<std::int64_t>(start_s * 1e9);
  const std::int64_t end_ns =
      start_ns + kKeyframes * kKeyframeIntervalNs + kPeriodNs + std::max<std::int64_t>(camera_delay_ns, 0);
  const sim::SimulatedImu simulated = sim::simulateImu(
      plan->agents.front().trajectory, static_cast<double>(end_ns) * 1e-9, dataset::eurocImu(), imu_options, seed);
  const std::vector<dataset::ImuSample>& imu = simulated.imu;
  const std::vector<dataset::GroundTruthState>& gt = simulated.ground_truth;
  const auto state_at = [&](std::int64_t t_ns) { return gt[static_cast<std::size_t>(t_ns / kPeriodNs)]; };

  // The visual frame: the first keyframe's camera, with positions shrunk by kTrueScale.
  const SE3d T_w_c0 = state_at(start_ns).T_w_b * s.T_s_c;
  const SO3d R_c0_w = T_w_c0.so3().inverse();
  s.g_v_true = R_c0_w * Vector3d(0.0, 0.0, -9.81);
  s.gyro_bias_true = state_at(start_ns).gyro_bias;
  for (int k = 0; k < kKeyframes; ++k) {
    const std::int64_t t_ns = start_ns + k * kKeyframeIntervalNs;
    const dataset::GroundTruthState state = state_at(t_ns);
    const SE3d T_c0_c = T_w_c0.inverse() * state_at(t_ns + camera_delay_ns).T_w_b * s.T_s_c;
    const Vector3d omega_s = imu[static_cast<std::size_t>(t_ns / kPeriodNs)].gyro_s;
    s.keyframes.push_back({SE3d(T_c0_c.so3(), kTrueScale * T_c0_c.translation()), omega_s});
    s.v_v_true.push_back(R_c0_w * state.v_w);
    if (k > 0) {
      Preintegration pre(ImuBias{}, ImuNoise::fromCalibration(dataset::eurocImu()));
      EXPECT_TRUE(pre.integrateInterval(imu, t_ns - kKeyframeIntervalNs, t_ns).ok());
      s.preintegrations.push_back(pre);
    }
  }
  return s;
}

struct Errors {
  double scale_percent;
  double gravity_deg;
  double worst_velocity_mps;
  double gyro_bias;
};

Errors compare(const Scenario& s, const VisualInertialAlignment& a) {
  Errors e{};
  e.scale_percent = 100.0 * std::abs(a.scale * kTrueScale - 1.0);
  e.gravity_deg = std::acos(std::min(1.0, a.g_v.normalized().dot(s.g_v_true.normalized()))) * 180.0 / M_PI;
  for (std::size_t k = 0; k < a.v_w.size(); ++k) {
    const Vector3d v_v = a.R_w_v.inverse() * a.v_w[k];
    e.worst_velocity_mps = std::max(e.worst_velocity_mps, (v_v - s.v_v_true[k]).norm());
  }
  e.gyro_bias = (a.gyro_bias - s.gyro_bias_true).norm();
  std::printf("scale error %.3f %%, gravity %.3f deg, worst velocity %.4f m/s, gyro bias error %.2e rad/s\n",
              e.scale_percent, e.gravity_deg, e.worst_velocity_mps, e.gyro_bias);
  return e;
}

TEST(VisualInertialAlignment, RecoversScaleGravityAndVelocitiesFromExactData) {
  const Scenario s = makeScenario("loop", false, 0.5, 3);
  auto sut = alignVisualInertial(s.keyframes, s.preintegrations, s.T_s_c);
  ASSERT_TRUE(sut.ok()) << sut.error().toString();
  const Errors e = compare(s, *sut);
  EXPECT_LT(e.scale_percent, 0.1);
  EXPECT_LT(e.gravity_deg, 0.05);
  EXPECT_LT(e.worst_velocity_mps, 0.005);
  EXPECT_LT(e.gyro_bias, 1e-4);
  // The result is gravity-aligned: the world's gravity points down.
  EXPECT_LT((sut->R_w_v * sut->g_v - Vector3d(0.0, 0.0, -9.81)).norm(), 1e-9);
}

TEST(VisualInertialAlignment, WithEurocImuNoiseAndUnknownBiasesScaleIsWithinOnePercent) {
  for (const char* preset : {"loop", "aggressive", "overlap2"}) {
    for (const std::uint64_t seed : {1U, 2U, 3U}) {
      const Scenario s = makeScenario(preset, true, 0.5, seed);
      auto sut = alignVisualInertial(s.keyframes, s.preintegrations, s.T_s_c);
      ASSERT_TRUE(sut.ok()) << preset << " seed " << seed << ": " << sut.error().toString();
      std::printf("%s seed %llu: ", preset, static_cast<unsigned long long>(seed));
      const Errors e = compare(s, *sut);
      // The accelerometer bias (drawn with sigma 0.02 m/s^2) is not estimated at this stage; the paper's
      // target for the whole system is a scale error under 2 %.
      EXPECT_LT(e.scale_percent, 1.0) << preset << " seed " << seed;
      EXPECT_LT(e.gravity_deg, 0.5) << preset << " seed " << seed;
      EXPECT_LT(e.worst_velocity_mps, 0.05) << preset << " seed " << seed;
      EXPECT_LT(e.gyro_bias, 3e-4) << preset << " seed " << seed;
    }
  }
}

// The scale's standard deviation from the fit says how far the scale may be off: from exact data next to nothing,
// and with EuRoC-grade noise an error within three of it on every flight (the monocular start initialises early on
// it). Gentle motion observes scale worse than aggressive motion, and the sigma says so.
TEST(VisualInertialAlignment, TheScalesSigmaBoundsItsError) {
  const Scenario exact = makeScenario("loop", false, 0.5, 3);
  auto clean = alignVisualInertial(exact.keyframes, exact.preintegrations, exact.T_s_c);
  ASSERT_TRUE(clean.ok()) << clean.error().toString();
  EXPECT_LT(clean->scale_sigma_relative, 1e-4);
  double loop_sigma = 0.0;
  double aggressive_sigma = 0.0;
  for (const char* preset : {"loop", "aggressive", "overlap2"}) {
    for (const std::uint64_t seed : {1U, 2U, 3U, 4U, 5U}) {
      const Scenario s = makeScenario(preset, true, 0.5, seed);
      auto sut = alignVisualInertial(s.keyframes, s.preintegrations, s.T_s_c);
      ASSERT_TRUE(sut.ok()) << preset << " seed " << seed << ": " << sut.error().toString();
      const double error = std::abs(sut->scale * kTrueScale - 1.0);
      std::printf("%s seed %llu: scale error %.3f %%, sigma %.3f %%\n", preset, static_cast<unsigned long long>(seed),
                  100.0 * error, 100.0 * sut->scale_sigma_relative);
      EXPECT_GT(sut->scale_sigma_relative, 0.0) << preset << " seed " << seed;
      EXPECT_LE(error, 3.0 * sut->scale_sigma_relative) << preset << " seed " << seed;
      if (std::string(preset) == "loop") loop_sigma += sut->scale_sigma_relative;
      if (std::string(preset) == "aggressive") aggressive_sigma += sut->scale_sigma_relative;
    }
  }
  EXPECT_GT(loop_sigma, aggressive_sigma);
  // A known scale is not estimated, so it has no sigma.
  const Scenario s = makeScenario("loop", true, 0.5, 1);
  std::vector<VisualKeyframe> metric = s.keyframes;
  for (VisualKeyframe& kf : metric) kf.T_v_c.translation() /= kTrueScale;
  VisualInertialAlignmentOptions known;
  known.known_scale = 1.0;
  auto fixed = alignVisualInertial(metric, s.preintegrations, s.T_s_c, known);
  ASSERT_TRUE(fixed.ok()) << fixed.error().toString();
  EXPECT_EQ(fixed->scale_sigma_relative, 0.0);
}

// Images taken 30 ms (or -20 ms) after the IMU times: held at zero, the gyro bias absorbs the offset; estimated with
// it, the offset comes back to a tenth of a millisecond and the bias error shrinks five- to twentyfold. What is left
// (1e-3 rad/s, 2 % of scale at 30 ms, the same without noise) is the model's: it turns each keyframe at its rate at
// t_k over the whole offset, and the loop's angular acceleration over 30 ms is not in it. Local BA refines both.
TEST(VisualInertialAlignment, ACameraTimeOffsetIsEstimatedWithTheGyroBiasInsteadOfBiasingIt) {
  for (const std::int64_t delay_ns : {std::int64_t{30'000'000}, std::int64_t{-20'000'000}}) {
    for (const std::uint64_t seed : {1U, 2U}) {
      const Scenario s = makeScenario("loop", true, 0.5, seed, delay_ns);
      VisualInertialAlignmentOptions options;
      auto held = alignVisualInertial(s.keyframes, s.preintegrations, s.T_s_c, options);
      options.estimate_time_offset = true;
      auto estimated = alignVisualInertial(s.keyframes, s.preintegrations, s.T_s_c, options);
      ASSERT_TRUE(held.ok() && estimated.ok()) << "seed " << seed;
      const double held_bias_error = (held->gyro_bias - s.gyro_bias_true).norm();
      const double bias_error = (estimated->gyro_bias - s.gyro_bias_true).norm();
      const double td_error_ms = std::abs(estimated->time_correction_s * 1e9 - static_cast<double>(delay_ns)) * 1e-6;
      std::printf("delay %lld ms seed %llu: td error %.3f ms, gyro bias error %.2e (held at 0: %.2e) rad/s\n",
                  static_cast<long long>(delay_ns / 1'000'000), static_cast<unsigned long long>(seed), td_error_ms,
                  bias_error, held_bias_error);
      EXPECT_LT(td_error_ms, 0.2) << "seed " << seed;
      EXPECT_GT(held_bias_error, 5.0 * bias_error) << "seed " << seed;
      const Errors e = compare(s, *estimated);
      EXPECT_LT(e.scale_percent, 3.0) << "seed " << seed;
      EXPECT_LT(e.gravity_deg, 0.5) << "seed " << seed;
    }
  }
}

TEST(VisualInertialAlignment, AKnownScaleGivesGravityAndVelocitiesWithoutEstimatingIt) {
  // A stereo map knows its scale: gravity, velocities and gyro bias remain, which noisy IMU over the same
  // windows gives at least as well as with the scale free, and the scale comes back exactly as given.
  for (const char* preset : {"loop", "aggressive", "overlap2"}) {
    for (const std::uint64_t seed : {1U, 2U}) {
      const Scenario s = makeScenario(preset, true, 0.5, seed);
      VisualInertialAlignmentOptions options;
      options.known_scale = 1.0 / kTrueScale;
      auto sut = alignVisualInertial(s.keyframes, s.preintegrations, s.T_s_c, options);
      ASSERT_TRUE(sut.ok()) << preset << " seed " << seed << ": " << sut.error().toString();
      std::printf("%s seed %llu, known scale: ", preset, static_cast<unsigned long long>(seed));
      const Errors e = compare(s, *sut);
      EXPECT_EQ(sut->scale, 1.0 / kTrueScale);
      EXPECT_LT(e.gravity_deg, 0.5) << preset << " seed " << seed;
      EXPECT_LT(e.worst_velocity_mps, 0.05) << preset << " seed " << seed;
    }
  }
}

TEST(VisualInertialAlignment, AHoveringStartIsRefusedAsUnobservable) {
  // Standing still: no translation, so the scale is unobservable.
  std::vector<VisualKeyframe> keyframes;
  std::vector<Preintegration> preintegrations;
  std::vector<dataset::ImuSample> imu;
  const SO3d R_w_s = SO3d::exp(Vector3d(0.1, -0.2, 0.3));
  for (std::int64_t t_ns = 0; t_ns <= 2'000'000'000; t_ns += 5'000'000) {
    imu.push_back({t_ns, Vector3d::Zero(), R_w_s.inverse() * Vector3d(0.0, 0.0, 9.81)});
  }
  const SE3d T_s_c = dataset::eurocCam0().T_b_c;
  for (int k = 0; k < 10; ++k) {
    keyframes.push_back({SE3d(R_w_s, Vector3d::Zero()) * T_s_c});
    if (k > 0) {
      Preintegration pre(ImuBias{}, ImuNoise{});
      ASSERT_TRUE(pre.integrateInterval(imu, (k - 1) * kKeyframeIntervalNs, k * kKeyframeIntervalNs).ok());
      preintegrations.push_back(pre);
    }
  }
  auto sut = alignVisualInertial(keyframes, preintegrations, T_s_c);
  ASSERT_FALSE(sut.ok());
  EXPECT_EQ(sut.error().code(), ErrorCode::kDegenerate);
  EXPECT_NE(sut.error().message().find("waiting for more keyframes"), std::string::npos) << sut.error().message();

  // With the scale known (stereo), standing still observes gravity: the accelerometer alone gives it.
  VisualInertialAlignmentOptions known;
  known.known_scale = 1.0;
  auto stereo = alignVisualInertial(keyframes, preintegrations, T_s_c, known);
  ASSERT_TRUE(stereo.ok()) << stereo.error().toString();
  const Vector3d g_true = R_w_s.inverse() * Vector3d(0.0, 0.0, -9.81);  // v is the IMU's axes here
  const Vector3d g_v = (keyframes.front().T_v_c * T_s_c.inverse()).so3() * g_true;
  EXPECT_LT(std::acos(std::min(1.0, stereo->g_v.normalized().dot(g_v.normalized()))), 1e-3);
}

TEST(VisualInertialAlignment, InconsistentInputIsRefusedWithAMessage) {
  const Scenario s = makeScenario("loop", false, 0.5, 3);
  std::vector<Preintegration> too_few(s.preintegrations.begin(), s.preintegrations.end() - 1);
  auto sut = alignVisualInertial(s.keyframes, too_few, s.T_s_c);
  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("one preintegration between each pair"), std::string::npos);
  std::vector<VisualKeyframe> three(s.keyframes.begin(), s.keyframes.begin() + 3);
  EXPECT_FALSE(alignVisualInertial(three, {s.preintegrations[0], s.preintegrations[1]}, s.T_s_c).ok());
}

}  // namespace
}  // namespace cvislam::imu
