#include "common/factors/world_point_factor.hpp"

#include "common/factors/pinhole_projection.hpp"

namespace cvislam::factors {

WorldPointReprojectionFactor::WorldPointReprojectionFactor(const Eigen::Vector2d& keypoint_px,
                                                           const PinholeIntrinsics& intrinsics, double sigma_px,
                                                           const geometry::SE3d& T_c_s)
    : keypoint_px_(keypoint_px),
      intrinsics_(intrinsics),
      inv_sigma_(1.0 / sigma_px),
      R_c_s_(T_c_s.rotationMatrix()),
      t_c_s_(T_c_s.translation()) {}

bool WorldPointReprojectionFactor::Evaluate(double const* const* parameters, double* residuals,
                                            double** jacobians) const {
  const double* pose = parameters[0];
  const Eigen::Map<const Eigen::Vector3d> p_w_s(pose);
  const Eigen::Matrix3d R_w_s = Eigen::Quaterniond(pose[6], pose[3], pose[4], pose[5]).normalized().toRotationMatrix();
  const Eigen::Map<const Eigen::Vector3d> p_w(parameters[1]);

  const Eigen::Vector3d X_s = R_w_s.transpose() * (p_w - p_w_s);
  const Eigen::Vector3d X_c = R_c_s_ * X_s + t_c_s_;
  Eigen::Matrix<double, 2, 3> d_r_d_Xc;
  if (!detail::projectWhitened(X_c, keypoint_px_, intrinsics_, inv_sigma_, residuals, d_r_d_Xc)) return false;
  if (jacobians == nullptr) return true;
  const Eigen::Matrix<double, 2, 3> d_r_d_Xs = d_r_d_Xc * R_c_s_;
  if (jacobians[0] != nullptr) {
    // p_w_s + dp moves X_s by -R^T dp; R Exp(dphi) turns it by Exp(-dphi): dX_s = [X_s]x dphi.
    Eigen::Matrix<double, 2, 6> J;
    J.leftCols<3>() = -d_r_d_Xs * R_w_s.transpose();
    J.rightCols<3>() = d_r_d_Xs * geometry::hatSO3(X_s);
    writePoseJacobian<2>(J, pose, jacobians[0]);
  }
  if (jacobians[1] != nullptr) {
    Eigen::Map<Eigen::Matrix<double, 2, 3, Eigen::RowMajor>>{jacobians[1]} = d_r_d_Xs * R_w_s.transpose();
  }
  return true;
}

}  // namespace cvislam::factors
