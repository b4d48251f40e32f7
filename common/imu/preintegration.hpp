// On-manifold IMU preintegration between two keyframes, after Forster, Carlone, Dellaert and Scaramuzza,
// "On-Manifold Preintegration for Real-Time Visual-Inertial Odometry", IEEE T-RO 2017 (CVI-SLAM Eq. 4-8).
//
// Frames and conventions (see common/geometry/lie.hpp): s is the IMU (sensor) frame, w the gravity-aligned
// world; R_w_s, p_w (position of s in w), v_w. Gravity g_w = (0, 0, -9.81) by default. Raw measurements are
// gyro_s = w_s + b_g + n_g and accel_s = R_w_s^T (a_w - g_w) + b_a + n_a.
//
// Between keyframes i and j the preintegrated deltas, computed with the biases frozen at the linearisation
// point b_lin, are
//   dR = R_w_si^T R_w_sj
//   dv = R_w_si^T (v_wj - v_wi - g_w dt)
//   dp = R_w_si^T (p_wj - p_wi - v_wi dt - 1/2 g_w dt^2)
// integrate() holds a reading constant over its interval, as in Forster's scheme, but the acceleration is rotated
// with the delta rotation at the middle of the interval rather than at its start, which removes Euler's
// first-order error (see integrate()). The covariance of the
// deltas' errors is propagated in the order [dphi, dv, dp] (right perturbation of dR) from the continuous
// noise densities; the Jacobians with respect to the biases give the first-order correction for a new bias
// estimate without re-integration (Forster Eq. 44, CVI-SLAM Eq. 7).
//
// Everything is fixed-size: integrate() does not allocate, so the agent's tracking loop can call it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::imu {

using Mat9 = Eigen::Matrix<double, 9, 9>;

// Continuous-time IMU noise (Kalibr's definitions, as in EuRoC's imu0/sensor.yaml).
struct ImuNoise {
  double gyro_noise_density = 1.6968e-4;  // [rad/s/sqrt(Hz)]
  double accel_noise_density = 2.0e-3;    // [m/s^2/sqrt(Hz)]
  double gyro_random_walk = 1.9393e-5;    // [rad/s^2/sqrt(Hz)]
  double accel_random_walk = 3.0e-3;      // [m/s^3/sqrt(Hz)]

  static ImuNoise fromCalibration(const dataset::ImuCalibration& calibration);
  // All densities positive and finite; the message names the bad field.
  [[nodiscard]] Status validate() const;
};

struct ImuBias {
  Eigen::Vector3d gyro = Eigen::Vector3d::Zero();   // b_g [rad/s]
  Eigen::Vector3d accel = Eigen::Vector3d::Zero();  // b_a [m/s^2]
};

// A navigation state of the IMU frame: the quantities the deltas relate.
struct NavState {
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
};

inline const Eigen::Vector3d kGravityW(0.0, 0.0, -9.81);

class Preintegration {
 public:
  // Indices of the blocks of the 9x9 covariance.
  static constexpr int kRot = 0;
  static constexpr int kVel = 3;
  static constexpr int kPos = 6;

  Preintegration() = default;
  Preintegration(const ImuBias& bias_lin, const ImuNoise& noise) : bias_lin_(bias_lin), noise_(noise) {}

  // Starts again from identity deltas with a new linearisation bias.
  void reset(const ImuBias& bias_lin);

  // Adds one measurement held constant for dt_s seconds (dt_s > 0; a non-positive dt_s is ignored).
  void integrate(double dt_s, const Eigen::Vector3d& gyro_s, const Eigen::Vector3d& accel_s);

  // Integrates the samples covering [t0_ns, t1_ns]. Readings are instantaneous and taken as linear between
  // two samples: each piece between samples (cut at t0 and t1, so keyframe times need not coincide with IMU
  // times) is integrated with its mean value. Fails, naming the
  // times, when the samples do not cover the interval or leave a gap larger than max_gap_ns.
  Status integrateInterval(std::span<const dataset::ImuSample> samples, std::int64_t t0_ns, std::int64_t t1_ns,
                           std::int64_t max_gap_ns = 50'000'000);

  [[nodiscard]] double dt() const { return dt_s_; }
  [[nodiscard]] int sampleCount() const { return sample_count_; }
  [[nodiscard]] const ImuBias& biasLin() const { return bias_lin_; }
  [[nodiscard]] const ImuNoise& noise() const { return noise_; }
  [[nodiscard]] const geometry::SO3d& deltaR() const { return delta_R_; }
  [[nodiscard]] const Eigen::Vector3d& deltaV() const { return delta_v_; }
  [[nodiscard]] const Eigen::Vector3d& deltaP() const { return delta_p_; }
  // Covariance of [dphi, dv, dp].
  [[nodiscard]] const Mat9& covariance() const { return covariance_; }

  [[nodiscard]] const Eigen::Matrix3d& dR_dbg() const { return dR_dbg_; }
  [[nodiscard]] const Eigen::Matrix3d& dv_dbg() const { return dv_dbg_; }
  [[nodiscard]] const Eigen::Matrix3d& dv_dba() const { return dv_dba_; }
  [[nodiscard]] const Eigen::Matrix3d& dp_dbg() const { return dp_dbg_; }
  [[nodiscard]] const Eigen::Matrix3d& dp_dba() const { return dp_dba_; }

  // The deltas corrected to first order for the bias `bias` (Forster Eq. 44).
  [[nodiscard]] geometry::SO3d correctedDeltaR(const ImuBias& bias) const;
  [[nodiscard]] Eigen::Vector3d correctedDeltaV(const ImuBias& bias) const;
  [[nodiscard]] Eigen::Vector3d correctedDeltaP(const ImuBias& bias) const;

  // The state at j predicted from the state at i, with the deltas corrected for `bias`.
  [[nodiscard]] NavState predict(const NavState& state_i, const ImuBias& bias,
                                 const Eigen::Vector3d& g_w = kGravityW) const;

 private:
  ImuBias bias_lin_;
  ImuNoise noise_;
  double dt_s_ = 0.0;
  int sample_count_ = 0;
  geometry::SO3d delta_R_;
  Eigen::Vector3d delta_v_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d delta_p_ = Eigen::Vector3d::Zero();
  Mat9 covariance_ = Mat9::Zero();
  Eigen::Matrix3d dR_dbg_ = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d dv_dbg_ = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d dv_dba_ = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d dp_dbg_ = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d dp_dba_ = Eigen::Matrix3d::Zero();
};

// The IMU at t_ns, past the newest of `samples` (oldest first), by the straight line that best fits the newest
// `fit_samples` of them (least squares, each axis on its own): for a short span of IMU that has not come yet, such as
// the few tens of ms by which a camera-IMU time offset moves a keyframe past it. The fit's span (35 ms at 200 Hz by
// default) averages the readings' noise down, as a line through the last two would not. With fewer samples than
// that, the newest is held. `samples` must not be empty.
dataset::ImuSample extrapolateImu(std::span<const dataset::ImuSample> samples, std::int64_t t_ns,
                                  std::size_t fit_samples = 8);

}  // namespace cvislam::imu
