#include "agent_rt/tracking/inertial_pose_optimizer.hpp"

#include <string>

#include <Eigen/Cholesky>

#include "common/factors/imu_factor.hpp"

namespace cvislam::agent {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;
using Vec9 = Eigen::Matrix<double, 9, 1>;
using Mat9 = Eigen::Matrix<double, 9, 9>;

Vec9 inertialResidual(const InertialAnchor& anchor, const SE3d& T_w_s, const Vector3d& v_w, Mat9* J) {
  const imu::Preintegration& pre = *anchor.preintegration;
  const double dt = pre.dt();
  const Eigen::Matrix3d R_i_t = anchor.T_w_s.rotationMatrix().transpose();
  const SO3d dR = pre.correctedDeltaR(anchor.bias);
  const Vector3d& g = imu::kGravityW;
  Vec9 r;
  const SO3d R_err = dR.inverse() * anchor.T_w_s.so3().inverse() * T_w_s.so3();
  r.segment<3>(0) = R_err.log();
  r.segment<3>(3) = R_i_t * (v_w - anchor.v_w - g * dt) - pre.correctedDeltaV(anchor.bias);
  r.segment<3>(6) = R_i_t * (T_w_s.translation() - anchor.T_w_s.translation() - anchor.v_w * dt - 0.5 * g * dt * dt) -
                    pre.correctedDeltaP(anchor.bias);
  if (J != nullptr) {
    J->setZero();
    J->block<3, 3>(0, 3) = SO3d::rightJacobianInverse(r.segment<3>(0));  // r_R wrt dphi
    J->block<3, 3>(3, 6) = R_i_t;                                        // r_v wrt dv
    J->block<3, 3>(6, 0) = R_i_t;                                        // r_p wrt dp
  }
  return r;
}

Result<InertialPoseResult> optimizePoseInertial(std::span<const PoseObservation> observations,
                                                const SE3d& T_w_s_initial, const Vector3d& v_w_initial,
                                                const InertialAnchor& anchor, const SE3d& T_s_c,
                                                const factors::PinholeIntrinsics& intrinsics,
                                                const PoseOptimizerOptions& options,
                                                std::span<std::uint8_t> is_outlier) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  if (anchor.preintegration == nullptr || anchor.preintegration->dt() <= 0.0) {
    return Error{ErrorCode::kInvalidArgument, "optimizePoseInertial: the anchor has no IMU to the frame"};
  }
  if (is_outlier.size() != observations.size()) {
    return Error{ErrorCode::kInvalidArgument, "optimizePoseInertial: is_outlier must be as long as observations"};
  }
  for (std::uint8_t& flag : is_outlier) flag = 0;
  const Mat9 S = factors::sqrtInformationFromCovariance<9>(anchor.preintegration->covariance());

  InertialPoseResult result;
  result.T_w_s = T_w_s_initial;
  result.v_w = v_w_initial;
  for (int round = 0; round < options.rounds; ++round) {
    for (int it = 0; it < options.iterations_per_round; ++it) {
      Mat9 H = Mat9::Zero();
      Vec9 g = Vec9::Zero();
      Eigen::Matrix<double, 6, 6> H_pose = Eigen::Matrix<double, 6, 6>::Zero();
      Eigen::Matrix<double, 6, 1> g_pose = Eigen::Matrix<double, 6, 1>::Zero();
      const int used = accumulateReprojection(observations, result.T_w_s, T_s_c, intrinsics, options.huber_delta,
                                              is_outlier, H_pose, g_pose);
      H.topLeftCorner<6, 6>() = H_pose;
      g.head<6>() = g_pose;
      if (used < options.min_inliers) break;
      Mat9 J_imu;
      const Vec9 r_imu = S * inertialResidual(anchor, result.T_w_s, result.v_w, &J_imu);
      J_imu = S * J_imu;
      H.noalias() += J_imu.transpose() * J_imu;
      g.noalias() += J_imu.transpose() * r_imu;
      const Vec9 dx = -H.ldlt().solve(g);
      if (!dx.allFinite()) break;
      result.T_w_s = SE3d(result.T_w_s.so3() * SO3d::exp(dx.segment<3>(3)), result.T_w_s.translation() + dx.head<3>());
      result.v_w += dx.tail<3>();
      ++result.iterations;
      if (dx.norm() < options.min_step) break;
    }
    result.inliers = classifyObservations(observations, result.T_w_s, T_s_c, intrinsics, options.chi2_threshold,
                                          is_outlier, nullptr);
  }
  result.imu_chi2 = (S * inertialResidual(anchor, result.T_w_s, result.v_w, nullptr)).squaredNorm();
  if (result.inliers < options.min_inliers) {
    return Error{ErrorCode::kDegenerate, "visual-inertial pose optimisation kept " + std::to_string(result.inliers) +
                                             " inliers, fewer than the " + std::to_string(options.min_inliers) +
                                             " required"};
  }
  return result;
}

}  // namespace cvislam::agent
