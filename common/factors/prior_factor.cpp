#include "common/factors/prior_factor.hpp"

#include <cmath>

namespace cvislam::factors {

using Eigen::Vector3d;
using geometry::SO3d;
constexpr int kRowMajor = Eigen::RowMajor;

PosePriorFactor::PosePriorFactor(const geometry::SE3d& T_w_s_prior, const Eigen::Matrix<double, 6, 6>& sqrt_information)
    : T_w_s_prior_(T_w_s_prior), sqrt_information_(sqrt_information) {}

bool PosePriorFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const double* pose = parameters[0];
  const geometry::SE3d T_w_s = poseFromBlock(pose);
  Eigen::Matrix<double, 6, 1> r;
  r.head<3>() = T_w_s.translation() - T_w_s_prior_.translation();
  const Vector3d phi = (T_w_s_prior_.so3().inverse() * T_w_s.so3()).log();
  r.tail<3>() = phi;
  Eigen::Map<Eigen::Matrix<double, 6, 1>>{residuals} = sqrt_information_ * r;
  if (jacobians != nullptr && jacobians[0] != nullptr) {
    Eigen::Matrix<double, 6, 6> J = Eigen::Matrix<double, 6, 6>::Identity();
    J.bottomRightCorner<3, 3>() = SO3d::rightJacobianInverse(phi);
    J = sqrt_information_ * J;
    writePoseJacobian<6>(J, pose, jacobians[0]);
  }
  return true;
}

BearingPriorFactor::BearingPriorFactor(const Vector3d& bearing_prior, const Eigen::Matrix2d& sqrt_information)
    : bearing_prior_(bearing_prior.normalized()),
      projection_(sqrt_information * bearingTangentBasis(bearing_prior_).transpose()) {}

bool BearingPriorFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const Eigen::Map<const Vector3d> b(parameters[0]);
  const Vector3d& b0 = bearing_prior_;
  Eigen::Map<Eigen::Vector2d>{residuals} = projection_ * greatCircleRotation(b0, b);
  if (jacobians == nullptr || jacobians[0] == nullptr) return true;

  // w = k s with s = b0 x b, n = |s|, c = b0 . b, k = atan2(n, c) / n; dw/db = k [b0]x + s dk/db.
  const Vector3d s = b0.cross(b);
  const double n = s.norm();
  const double c = b0.dot(b);
  const Eigen::Matrix3d b0_hat = geometry::hatSO3(b0);
  Eigen::Matrix3d dw_db;
  if (n < 1e-9 && c > 0.0) {  // k = 1/c - n^2 / (3 c^3) + ...: dk/db -> -b0^T / c^2
    dw_db = b0_hat / c - s * b0.transpose() / (c * c);
  } else {
    const double theta = std::atan2(n, c);
    const double k = theta / n;
    const Eigen::RowVector3d dn_db = s.transpose() * b0_hat / n;
    const Eigen::RowVector3d dc_db = b0.transpose();
    const Eigen::RowVector3d dtheta_db = (c * dn_db - n * dc_db) / (n * n + c * c);
    const Eigen::RowVector3d dk_db = (dtheta_db - k * dn_db) / n;
    dw_db = k * b0_hat + s * dk_db;
  }
  Eigen::Map<Eigen::Matrix<double, 2, 3, kRowMajor>>{jacobians[0]} = projection_ * dw_db;
  return true;
}

}  // namespace cvislam::factors
