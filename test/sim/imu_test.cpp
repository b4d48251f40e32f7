// With noise off, integrating the simulated IMU reproduces the ground-truth increments to numerical precision;
// with noise on, the noise has the EuRoC figures.
#include "test/sim/imu_simulator.hpp"

#include <cmath>
#include <iomanip>
#include <sstream>
#include <vector>

#include <gtest/gtest.h>

#include "common/camera/camera_model.hpp"
#include "common/dataset/euroc.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::sim {
namespace {

struct NavState {
  Eigen::Quaterniond q_w_b = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
};

struct Derivative {
  Eigen::Vector4d dq;  // quaternion coefficients (x, y, z, w)
  Eigen::Vector3d dv;
  Eigen::Vector3d dp;
};

Derivative rates(const NavState& x, const Eigen::Vector3d& gyro, const Eigen::Vector3d& accel) {
  const Eigen::Quaterniond omega(0.0, gyro.x(), gyro.y(), gyro.z());
  Derivative d;
  d.dq = 0.5 * (x.q_w_b * omega).coeffs();
  d.dv = x.q_w_b * accel + Eigen::Vector3d(0.0, 0.0, -kGravityMps2);
  d.dp = x.v_w;
  return d;
}

NavState advance(const NavState& x, const Derivative& d, double h) {
  NavState y;
  y.q_w_b.coeffs() = x.q_w_b.coeffs() + h * d.dq;
  y.v_w = x.v_w + h * d.dv;
  y.p_w = x.p_w + h * d.dp;
  return y;
}

// Classic RK4 over the IMU samples; the readings at the half step come from cubic interpolation of the
// four surrounding samples. Both are fourth order, so at 200 Hz the result is exact to ~1e-9.
NavState integrate(const std::vector<dataset::ImuSample>& imu, std::size_t first, std::size_t last, NavState x) {
  for (std::size_t k = first; k < last; ++k) {
    const double h = static_cast<double>(imu[k + 1].t_ns - imu[k].t_ns) * 1e-9;
    const auto mid = [&](auto member) {
      return Eigen::Vector3d(
          (-(imu[k - 1].*member) + 9.0 * (imu[k].*member) + 9.0 * (imu[k + 1].*member) - (imu[k + 2].*member)) / 16.0);
    };
    const Eigen::Vector3d gyro_mid = mid(&dataset::ImuSample::gyro_s);
    const Eigen::Vector3d accel_mid = mid(&dataset::ImuSample::accel_s);
    const Derivative k1 = rates(x, imu[k].gyro_s, imu[k].accel_s);
    const Derivative k2 = rates(advance(x, k1, 0.5 * h), gyro_mid, accel_mid);
    const Derivative k3 = rates(advance(x, k2, 0.5 * h), gyro_mid, accel_mid);
    const Derivative k4 = rates(advance(x, k3, h), imu[k + 1].gyro_s, imu[k + 1].accel_s);
    Derivative sum;
    sum.dq = (k1.dq + 2.0 * k2.dq + 2.0 * k3.dq + k4.dq) / 6.0;
    sum.dv = (k1.dv + 2.0 * k2.dv + 2.0 * k3.dv + k4.dv) / 6.0;
    sum.dp = (k1.dp + 2.0 * k2.dp + 2.0 * k3.dp + k4.dp) / 6.0;
    x = advance(x, sum, h);
    x.q_w_b.normalize();
  }
  return x;
}

NavState fromGroundTruth(const dataset::GroundTruthState& gt) {
  NavState x;
  x.q_w_b = gt.T_w_b.quaternion();
  x.v_w = gt.v_w;
  x.p_w = gt.T_w_b.translation();
  return x;
}

struct IncrementErrors {
  double rotation_rad = 0.0;
  double velocity_mps = 0.0;
  double position_m = 0.0;
};

// Integrates one-second windows from the ground truth and compares with the ground truth at their ends.
IncrementErrors worstIncrementError(const std::vector<dataset::ImuSample>& imu,
                                    const std::vector<dataset::GroundTruthState>& gt) {
  EXPECT_EQ(imu.size(), gt.size());
  IncrementErrors worst;
  constexpr std::size_t kWindow = 200;  // 1 s at 200 Hz
  for (std::size_t first = 1; first + kWindow + 2 < imu.size(); first += 50) {
    EXPECT_EQ(imu[first].t_ns, gt[first].t_ns);
    const std::size_t last = first + kWindow;
    const NavState x = integrate(imu, first, last, fromGroundTruth(gt[first]));
    const NavState truth = fromGroundTruth(gt[last]);
    worst.rotation_rad = std::max(worst.rotation_rad, truth.q_w_b.angularDistance(x.q_w_b));
    worst.velocity_mps = std::max(worst.velocity_mps, (truth.v_w - x.v_w).norm());
    worst.position_m = std::max(worst.position_m, (truth.p_w - x.p_w).norm());
  }
  return worst;
}

// Precision over one second of integration at 200 Hz; a wrong gravity, frame or sign is off by centimetres.
constexpr double kMaxRotationErrorRad = 1e-7;
constexpr double kMaxVelocityErrorMps = 1e-6;
constexpr double kMaxPositionErrorM = 1e-6;

TEST(SimulatedImu, NoiseFreeReadingsWrittenToDiskIntegrateToTheGroundTruth) {
  const test::TempDir dir;
  MissionPlanOptions plan_options;
  plan_options.preset = "loop";
  plan_options.seed = 3;
  plan_options.duration_s = 3.0;
  auto plan = planMission(plan_options);
  ASSERT_TRUE(plan.ok()) << plan.error().toString();
  MissionWriterOptions options = defaultWriterOptions();
  options.out_dir = dir.path();
  options.imu_options.noise = false;
  options.texture.texel_size_m = 0.04;  // the images do not matter here
  ASSERT_TRUE(writeMission(*plan, options).ok());

  auto seq = dataset::EurocSequence::open(dir / "agent0");
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  for (const dataset::GroundTruthState& s : seq->groundTruth()) {
    ASSERT_TRUE(s.has_velocity_and_biases);
    ASSERT_EQ(s.gyro_bias.norm() + s.accel_bias.norm(), 0.0);
  }
  const IncrementErrors e = worstIncrementError(seq->imu(), seq->groundTruth());
  EXPECT_LT(e.rotation_rad, kMaxRotationErrorRad);
  EXPECT_LT(e.velocity_mps, kMaxVelocityErrorMps);
  EXPECT_LT(e.position_m, kMaxPositionErrorM);
  std::ostringstream figures;
  figures << std::scientific << std::setprecision(2) << "rotation " << e.rotation_rad << " rad, velocity "
          << e.velocity_mps << " m/s, position " << e.position_m << " m";
  RecordProperty("worst_1s_increment_error", figures.str());
}

// In memory, for every synthetic preset, including the aggressive one.
TEST(SimulatedImu, NoiseFreeReadingsIntegrateToTheGroundTruthForEveryPreset) {
  for (const char* preset : {"loop", "overlap2", "hall4", "aggressive"}) {
    MissionPlanOptions plan_options;
    plan_options.preset = preset;
    plan_options.seed = 11;
    plan_options.duration_s = 8.0;
    auto plan = planMission(plan_options);
    ASSERT_TRUE(plan.ok()) << plan.error().toString();
    ImuSimulatorOptions imu_options;
    imu_options.noise = false;
    const dataset::ImuCalibration calibration = dataset::eurocImu();
    for (const AgentPlan& agent : plan->agents) {
      const SimulatedImu sut = simulateImu(agent.trajectory, 8.0, calibration, imu_options, 1);
      const IncrementErrors e = worstIncrementError(sut.imu, sut.ground_truth);
      EXPECT_LT(e.rotation_rad, kMaxRotationErrorRad) << preset << " " << agent.name;
      EXPECT_LT(e.velocity_mps, kMaxVelocityErrorMps) << preset << " " << agent.name;
      EXPECT_LT(e.position_m, kMaxPositionErrorM) << preset << " " << agent.name;
    }
  }
}

TEST(SimulatedImu, NoiseAndBiasRandomWalkHaveTheEurocFigures) {
  const dataset::ImuCalibration calibration = dataset::eurocImu();
  ImuSimulator sut(calibration, ImuSimulatorOptions{}, 99);
  ImuSimulatorOptions exact_options;
  exact_options.noise = false;
  ImuSimulator exact(calibration, exact_options, 99);
  KinematicState still;  // hovering: exact readings are (0, 0, 0) and (g along world z in body)
  constexpr int kSamples = 40000;
  double gyro_sq = 0.0, accel_sq = 0.0;
  Eigen::Vector3d first_gyro_bias = Eigen::Vector3d::Zero(), first_accel_bias = Eigen::Vector3d::Zero();
  Eigen::Vector3d last_gyro_bias = Eigen::Vector3d::Zero(), last_accel_bias = Eigen::Vector3d::Zero();
  for (int k = 0; k < kSamples; ++k) {
    dataset::ImuSample noisy, ideal;
    dataset::GroundTruthState gt, gt_ideal;
    sut.step(still, k, noisy, gt);
    exact.step(still, k, ideal, gt_ideal);
    gyro_sq += (noisy.gyro_s - ideal.gyro_s - gt.gyro_bias).squaredNorm();
    accel_sq += (noisy.accel_s - ideal.accel_s - gt.accel_bias).squaredNorm();
    if (k == 0) {
      first_gyro_bias = gt.gyro_bias;
      first_accel_bias = gt.accel_bias;
    }
    last_gyro_bias = gt.gyro_bias;
    last_accel_bias = gt.accel_bias;
  }
  const double rate = calibration.rate_hz;
  const double gyro_sigma = std::sqrt(gyro_sq / (3.0 * kSamples));
  const double accel_sigma = std::sqrt(accel_sq / (3.0 * kSamples));
  EXPECT_NEAR(gyro_sigma, calibration.gyro_noise_density * std::sqrt(rate), 0.02 * gyro_sigma);
  EXPECT_NEAR(accel_sigma, calibration.accel_noise_density * std::sqrt(rate), 0.02 * accel_sigma);
  EXPECT_GT(first_gyro_bias.norm(), 0.0);
  EXPECT_GT(first_accel_bias.norm(), 0.0);
  // Over 200 s the walk moves the bias by about sigma_b * sqrt(200 s) per axis; it must have moved.
  EXPECT_GT((last_gyro_bias - first_gyro_bias).norm(), 0.1 * calibration.gyro_random_walk * std::sqrt(200.0));
  EXPECT_GT((last_accel_bias - first_accel_bias).norm(), 0.1 * calibration.accel_random_walk * std::sqrt(200.0));
}

}  // namespace
}  // namespace cvislam::sim
