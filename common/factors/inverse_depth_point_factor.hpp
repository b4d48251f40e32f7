// Reprojection of a map point held as ONE parameter block, for bundle adjustments that eliminate points by
// the Schur complement (Ceres' SPARSE_SCHUR needs each point to be a single e-block; the bearing +
// inverse-depth pair of reprojection_factor.hpp is two blocks per point, so points could not be eliminated).
//
// The point is the inverse-depth point of its reference keyframe r's cam0:
//   m = (a, b, rho),   X_cr = (a, b, 1) / rho,   a = x/z, b = y/z, rho = 1/z  (z: depth along the optical axis)
// It is Euclidean (3 dof, no manifold), rho > 0 is exactly "in front of the reference camera" (a simple
// bound), it stays finite for far points (rho -> 0 with a, b fixed), and the reference keyframe's own
// observation is linear in (a, b). Its one limitation, a bearing at 90 degrees to the optical axis, cannot
// occur for a point the reference camera's image saw (see inverseDepthPointFromBearing).
//
// With v = (a, b, 1), rho X_cr = v, and the observation by the camera of keyframe i is computed, as in
// ReprojectionFactor, from rho X_ci, which stays finite as rho -> 0 so that far points still constrain rotation:
//   u = R_s_c v + rho t_s_c                                 (rho X_sr)
//   w = R_w_sr u + rho (p_w_sr - p_w_si)                    (rho (X_w - p_w_si))
//   h = R_c_s ( R_w_si^T w - rho t_s_c )                    (rho X_ci)
//   r = (pi(h) - z) / sigma,   pi(h) = (fx h_x / h_z + cx, fy h_y / h_z + cy)
// Point Jacobian: dh/d(a, b) = R_c_w R_w_sr R_s_c [e_x e_y], dh/drho = R_c_s (R_si_w (R_w_sr t_s_c + p_w_sr -
// p_w_si) - t_s_c); the pose and extrinsics Jacobians are those of ReprojectionFactor with the bearing replaced
// by v (right perturbations, state_layout.hpp).
//
// Host observation (keyframe r's own cam0): pi(v) = (fx a + cx, fy b + cy), linear, and independent of rho.
// Stereo: cam1 observes rho X_c1 = R_c1_c0 h + rho t_c1_c0 with cam1's pinhole, T_c1_c0 a constant of the
// factor; in the reference keyframe, h1 = R_c1_c0 v + rho t_c1_c0, which is what fixes a stereo point's depth.
//
// The agent's LocalMap stores a unit bearing and the inverse of the distance along it; the conversions below
// go between the two.
#pragma once

#include <ceres/sized_cost_function.h>

#include "common/factors/reprojection_factor.hpp"
#include "common/factors/state_layout.hpp"

namespace cvislam::factors {

inline constexpr int kInverseDepthPointSize = 3;

// A stored bearing closer than this to the reference image plane (|angle to the optical axis| above ~84 deg)
// has no inverse-depth point: no pinhole image can have seen it, and (a, b) would be huge and ill-conditioned.
inline constexpr double kMinInverseDepthPointBearingZ = 0.1;

// From a unit bearing u and the inverse distance along it r (X = u / r) to m = (a, b, rho):
// a = u_x / u_z, b = u_y / u_z, and 1/rho = z = u_z / r, so rho = r / u_z. False (m untouched) when u_z is
// below kMinInverseDepthPointBearingZ or the inputs are not finite.
bool inverseDepthPointFromBearing(const Eigen::Vector3d& bearing, double inverse_distance, Eigen::Vector3d& point);

// Back: u = v / |v| and r = 1 / |X| = rho / |v|, with v = (a, b, 1).
void bearingFromInverseDepthPoint(const Eigen::Vector3d& point, Eigen::Vector3d& bearing, double& inverse_distance);

// The point in its reference camera, X_cr = (a, b, 1) / rho (infinite for rho = 0).
inline Eigen::Vector3d inverseDepthPointInCamera(const Eigen::Vector3d& point) {
  return Eigen::Vector3d(point.x(), point.y(), 1.0) / point.z();
}

// Parameter blocks: observing keyframe's pose T_w_si (7), reference keyframe's pose T_w_sr (7), camera-IMU
// extrinsics T_s_c (7, pose layout; hold it constant when calibrated), point m (3). The observing and
// reference keyframes must differ (Ceres forbids one block twice); the reference keyframe's own observations
// are InverseDepthPointHostFactor and InverseDepthPointSecondCameraHostFactor.
class InverseDepthPointFactor final
    : public ceres::SizedCostFunction<2, kPoseSize, kPoseSize, kPoseSize, kInverseDepthPointSize> {
 public:
  // Observed by cam0 (the camera the extrinsics block describes).
  InverseDepthPointFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px);
  // Observed by cam1 of a stereo rig: `keypoint_px` and `intrinsics` are cam1's, T_c1_c0 its rigid offset.
  InverseDepthPointFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px,
                          const geometry::SE3d& T_c1_c0);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
  Eigen::Matrix3d R_obs_c0_ = Eigen::Matrix3d::Identity();  // the observing camera from cam0
  Eigen::Vector3d t_obs_c0_ = Eigen::Vector3d::Zero();
};

// The reference keyframe's own cam0 observation: r = ((fx a + cx, fy b + cy) - z) / sigma. Block: point (3).
// Always evaluable (the point is on the ray through the keypoint whatever rho is).
class InverseDepthPointHostFactor final : public ceres::SizedCostFunction<2, kInverseDepthPointSize> {
 public:
  InverseDepthPointHostFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics, double sigma_px);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
};

// cam1's observation in the reference keyframe: r = (pi1(R_c1_c0 v + rho t_c1_c0) - z1) / sigma. Block: point (3).
class InverseDepthPointSecondCameraHostFactor final : public ceres::SizedCostFunction<2, kInverseDepthPointSize> {
 public:
  InverseDepthPointSecondCameraHostFactor(const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& intrinsics,
                                          double sigma_px, const geometry::SE3d& T_c1_c0);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  Eigen::Vector2d keypoint_px_;
  PinholeIntrinsics intrinsics_;
  double inv_sigma_;
  Eigen::Matrix3d R_c1_c0_;
  Eigen::Vector3d t_c1_c0_;
};

}  // namespace cvislam::factors
