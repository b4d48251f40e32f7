// Motion-only visual-inertial BA of tracking (CVI-SLAM IV-C, "motion-only BA ... with the IMU terms"): the
// pose T_w_s and velocity v_w of the current frame that best fit the matched map points and the IMU
// preintegrated from the newest keyframe, whose state (pose, velocity, biases) is held fixed. It smooths the
// vision-only pose and gives tracking a velocity for the next prediction.
//
// Gauss-Newton on 9 dof [dp, dphi, dv] (right rotation perturbation, world-frame translation and velocity),
// reprojection terms with a Huber kernel and chi-square outlier rounds as in optimizePose(), and the 9-dof
// IMU residual [r_R, r_v, r_p] of the IMU factor whitened by the preintegration's square-root information.
// Fixed-size maths only: nothing allocates on success.
//
// optimizeMotionWindow() is the paper's form over the newest n keyframes: they and the frame are chained by
// the IMU between consecutive keyframes and from the newest keyframe to the frame. The oldest of them is
// held fixed: it carries into the window what local BA knows of velocity and biases, which the window's own
// few IMU links cannot recover (with it free, velocities came out worse on the simulated flights). The
// others' poses and velocities are optimised with the frame's against the map points they observe (held
// fixed). Biases stay at the keyframes' (local BA's) values. optimizePoseInertial() is the n = 1 case.
#pragma once

#include <cstdint>
#include <span>

#include <Eigen/Core>

#include "agent_rt/map/capacities.hpp"
#include "agent_rt/tracking/pose_optimizer.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

// The fixed keyframe state the IMU term hangs from, and the IMU from it to the frame.
struct InertialAnchor {
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
  const imu::Preintegration* preintegration = nullptr;  // keyframe -> frame, at least one sample
};

struct InertialPoseResult {
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  int inliers = 0;
  int iterations = 0;
  double imu_chi2 = 0.0;  // whitened squared IMU residual at the end
};

// The IMU residual [r_R, r_v, r_p] (unwhitened) between the fixed anchor and the frame state, and, when J is
// given, its Jacobian with respect to the frame's tangent [dp, dphi, dv].
Eigen::Matrix<double, 9, 1> inertialResidual(const InertialAnchor& anchor, const geometry::SE3d& T_w_s,
                                             const Eigen::Vector3d& v_w, Eigen::Matrix<double, 9, 9>* J);

// The same residual with both states free: J_i and J_j (when given) are its Jacobians with respect to the
// tangents [dp, dphi, dv] of state i (where the IMU starts) and state j.
Eigen::Matrix<double, 9, 1> inertialResidualBetween(const InertialAnchor& i, const geometry::SE3d& T_w_sj,
                                                    const Eigen::Vector3d& v_wj, Eigen::Matrix<double, 9, 9>* J_i,
                                                    Eigen::Matrix<double, 9, 9>* J_j);

// A keyframe of the motion-only BA window. Its pose and velocity are optimised (the first's are held), its
// biases held.
struct MotionWindowKeyframe {
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
  std::span<const PoseObservation> observations;  // may be empty: a keyframe mapping has not sent back yet;
                                                  // unused for the first (held) keyframe
  std::span<std::uint8_t> is_outlier;             // as long as observations; receives the classification
  const imu::Preintegration* to_next = nullptr;   // the IMU to the next keyframe of the window, or to the frame
};

// The window: up to kMaxMotionBaKeyframes keyframes from the snapshot and the newest one tracking published
// and mapping has not returned yet.
inline constexpr std::size_t kMaxMotionWindowKeyframes = kMaxMotionBaKeyframes + 1;

struct MotionWindowResult {
  geometry::SE3d T_w_s;  // the frame's
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  int inliers = 0;           // the frame's
  int keyframe_inliers = 0;  // of the optimised keyframes
  int iterations = 0;
  double imu_chi2 = 0.0;  // whitened squared IMU residuals, summed over the links, at the end
};

// `keyframes` oldest first, at least one (the held one), at most kMaxMotionWindowKeyframes; each with its IMU
// to the next (the last one's to the frame). Fails when the frame keeps fewer than min_inliers.
Result<MotionWindowResult> optimizeMotionWindow(std::span<MotionWindowKeyframe> keyframes,
                                                std::span<const PoseObservation> observations,
                                                const geometry::SE3d& T_w_s_initial, const Eigen::Vector3d& v_w_initial,
                                                const geometry::SE3d& T_s_c,
                                                const factors::PinholeIntrinsics& intrinsics,
                                                const PoseOptimizerOptions& options,
                                                std::span<std::uint8_t> is_outlier);

Result<InertialPoseResult> optimizePoseInertial(std::span<const PoseObservation> observations,
                                                const geometry::SE3d& T_w_s_initial, const Eigen::Vector3d& v_w_initial,
                                                const InertialAnchor& anchor, const geometry::SE3d& T_s_c,
                                                const factors::PinholeIntrinsics& intrinsics,
                                                const PoseOptimizerOptions& options,
                                                std::span<std::uint8_t> is_outlier);

}  // namespace cvislam::agent
