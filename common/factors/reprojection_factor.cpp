#include "common/factors/reprojection_factor.hpp"

#include "common/factors/pinhole_projection.hpp"

namespace cvislam::factors {

using detail::projectWhitened;
using Eigen::Matrix3d;
using Eigen::Vector3d;
using geometry::hatSO3;
constexpr int kRowMajor = Eigen::RowMajor;

namespace {

Matrix3d rotationAt(const double* pose) {
  return Eigen::Quaterniond(pose[6], pose[3], pose[4], pose[5]).normalized().toRotationMatrix();
}

}  // namespace

ReprojectionFactor::ReprojectionFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics,
                                       double sigma_px)
    : keypoint_px_(keypoint_px), intrinsics_(intrinsics), inv_sigma_(1.0 / sigma_px) {}

ReprojectionFactor::ReprojectionFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics,
                                       double sigma_px, const geometry::SE3d& T_c1_c0)
    : keypoint_px_(keypoint_px),
      intrinsics_(intrinsics),
      inv_sigma_(1.0 / sigma_px),
      R_obs_c0_(T_c1_c0.rotationMatrix()),
      t_obs_c0_(T_c1_c0.translation()) {}

bool ReprojectionFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const double* pose_i = parameters[0];
  const double* pose_r = parameters[1];
  const double* extrinsics = parameters[2];
  const Eigen::Map<const Vector3d> b(parameters[3]);
  const double rho = parameters[4][0];

  const Matrix3d R_w_si = rotationAt(pose_i);
  const Matrix3d R_w_sr = rotationAt(pose_r);
  const Matrix3d R_s_c = rotationAt(extrinsics);
  const Eigen::Map<const Vector3d> p_w_si(pose_i);
  const Eigen::Map<const Vector3d> p_w_sr(pose_r);
  const Eigen::Map<const Vector3d> t_s_c(extrinsics);

  const Matrix3d R_si_w = R_w_si.transpose();
  const Matrix3d R_c_s = R_s_c.transpose();
  const Vector3d u = R_s_c * b + rho * t_s_c;               // rho X_sr
  const Vector3d w = R_w_sr * u + rho * (p_w_sr - p_w_si);  // rho (X_w - p_w_si)
  const Vector3d m = R_si_w * w;                            // rho X_si
  const Vector3d h = R_c_s * (m - rho * t_s_c);             // rho X_ci (cam0)
  const Vector3d h_obs = R_obs_c0_ * h + rho * t_obs_c0_;   // in the observing camera (cam0 or cam1)

  Eigen::Matrix<double, 2, 3> d_r_d_h_obs;
  if (!projectWhitened(h_obs, keypoint_px_, intrinsics_, inv_sigma_, residuals, d_r_d_h_obs)) return false;
  if (jacobians == nullptr) return true;
  const Eigen::Matrix<double, 2, 3> d_r_d_h = d_r_d_h_obs * R_obs_c0_;

  const Matrix3d R_c_w = R_c_s * R_si_w;
  if (jacobians[0] != nullptr) {  // observing pose [dp, dphi]
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
  if (jacobians[2] != nullptr) {         // extrinsics T_s_c
    const Matrix3d A = R_si_w * R_w_sr;  // R_si_sr
    const Matrix3d M = R_c_s * A * R_s_c;
    Eigen::Matrix<double, 2, 6> J;
    J.leftCols<3>() = d_r_d_h * (rho * R_c_s * (A - Matrix3d::Identity()));
    J.rightCols<3>() = d_r_d_h * (hatSO3(h) - M * hatSO3(Vector3d(b)));
    writePoseJacobian<2>(J, extrinsics, jacobians[2]);
  }
  if (jacobians[3] != nullptr) {  // bearing, ambient
    Eigen::Map<Eigen::Matrix<double, 2, 3, kRowMajor>>{jacobians[3]} = d_r_d_h * (R_c_w * R_w_sr * R_s_c);
  }
  if (jacobians[4] != nullptr) {  // inverse depth
    const Vector3d d_h_d_rho = R_c_s * (R_si_w * (R_w_sr * t_s_c + p_w_sr - p_w_si) - t_s_c);
    Eigen::Map<Eigen::Vector2d>{jacobians[4]} = d_r_d_h * d_h_d_rho + d_r_d_h_obs * t_obs_c0_;
  }
  return true;
}

ReprojectionHostFactor::ReprojectionHostFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics,
                                               double sigma_px)
    : keypoint_px_(keypoint_px), intrinsics_(intrinsics), inv_sigma_(1.0 / sigma_px) {}

bool ReprojectionHostFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const Eigen::Map<const Vector3d> b(parameters[0]);
  Eigen::Matrix<double, 2, 3> d_r_d_h;
  if (!projectWhitened(b, keypoint_px_, intrinsics_, inv_sigma_, residuals, d_r_d_h)) return false;
  if (jacobians != nullptr && jacobians[0] != nullptr) {
    Eigen::Map<Eigen::Matrix<double, 2, 3, kRowMajor>>{jacobians[0]} = d_r_d_h;
  }
  return true;
}

SecondCameraHostFactor::SecondCameraHostFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics,
                                               double sigma_px, const geometry::SE3d& T_c1_c0)
    : keypoint_px_(keypoint_px),
      intrinsics_(intrinsics),
      inv_sigma_(1.0 / sigma_px),
      R_c1_c0_(T_c1_c0.rotationMatrix()),
      t_c1_c0_(T_c1_c0.translation()) {}

bool SecondCameraHostFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const Eigen::Map<const Vector3d> b(parameters[0]);
  const double rho = parameters[1][0];
  const Vector3d h1 = R_c1_c0_ * b + rho * t_c1_c0_;  // rho X_c1
  Eigen::Matrix<double, 2, 3> d_r_d_h1;
  if (!projectWhitened(h1, keypoint_px_, intrinsics_, inv_sigma_, residuals, d_r_d_h1)) return false;
  if (jacobians == nullptr) return true;
  if (jacobians[0] != nullptr) {
    Eigen::Map<Eigen::Matrix<double, 2, 3, kRowMajor>>{jacobians[0]} = d_r_d_h1 * R_c1_c0_;
  }
  if (jacobians[1] != nullptr) Eigen::Map<Eigen::Vector2d>{jacobians[1]} = d_r_d_h1 * t_c1_c0_;
  return true;
}

}  // namespace cvislam::factors
