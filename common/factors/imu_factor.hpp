// The IMU preintegration factor between consecutive keyframes i and j (Forster Eq. 45, CVI-SLAM Eq. 8),
// and the bias random-walk factor that joins their biases.
#pragma once

#include <ceres/sized_cost_function.h>

#include "common/factors/state_layout.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::factors {

// Residual r = S [r_dR, r_dv, r_dp] (9), whitened by the triangular square-root information S of the
// preintegration covariance (S^T S = Sigma^-1):
//   r_dR = Log((dR Exp(dR_dbg db_g))^T R_i^T R_j)
//   r_dv = R_i^T (v_j - v_i - g dt) - (dv + dv_dbg db_g + dv_dba db_a)
//   r_dp = R_i^T (p_j - p_i - v_i dt - g dt^2 / 2) - (dp + dp_dbg db_g + dp_dba db_a)
// with db = bias_i - preintegration.biasLin(). Parameter blocks: pose_i (7), v_i (3), bias_i (6),
// pose_j (7), v_j (3). The bias of keyframe j enters only through the BiasRandomWalkFactor.
class ImuFactor final
    : public ceres::SizedCostFunction<9, kPoseSize, kVelocitySize, kBiasSize, kPoseSize, kVelocitySize> {
 public:
  explicit ImuFactor(const imu::Preintegration& preintegration, const Eigen::Vector3d& g_w = imu::kGravityW);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  imu::Preintegration preintegration_;
  Eigen::Vector3d g_w_;
  Eigen::Matrix<double, 9, 9> sqrt_information_;
};

// r = S (bias_j - bias_i), S = diag(1 / (sigma_bg sqrt(dt)), 1 / (sigma_ba sqrt(dt))): the biases drift as
// Brownian motion with the continuous random-walk densities. Parameter blocks: bias_i (6), bias_j (6).
class BiasRandomWalkFactor final : public ceres::SizedCostFunction<6, kBiasSize, kBiasSize> {
 public:
  BiasRandomWalkFactor(const imu::ImuNoise& noise, double dt_s);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Matrix<double, 6, 1> sqrt_information_diagonal_;
};

// A lower-triangular S with S^T S = covariance^-1, so that S r has unit covariance. Covariances that are
// not positive definite (for example, one preintegrated over no time) are regularised by 1e-12 on the
// diagonal rather than producing NaNs.
template <int N>
Eigen::Matrix<double, N, N> sqrtInformationFromCovariance(const Eigen::Matrix<double, N, N>& covariance);

}  // namespace cvislam::factors
