// Visual-inertial alignment: the linear IMU initialisation of CVI-SLAM (section IV-C, after VI ORB-SLAM and
// VINS-Mono). Given keyframe poses from vision alone (correct up to scale, in an arbitrary visual frame v)
// and the IMU preintegrated between consecutive keyframes, it estimates
//   1. the gyroscope bias, by linear least squares on the rotation deltas, and, when asked, the camera-IMU time
//      offset with it: vision gives each keyframe's rotation at the time its image was really taken, t_k + d_k, the
//      IMU between the state times t_k, so R(t_k) = R_vis_k Exp(-w_k d_k) with w_k the body's rate (a gyro bias
//      alone would otherwise absorb the offset, and local BA's bias random walk is slow to give it back);
//   2. the scale, every keyframe's velocity and gravity in v, by linear least squares on the velocity and
//      position deltas (accelerometer bias taken as zero at this stage);
//   3. gravity again, with its magnitude fixed to |g| (two degrees of freedom, a few iterations);
// and returns the rotation R_w_v that makes v gravity-aligned (world z up, yaw of v kept).
//
// It fails, saying why, when the motion does not observe what it must (too little acceleration for the
// scale, a negative scale, gravity far from its known magnitude): the caller waits for more keyframes.
// It runs once, in the mapping thread, so it may allocate.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::imu {

struct VisualInertialAlignmentOptions {
  double gravity_magnitude = 9.81;        // [m/s^2]
  int gravity_refinement_iterations = 4;  // step 3
  int gyro_bias_iterations = 2;           // step 1 (re-linearised)
  // Step 2's |g| must be within this fraction of gravity_magnitude, or the solution is refused.
  double max_gravity_magnitude_error = 0.1;
  // The smallest singular value of step 2's scale column (relative) below which scale is unobservable.
  double min_scale_observability = 1e-6;
  // > 0: the visual poses are metric up to this known scale (a stereo map: 1), which is then not estimated;
  // gravity, velocities and the gyro bias are, which short or gentle motion observes far better than scale.
  double known_scale = 0.0;
  // Step 1 estimates the correction to the calibrated camera-IMU time offset too (VisualKeyframe::omega_s and
  // time_correction_s then matter). A prior of this sigma about the newest keyframe's correction keeps it put
  // where the rotation rate hardly changes (the offset is then not observed); bounded to +-max_time_offset_s.
  bool estimate_time_offset = false;
  double time_offset_prior_sigma_s = 0.05;
  double max_time_offset_s = 0.1;

  [[nodiscard]] Status validate() const;
};

struct VisualKeyframe {
  geometry::SE3d T_v_c;                               // camera pose from vision, up to scale, in the visual frame v
  Eigen::Vector3d omega_s = Eigen::Vector3d::Zero();  // raw gyro at the keyframe's time [rad/s]
  double time_correction_s = 0.0;  // the time offset's correction the keyframe's time carries already
};

struct VisualInertialAlignment {
  double scale = 1.0;  // metric = scale * visual
  // The scale's standard deviation relative to it, from the fit's residual (0 with a known scale): how well the
  // equations pin the scale down. On real data the residual holds model error too (the accelerometer bias is not
  // estimated here), so it says more about the fit than about the scale's true error; the agent logs it.
  double scale_sigma_relative = 0.0;
  geometry::SO3d R_w_v;  // rotates v into the gravity-aligned world
  Eigen::Vector3d gyro_bias = Eigen::Vector3d::Zero();
  double time_correction_s = 0.0;                 // estimated (estimate_time_offset), else the newest keyframe's
  Eigen::Vector3d g_v = Eigen::Vector3d::Zero();  // gravity in v after refinement
  std::vector<Eigen::Vector3d> v_w;               // keyframe velocities in the world frame
  std::vector<geometry::SE3d> T_w_s;              // keyframe IMU poses, metric and gravity-aligned
};

// `preintegrations[k]` runs from keyframe k to k+1 (so there is one fewer than keyframes); T_s_c is the
// camera-IMU extrinsics. Needs at least 4 keyframes.
Result<VisualInertialAlignment> alignVisualInertial(const std::vector<VisualKeyframe>& keyframes,
                                                    const std::vector<Preintegration>& preintegrations,
                                                    const geometry::SE3d& T_s_c,
                                                    const VisualInertialAlignmentOptions& options = {});

}  // namespace cvislam::imu
