// Motion-only visual-inertial BA of tracking (CVI-SLAM IV-C, "motion-only BA ... with the IMU terms"): the
// pose T_w_s and velocity v_w of the current frame that best fit the matched map points and the IMU
// preintegrated from the newest keyframe, whose state (pose, velocity, biases) is held fixed. It smooths the
// vision-only pose and gives tracking a velocity for the next prediction.
//
// Gauss-Newton on 9 dof [dp, dphi, dv] (right rotation perturbation, world-frame translation and velocity),
// reprojection terms with a Huber kernel and chi-square outlier rounds as in optimizePose(), and the 9-dof
// IMU residual [r_R, r_v, r_p] of the IMU factor whitened by the preintegration's square-root information.
// Fixed-size maths only: nothing allocates on success.
#pragma once

#include <cstdint>
#include <span>

#include <Eigen/Core>

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

Result<InertialPoseResult> optimizePoseInertial(std::span<const PoseObservation> observations,
                                                const geometry::SE3d& T_w_s_initial, const Eigen::Vector3d& v_w_initial,
                                                const InertialAnchor& anchor, const geometry::SE3d& T_s_c,
                                                const factors::PinholeIntrinsics& intrinsics,
                                                const PoseOptimizerOptions& options,
                                                std::span<std::uint8_t> is_outlier);

}  // namespace cvislam::agent
