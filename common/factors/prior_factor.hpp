// Priors on single states (CVI-SLAM Eq. 9): r = S (x [-] x0), with the manifold's box-minus for poses and
// bearings. S is any square-root information (S^T S = information), e.g. from the marginal of a previous
// solve, or sqrtInformationFromCovariance() in imu_factor.hpp.
#pragma once

#include <ceres/sized_cost_function.h>

#include "common/factors/state_layout.hpp"

namespace cvislam::factors {

// On a pose T_w_s: r = S [p - p0, Log(R0^T R)]. Parameter block: pose (7).
class PosePriorFactor final : public ceres::SizedCostFunction<6, kPoseSize> {
 public:
  PosePriorFactor(const geometry::SE3d& T_w_s_prior, const Eigen::Matrix<double, 6, 6>& sqrt_information);
  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  geometry::SE3d T_w_s_prior_;
  Eigen::Matrix<double, 6, 6> sqrt_information_;
};

// On a unit bearing: r = S B(b0)^T w(b0 -> b), the bearing manifold's Minus(b, b0). Parameter block: bearing (3).
class BearingPriorFactor final : public ceres::SizedCostFunction<2, kBearingSize> {
 public:
  BearingPriorFactor(const Eigen::Vector3d& bearing_prior, const Eigen::Matrix2d& sqrt_information);
  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector3d bearing_prior_;
  Eigen::Matrix<double, 2, 3> projection_;  // S B(b0)^T
};

// On a Euclidean state of size N (velocity 3, bias 6, inverse depth 1): r = S (x - x0).
template <int N>
class VectorPriorFactor final : public ceres::SizedCostFunction<N, N> {
 public:
  VectorPriorFactor(const Eigen::Matrix<double, N, 1>& prior, const Eigen::Matrix<double, N, N>& sqrt_information)
      : prior_(prior), sqrt_information_(sqrt_information) {}

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
    const Eigen::Map<const Eigen::Matrix<double, N, 1>> x(parameters[0]);
    Eigen::Map<Eigen::Matrix<double, N, 1>>{residuals} = sqrt_information_ * (x - prior_);
    if (jacobians != nullptr && jacobians[0] != nullptr) {
      Eigen::Map<Eigen::Matrix<double, N, N, (N == 1 ? Eigen::ColMajor : Eigen::RowMajor)>>{jacobians[0]} =
          sqrt_information_;
    }
    return true;
  }

 private:
  Eigen::Matrix<double, N, 1> prior_;
  Eigen::Matrix<double, N, N> sqrt_information_;
};

}  // namespace cvislam::factors
