// Reprojection of a map point held as one 3-dof world position (the server's global BA, CVI-SLAM Eq. 11).
//
// A point p_w in the map frame, observed by keyframe i's camera as an undistorted keypoint z of a pinhole camera:
//   X_s = R_w_s^T (p_w - p_w_s),  X_c = R_c_s X_s + t_c_s,  r = (pi(X_c) - z) / sigma
// with T_c_s the observing camera from the body (cam0: T_s_c0^-1; cam1 of a stereo rig: (T_s_c0 T_c1_c0^-1)^-1),
// a constant of the factor. One parameter block per point, so SPARSE_SCHUR eliminates every point.
//
// Unlike the agent's anchored (bearing, inverse depth) points, a world point does not depend on a reference
// keyframe: merging maps, removing keyframes and propagating corrections never re-anchors it.
#pragma once

#include <ceres/sized_cost_function.h>

#include "common/factors/reprojection_factor.hpp"
#include "common/factors/state_layout.hpp"

namespace cvislam::factors {

inline constexpr int kPointSize = 3;

// Parameter blocks: the observing keyframe's pose T_w_s (7), the point p_w (3).
class WorldPointReprojectionFactor final : public ceres::SizedCostFunction<2, kPoseSize, kPointSize> {
 public:
  // `T_c_s`: the observing camera from the body.
  WorldPointReprojectionFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px,
                               const geometry::SE3d& T_c_s);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

  // The same residual with the pose's Jacobian in its tangent [dp, dphi] (2 x 6), for solvers that work in the
  // tangent space themselves (the server's Schur solver): no lift to the 7 ambient parameters and back.
  // Jacobians may be null; false when the point is not in front of the camera.
  bool evaluateTangent(const double* pose, const double* p_w, Eigen::Vector2d& residual,
                       Eigen::Matrix<double, 2, 6>* J_pose, Eigen::Matrix<double, 2, 3>* J_point) const;
  // The same with the pose as its rotation matrix and position, for a solver that evaluates many observations of
  // one pose and converts its quaternion once.
  bool evaluateTangent(const Eigen::Matrix3d& R_w_s, const Eigen::Vector3d& p_w_s, const double* p_w,
                       Eigen::Vector2d& residual, Eigen::Matrix<double, 2, 6>* J_pose,
                       Eigen::Matrix<double, 2, 3>* J_point) const;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
  Eigen::Matrix3d R_c_s_;
  Eigen::Vector3d t_c_s_;
};

}  // namespace cvislam::factors
