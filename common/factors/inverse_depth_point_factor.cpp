#include "common/factors/inverse_depth_point_factor.hpp"

#include <cmath>

#include "common/factors/pinhole_projection.hpp"

namespace cvislam::factors {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using geometry::hatSO3;
using RowMajor2x3 = Eigen::Matrix<double, 2, 3, Eigen::RowMajor>;

namespace {

Matrix3d rotationAt(const double* pose) {
  return Eigen::Quaterniond(pose[6], pose[3], pose[4], pose[5]).normalized().toRotationMatrix();
}

}  // namespace

bool inverseDepthPointFromBearing(const Vector3d& bearing, double inverse_distance, Vector3d& point) {
  if (!bearing.allFinite() || !std::isfinite(inverse_distance)) return false;
  // The bearing is stored unit length, but normalising here costs nothing and keeps a, b and rho consistent
  // with X = bearing / inverse_distance for a bearing that drifted from unit length.
  const double norm = bearing.norm();
  if (!(norm > 0.0)) return false;
  const Vector3d u = bearing / norm;
  if (!(u.z() >= kMinInverseDepthPointBearingZ)) return false;
  point = Vector3d(u.x() / u.z(), u.y() / u.z(), inverse_distance / u.z());
  return true;
}

void bearingFromInverseDepthPoint(const Vector3d& point, Vector3d& bearing, double& inverse_distance) {
  const Vector3d v(point.x(), point.y(), 1.0);
  const double norm = v.norm();  // >= 1
  bearing = v / norm;
  inverse_distance = point.z() / norm;
}

// ----------------------------------------------------------------------------- another keyframe's view
InverseDepthPointFactor::InverseDepthPointFactor(const Eigen::Vector2d& keypoint_px,
                                                 const PinholeIntrinsics& intrinsics, double sigma_px)
    : keypoint_px_(keypoint_px), intrinsics_(intrinsics), inv_sigma_(1.0 / sigma_px) {}

InverseDepthPointFactor::InverseDepthPointFactor(const Eigen::Vector2d& keypoint_px,
                                                 const PinholeIntrinsics& intrinsics, double sigma_px,
                                                 const geometry::SE3d& T_c1_c0)
    : keypoint_px_(keypoint_px),
      intrinsics_(intrinsics),
      inv_sigma_(1.0 / sigma_px),
      R_obs_c0_(T_c1_c0.rotationMatrix()),
      t_obs_c0_(T_c1_c0.translation()) {}

bool InverseDepthPointFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const double* pose_i = parameters[0];
  const double* pose_r = parameters[1];
  const double* extrinsics = parameters[2];
  const double* point = parameters[3];
  const Vector3d v(point[0], point[1], 1.0);  // rho X_cr
  const double rho = point[2];

  const Matrix3d R_w_si = rotationAt(pose_i);
  const Matrix3d R_w_sr = rotationAt(pose_r);
  const Matrix3d R_s_c = rotationAt(extrinsics);
  const Eigen::Map<const Vector3d> p_w_si(pose_i);
  const Eigen::Map<const Vector3d> p_w_sr(pose_r);
  const Eigen::Map<const Vector3d> t_s_c(extrinsics);

  const Matrix3d R_si_w = R_w_si.transpose();
  const Matrix3d R_c_s = R_s_c.transpose();
  const Vector3d u = R_s_c * v + rho * t_s_c;               // rho X_sr
  const Vector3d w = R_w_sr * u + rho * (p_w_sr - p_w_si);  // rho (X_w - p_w_si)
  const Vector3d m = R_si_w * w;                            // rho X_si
  const Vector3d h = R_c_s * (m - rho * t_s_c);             // rho X_ci (cam0)
  const Vector3d h_obs = R_obs_c0_ * h + rho * t_obs_c0_;   // in the observing camera (cam0 or cam1)

  Eigen::Matrix<double, 2, 3> d_r_d_h_obs;
  if (!detail::projectWhitened(h_obs, keypoint_px_, intrinsics_, inv_sigma_, residuals, d_r_d_h_obs)) return false;
  if (jacobians == nullptr) return true;
  const Eigen::Matrix<double, 2, 3> d_r_d_h = d_r_d_h_obs * R_obs_c0_;

  const Matrix3d R_c_w = R_c_s * R_si_w;
  if (jacobians[0] != nullptr) {  // observing pose [dp, dphi]: h depends on it through -rho p_w_si and R_si_w
    Eigen::Matrix<double, 2, 6> J;
    J.leftCols<3>() = d_r_d_h * (-rho * R_c_w);
    J.rightCols<3>() = d_r_d_h * (R_c_s * hatSO3(m));
    writePoseJacobian<2>(J, pose_i, jacobians[0]);
  }
  if (jacobians[1] != nullptr) {  // reference pose
    Eigen::Matrix<double, 2, 6> J;
    J.leftCols<3>() = d_r_d_h * (rho * R_c_w);
    J.rightCols<3>() = d_r_d_h * (-R_c_w * R_w_sr * hatSO3(u));
    writePoseJacobian<2>(J, pose_r, jacobians[1]);
  }
  if (jacobians[2] != nullptr) {         // extrinsics T_s_c: enters at both ends of the chain
    const Matrix3d A = R_si_w * R_w_sr;  // R_si_sr
    const Matrix3d M = R_c_s * A * R_s_c;
    Eigen::Matrix<double, 2, 6> J;
    J.leftCols<3>() = d_r_d_h * (rho * R_c_s * (A - Matrix3d::Identity()));
    J.rightCols<3>() = d_r_d_h * (hatSO3(h) - M * hatSO3(v));
    writePoseJacobian<2>(J, extrinsics, jacobians[2]);
  }
  if (jacobians[3] != nullptr) {  // point (a, b, rho)
    const Matrix3d R_ci_cr = R_c_w * R_w_sr * R_s_c;
    const Vector3d d_h_d_rho = R_c_s * (R_si_w * (R_w_sr * t_s_c + p_w_sr - p_w_si) - t_s_c);
    Eigen::Map<RowMajor2x3> J(jacobians[3]);
    J.leftCols<2>() = d_r_d_h * R_ci_cr.leftCols<2>();
    J.col(2) = d_r_d_h * d_h_d_rho + d_r_d_h_obs * t_obs_c0_;
  }
  return true;
}

// ---------------------------------------------------------------------- the reference keyframe's own view
InverseDepthPointHostFactor::InverseDepthPointHostFactor(const Eigen::Vector2d& keypoint_px,
                                                         const PinholeIntrinsics& intrinsics, double sigma_px)
    : keypoint_px_(keypoint_px), intrinsics_(intrinsics), inv_sigma_(1.0 / sigma_px) {}

bool InverseDepthPointHostFactor::Evaluate(double const* const* parameters, double* residuals,
                                           double** jacobians) const {
  const double* point = parameters[0];
  residuals[0] = inv_sigma_ * (intrinsics_.fx * point[0] + intrinsics_.cx - keypoint_px_.x());
  residuals[1] = inv_sigma_ * (intrinsics_.fy * point[1] + intrinsics_.cy - keypoint_px_.y());
  if (jacobians != nullptr && jacobians[0] != nullptr) {
    Eigen::Map<RowMajor2x3> J(jacobians[0]);
    J << inv_sigma_ * intrinsics_.fx, 0.0, 0.0,  //
        0.0, inv_sigma_ * intrinsics_.fy, 0.0;
  }
  return true;
}

InverseDepthPointSecondCameraHostFactor::InverseDepthPointSecondCameraHostFactor(const Eigen::Vector2d& keypoint_px,
                                                                                 const PinholeIntrinsics& intrinsics,
                                                                                 double sigma_px,
                                                                                 const geometry::SE3d& T_c1_c0)
    : keypoint_px_(keypoint_px),
      intrinsics_(intrinsics),
      inv_sigma_(1.0 / sigma_px),
      R_c1_c0_(T_c1_c0.rotationMatrix()),
      t_c1_c0_(T_c1_c0.translation()) {}

bool InverseDepthPointSecondCameraHostFactor::Evaluate(double const* const* parameters, double* residuals,
                                                       double** jacobians) const {
  const double* point = parameters[0];
  const Vector3d v(point[0], point[1], 1.0);
  const double rho = point[2];
  const Vector3d h1 = R_c1_c0_ * v + rho * t_c1_c0_;  // rho X_c1
  Eigen::Matrix<double, 2, 3> d_r_d_h1;
  if (!detail::projectWhitened(h1, keypoint_px_, intrinsics_, inv_sigma_, residuals, d_r_d_h1)) return false;
  if (jacobians != nullptr && jacobians[0] != nullptr) {
    Eigen::Map<RowMajor2x3> J(jacobians[0]);
    J.leftCols<2>() = d_r_d_h1 * R_c1_c0_.leftCols<2>();
    J.col(2) = d_r_d_h1 * t_c1_c0_;
  }
  return true;
}

}  // namespace cvislam::factors
