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

bool WorldPointReprojectionFactor::evaluateTangent(const double* pose, const double* p_w_block,
                                                   Eigen::Vector2d& residual, Eigen::Matrix<double, 2, 6>* J_pose,
                                                   Eigen::Matrix<double, 2, 3>* J_point) const {
  const Eigen::Matrix3d R_w_s = Eigen::Quaterniond(pose[6], pose[3], pose[4], pose[5]).normalized().toRotationMatrix();
  return evaluateTangent(R_w_s, Eigen::Vector3d(pose[0], pose[1], pose[2]), p_w_block, residual, J_pose, J_point);
}

bool WorldPointReprojectionFactor::evaluateTangent(const Eigen::Matrix3d& R_w_s, const Eigen::Vector3d& p_w_s,
                                                   const double* p_w_block, Eigen::Vector2d& residual,
                                                   Eigen::Matrix<double, 2, 6>* J_pose,
                                                   Eigen::Matrix<double, 2, 3>* J_point) const {
  const Eigen::Map<const Eigen::Vector3d> p_w(p_w_block);

  const Eigen::Vector3d X_s = R_w_s.transpose() * (p_w - p_w_s);
  const Eigen::Vector3d X_c = R_c_s_ * X_s + t_c_s_;
  Eigen::Matrix<double, 2, 3> d_r_d_Xc;
  if (!detail::projectWhitened(X_c, keypoint_px_, intrinsics_, inv_sigma_, residual.data(), d_r_d_Xc)) return false;
  if (J_pose == nullptr && J_point == nullptr) return true;
  const Eigen::Matrix<double, 2, 3> d_r_d_Xs = d_r_d_Xc * R_c_s_;
  const Eigen::Matrix<double, 2, 3> d_r_d_pw = d_r_d_Xs * R_w_s.transpose();
  if (J_pose != nullptr) {
    // p_w_s + dp moves X_s by -R^T dp; R Exp(dphi) turns it by Exp(-dphi): dX_s = [X_s]x dphi.
    J_pose->leftCols<3>() = -d_r_d_pw;
    J_pose->rightCols<3>() = d_r_d_Xs * geometry::hatSO3(X_s);
  }
  if (J_point != nullptr) *J_point = d_r_d_pw;
  return true;
}

bool WorldPointReprojectionFactor::Evaluate(double const* const* parameters, double* residuals,
                                            double** jacobians) const {
  Eigen::Vector2d r;
  Eigen::Matrix<double, 2, 6> J_pose;
  Eigen::Matrix<double, 2, 3> J_point;
  const bool want_pose = jacobians != nullptr && jacobians[0] != nullptr;
  const bool want_point = jacobians != nullptr && jacobians[1] != nullptr;
  if (!evaluateTangent(parameters[0], parameters[1], r, want_pose ? &J_pose : nullptr,
                       want_point ? &J_point : nullptr)) {
    return false;
  }
  residuals[0] = r.x();
  residuals[1] = r.y();
  if (want_pose) writePoseJacobian<2>(J_pose, parameters[0], jacobians[0]);
  if (want_point) Eigen::Map<Eigen::Matrix<double, 2, 3, Eigen::RowMajor>>{jacobians[1]} = J_point;
  return true;
}

}  // namespace cvislam::factors
