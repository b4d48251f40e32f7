// Reprojection of a map point into a keyframe (CVI-SLAM Eq. 6), for the agent's local BA and the server's
// global BA.
//
// A map point is stored as a unit bearing b and an inverse depth rho in the camera of its reference
// keyframe r: X_cr = b / rho. It is observed by the camera of keyframe i as an undistorted keypoint z (pixels)
// of a pinhole camera. The residual is computed from rho X_ci, which stays finite as rho -> 0, so points
// near infinity still constrain rotation:
//   h = rho X_ci = R_s_c^T ( R_w_si^T ( R_w_sr (R_s_c b + rho t_s_c) + rho (p_w_sr - p_w_si) ) - rho t_s_c )
//   r = (pi(h) - z) / sigma,   pi(h) = (fx h_x / h_z + cx, fy h_y / h_z + cy)
// A robust loss (Cauchy, in the paper) is the caller's choice when adding the residual block.
//
// Stereo: the second camera of the rig (cam1) observes through the same parameter blocks, with its rigid
// offset from cam0 as a constant of the factor: h1 = R_c1_c0 h + rho t_c1_c0, projected with cam1's pinhole.
// Its observation in the reference keyframe itself (SecondCameraHostFactor) is what fixes a stereo point's
// depth: it depends on the bearing and the inverse depth only.
#pragma once

#include <ceres/sized_cost_function.h>

#include "common/factors/pinhole_intrinsics.hpp"
#include "common/factors/state_layout.hpp"

namespace cvislam::factors {

// Parameter blocks: pose of the observing keyframe T_w_si (7), pose of the reference keyframe T_w_sr (7),
// camera-IMU extrinsics T_s_c (7, same layout as a pose; hold it constant when it is calibrated), bearing
// (3), inverse depth (1). The observing and reference keyframes must differ (Ceres forbids one block twice);
// use ReprojectionHostFactor for the reference keyframe's own observation.
class ReprojectionFactor final : public ceres::SizedCostFunction<2, kPoseSize, kPoseSize, kPoseSize, kBearingSize, 1> {
 public:
  // Observed by cam0 (the camera the extrinsics block describes).
  ReprojectionFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px);
  // Observed by cam1 of a stereo rig: `keypoint_px` and `intrinsics` are cam1's, T_c1_c0 its rigid offset.
  ReprojectionFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px,
                     const geometry::SE3d& T_c1_c0);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
  Eigen::Matrix3d R_obs_c0_ = Eigen::Matrix3d::Identity();  // the observing camera from cam0
  Eigen::Vector3d t_obs_c0_ = Eigen::Vector3d::Zero();
};

// The observation in the reference keyframe itself: r = (pi(b) - z) / sigma. Parameter block: bearing (3).
class ReprojectionHostFactor final : public ceres::SizedCostFunction<2, kBearingSize> {
 public:
  ReprojectionHostFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
};

// cam1's observation in the reference keyframe: r = (pi1(R_c1_c0 b + rho t_c1_c0) - z1) / sigma.
// Parameter blocks: bearing (3), inverse depth (1).
class SecondCameraHostFactor final : public ceres::SizedCostFunction<2, kBearingSize, 1> {
 public:
  SecondCameraHostFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px,
                         const geometry::SE3d& T_c1_c0);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
  Eigen::Matrix3d R_c1_c0_;
  Eigen::Vector3d t_c1_c0_;
};

}  // namespace cvislam::factors
