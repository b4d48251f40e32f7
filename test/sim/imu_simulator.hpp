// IMU readings from a trajectory's exact kinematics, with the discrete-time noise model of Kalibr/EuRoC:
//   gyro  = omega_b + b_g + n_g,                 n_g ~ N(0, sigma_g^2 / dt)
//   accel = R_w_b^T (a_w - g_w) + b_a + n_a,     n_a ~ N(0, sigma_a^2 / dt),   g_w = (0, 0, -9.81)
//   b(k+1) = b(k) + sqrt(dt) sigma_b w(k),       w ~ N(0, I)
// The true biases go into the ground truth.
#pragma once

#include <cstdint>
#include <vector>

#include "common/dataset/types.hpp"
#include "test/sim/random.hpp"
#include "test/sim/trajectory.hpp"

namespace cvislam::sim {

inline constexpr double kGravityMps2 = 9.81;

struct ImuSimulatorOptions {
  bool noise = true;                       // white noise and bias random walk; off: exact readings, zero bias
  double initial_gyro_bias_sigma = 2e-3;   // [rad/s], drawn once per agent
  double initial_accel_bias_sigma = 2e-2;  // [m/s^2]
};

class ImuSimulator {
 public:
  ImuSimulator(const dataset::ImuCalibration& calibration, const ImuSimulatorOptions& options, std::uint64_t seed);

  // The reading and the ground-truth state at one IMU tick; advances the bias random walk by one period.
  void step(const KinematicState& state, std::int64_t t_ns, dataset::ImuSample& sample,
            dataset::GroundTruthState& ground_truth);

 private:
  dataset::ImuCalibration calibration_;
  ImuSimulatorOptions options_;
  Rng rng_;
  double dt_s_;
  Eigen::Vector3d gyro_bias_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d accel_bias_ = Eigen::Vector3d::Zero();
};

// Readings and ground truth at every IMU tick of [0, end_s], stamped from 0 ns, held in memory (for tests that
// need the IMU of a flight without writing a dataset).
struct SimulatedImu {
  std::vector<dataset::ImuSample> imu;
  std::vector<dataset::GroundTruthState> ground_truth;
};
SimulatedImu simulateImu(const BodyTrajectory& trajectory, double end_s, const dataset::ImuCalibration& calibration,
                         const ImuSimulatorOptions& options, std::uint64_t seed);

// The noise-free specific force and angular rate in the body (IMU) frame.
Eigen::Vector3d specificForce(const KinematicState& state);

}  // namespace cvislam::sim
