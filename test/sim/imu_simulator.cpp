#include "test/sim/imu_simulator.hpp"

#include <cmath>

namespace cvislam::sim {

Eigen::Vector3d specificForce(const KinematicState& state) {
  const Eigen::Vector3d g_w(0.0, 0.0, -kGravityMps2);
  return state.T_w_b.so3().inverse() * (state.a_w - g_w);
}

ImuSimulator::ImuSimulator(const dataset::ImuCalibration& calibration, const ImuSimulatorOptions& options,
                           std::uint64_t seed)
    : calibration_(calibration), options_(options), rng_(seed), dt_s_(1.0 / calibration.rate_hz) {
  if (options_.noise) {
    for (int i = 0; i < 3; ++i) gyro_bias_(i) = options_.initial_gyro_bias_sigma * rng_.normal();
    for (int i = 0; i < 3; ++i) accel_bias_(i) = options_.initial_accel_bias_sigma * rng_.normal();
  }
}

void ImuSimulator::step(const KinematicState& state, std::int64_t t_ns, dataset::ImuSample& sample,
                        dataset::GroundTruthState& ground_truth) {
  sample.t_ns = t_ns;
  sample.gyro_s = state.omega_b + gyro_bias_;
  sample.accel_s = specificForce(state) + accel_bias_;
  ground_truth.t_ns = t_ns;
  ground_truth.T_w_b = state.T_w_b;
  ground_truth.v_w = state.v_w;
  ground_truth.gyro_bias = gyro_bias_;
  ground_truth.accel_bias = accel_bias_;
  ground_truth.has_velocity_and_biases = true;
  if (!options_.noise) return;
  const double sqrt_rate = 1.0 / std::sqrt(dt_s_);
  const double sqrt_dt = std::sqrt(dt_s_);
  for (int i = 0; i < 3; ++i) sample.gyro_s(i) += calibration_.gyro_noise_density * sqrt_rate * rng_.normal();
  for (int i = 0; i < 3; ++i) sample.accel_s(i) += calibration_.accel_noise_density * sqrt_rate * rng_.normal();
  for (int i = 0; i < 3; ++i) gyro_bias_(i) += calibration_.gyro_random_walk * sqrt_dt * rng_.normal();
  for (int i = 0; i < 3; ++i) accel_bias_(i) += calibration_.accel_random_walk * sqrt_dt * rng_.normal();
}

SimulatedImu simulateImu(const BodyTrajectory& trajectory, double end_s, const dataset::ImuCalibration& calibration,
                         const ImuSimulatorOptions& options, std::uint64_t seed) {
  ImuSimulator simulator(calibration, options, seed);
  const auto period_ns = static_cast<std::int64_t>(std::llround(1e9 / calibration.rate_hz));
  SimulatedImu out;
  for (std::int64_t t_ns = 0; static_cast<double>(t_ns) * 1e-9 <= end_s + 1e-12; t_ns += period_ns) {
    dataset::ImuSample sample;
    dataset::GroundTruthState state;
    simulator.step(trajectory.state(static_cast<double>(t_ns) * 1e-9), t_ns, sample, state);
    out.imu.push_back(sample);
    out.ground_truth.push_back(state);
  }
  return out;
}

}  // namespace cvislam::sim
