// Motion-only pose optimisation for tracking: the IMU pose T_w_s of one frame that best reprojects a set of
// fixed map points onto their matched (undistorted) keypoints, robust to wrong matches.
//
// Gauss-Newton on the 6-dof pose (right perturbation of the rotation, world-frame translation, as everywhere in
// cvislam) with a Huber kernel, in rounds: after each round, observations whose chi-square exceeds the 2-dof
// 95 % bound (5.991) are marked outliers and left out of the next round, and outliers that fit again come
// back (as ORB-SLAM does). Fixed-size maths only: nothing allocates, so tracking can call it every frame.
//
// A residual test cannot catch a wrong match that the pose fits by itself. Map points a few metres ahead leave the
// pose a nearly flat valley (a sideways step and a small turn move them alike); one wrong point much nearer the
// camera can then drag the pose along it until it fits, and every match is an inlier. So after the first round,
// observations with a leverage (their share of the fit, the hat-matrix diagonal) above max_leverage sit out the
// second round. The pose found without them then decides whether they come back: by their residual against that
// pose with its own uncertainty added (a right match of a near point still fits within the valley's width; the
// wrong one lies far outside it).
// Seen in tracking after a frame had waited for the first map: no velocity yet, the prediction 4 cm behind, and
// the frame tracked 4 cm off through a wrong stereo depth.
#pragma once

#include <cstdint>
#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/factors/pinhole_intrinsics.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::agent {

struct PoseObservation {
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();          // map point, held fixed
  Eigen::Vector2d keypoint_px = Eigen::Vector2d::Zero();  // undistorted keypoint
  double sigma_px = 1.0;                                  // keypoint noise (grows with the pyramid level)
};

struct PoseOptimizerOptions {
  int rounds = 4;                 // outlier classification rounds
  int iterations_per_round = 10;  // Gauss-Newton iterations per round
  double chi2_threshold = 5.991;  // 2-dof, 95 %
  double huber_delta = 2.447;     // sqrt(5.991): the kernel turns linear where outliers begin
  double min_step = 1e-8;         // stop a round when the update is this small
  int min_inliers = 10;           // fewer and the result is refused
  // An observation that carries more than this share of the fit sits out the second round (see above); 1 never.
  // At least 0.5, so that at most 11 observations sit out (the leverages add up to 6).
  double max_leverage = 0.5;

  [[nodiscard]] Status validate() const;
};

struct PoseOptimizerResult {
  geometry::SE3d T_w_s;
  int inliers = 0;
  int held_out = 0;  // observations that sat out the second round for their leverage
  int iterations = 0;
  double final_chi2 = 0.0;  // sum over inliers
};

// Refines `T_w_s_initial`. `is_outlier` (same length as `observations`) receives the classification. Fails
// when fewer than min_inliers remain, naming the count.
Result<PoseOptimizerResult> optimizePose(std::span<const PoseObservation> observations,
                                         const geometry::SE3d& T_w_s_initial, const geometry::SE3d& T_s_c,
                                         const factors::PinholeIntrinsics& intrinsics,
                                         const PoseOptimizerOptions& options, std::span<std::uint8_t> is_outlier);

// The residual of one observation (pixels, unwhitened) and, when J is given, its Jacobian with respect to
// the pose tangent [dp, dphi]. False when the point is not in front of the camera.
bool poseReprojectionResidual(const PoseObservation& observation, const geometry::SE3d& T_w_s,
                              const geometry::SE3d& T_s_c, const factors::PinholeIntrinsics& intrinsics,
                              Eigen::Vector2d& residual, Eigen::Matrix<double, 2, 6>* J);

// The robust (Huber) normal equations of the reprojection terms that are not outliers, added to H and g
// (pose tangent [dp, dphi]); returns how many terms were used. Shared by optimizePose() and the
// visual-inertial optimisation.
int accumulateReprojection(std::span<const PoseObservation> observations, const geometry::SE3d& T_w_s,
                           const geometry::SE3d& T_s_c, const factors::PinholeIntrinsics& intrinsics,
                           double huber_delta, std::span<const std::uint8_t> is_outlier, Eigen::Matrix<double, 6, 6>& H,
                           Eigen::Matrix<double, 6, 1>& g);

// Classifies every observation again against the chi-square bound (so that a wrongly rejected one can come
// back); returns the inliers and adds their chi-square to *chi2 when given.
int classifyObservations(std::span<const PoseObservation> observations, const geometry::SE3d& T_w_s,
                         const geometry::SE3d& T_s_c, const factors::PinholeIntrinsics& intrinsics,
                         double chi2_threshold, std::span<std::uint8_t> is_outlier, double* chi2);

}  // namespace cvislam::agent
