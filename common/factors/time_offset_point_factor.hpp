// An inverse-depth point observation whose image was taken at an unknown time on the IMU's clock: the
// camera-IMU time offset td as a state of the bundle adjustment (as VINS-Mono and OpenVINS estimate it).
//
// A keyframe's state (pose, velocity) is at t_k = t_cam_k + c_k on the IMU's clock, c_k being the offset its frame
// time was corrected by when tracking made it. Its image was really taken at t_cam_k + td = t_k + d_k, with
// d_k = td - c_k. Over the few milliseconds of d_k the body turns at its angular rate w_k and moves at its velocity
// v_k, so the camera saw from
//   R_w_s' = R_w_s Exp(w_k d_k),   p_w_s' = p_w_s + v_k d_k
// (the acceleration's 1/2 a d^2 is under a millimetre for tens of milliseconds). Both the observing keyframe i and
// the point's reference keyframe r are shifted so; the residual is then InverseDepthPointFactor's on the shifted
// poses. w_k (gyro minus bias) and v_k are constants of the factor, taken when the problem is built: they enter
// multiplied by d_k, so an error of 1 cm/s in v_k moves the pose 0.3 mm at 30 ms. Setting both to zero for a keyframe
// (an anchor from the server, whose clock is not ours) leaves its pose unshifted.
//
// Jacobians, from the tangent Jacobians J' of the inner factor at the shifted poses ([dp, dphi], right
// perturbations):
//   d/d(pose): position as is; rotation J'_phi Exp(-w d) (a right perturbation before the shift moves
//              through it);
//   d/d(td):   J'_i [v_i; w_i] + J'_r [v_r; w_r] (Exp(w d) and Exp(w e) commute, so the shift's derivative is w).
#pragma once

#include <memory>

#include <ceres/sized_cost_function.h>

#include "common/factors/inverse_depth_point_factor.hpp"

namespace cvislam::factors {

// The motion of a keyframe over its time shift: its velocity and angular rate at its own time, and the time
// correction c_k [s] its frame time already carries.
struct KeyframeMotion {
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  Eigen::Vector3d omega_s = Eigen::Vector3d::Zero();  // gyro minus bias, in the body (IMU) frame [rad/s]
  double time_correction_s = 0.0;
};

// Blocks: observing pose T_w_si (7), reference pose T_w_sr (7), extrinsics T_s_c (7), point m (3), td (1) [s].
class TimeOffsetPointFactor final
    : public ceres::SizedCostFunction<2, kPoseSize, kPoseSize, kPoseSize, kInverseDepthPointSize, 1> {
 public:
  // `observation` is the factor of the same observation without the offset (cam0 or cam1); it becomes this one's.
  TimeOffsetPointFactor(std::unique_ptr<const InverseDepthPointFactor> observation, const KeyframeMotion& observing,
                        const KeyframeMotion& reference);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

 private:
  std::unique_ptr<const InverseDepthPointFactor> observation_;
  KeyframeMotion observing_;
  KeyframeMotion reference_;
};

}  // namespace cvislam::factors
