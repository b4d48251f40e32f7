// Local bundle adjustment of the mapping thread (CVI-SLAM Eq. 10): the newest `window` keyframes (pose,
// velocity, biases) and the map points they observe are optimised; keyframes outside the window that share
// at least `min_covisible` points with it, anchors (which may come from other agents), and the reference
// keyframes of the points are held fixed. Reprojection factors with a Cauchy loss, IMU and bias random-walk
// factors between consecutive window keyframes. With a stereo rig, a keypoint's match in cam1 adds a second
// reprojection factor: in the point's reference keyframe it fixes the point's depth, elsewhere it ties the
// keyframe's pose to metric depth. A cam1 observation already further than `max_second_camera_error_sigma`
// from the point's projection is a stereo mismatch and is left out. When nothing is held fixed, the oldest window
// keyframe's pose is, for the gauge.
//
// Each point is one parameter block, its inverse-depth point (a, b, rho) in its reference camera
// (common/factors/inverse_depth_point_factor.hpp), converted from and back to the map's bearing and inverse
// distance; points are eliminated first (SPARSE_SCHUR with an explicit ordering), so the linear system that
// remains is over the keyframes only. A point with no inverse-depth point (corrupt: its bearing nearly in the
// reference image plane) is left out, unchanged.
//
// The camera-IMU time offset (the correction to the calibrated one, LocalMap::timeCorrectionS) can be one more
// state: every observation from another keyframe than the point's reference then shifts both keyframes' poses by
// the part of the offset their frame times do not carry yet (common/factors/time_offset_point_factor.hpp), and the
// map's offset becomes the solve's. A prior holds it near the last estimate, so that a window with little motion
// (where it is barely observable) does not throw it about; it is bounded to +-max_time_offset_s.
//
// Runs in the mapping thread and allocates (Ceres does); tracking never waits for it. A caller that has newer
// work waiting (the next keyframe) can stop it after any iteration: what the finished iterations gave is kept.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>

#include "agent_rt/map/local_map.hpp"
#include "common/core/result.hpp"
#include "common/factors/pinhole_intrinsics.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

struct LocalBundleAdjustmentOptions {
  int window = 10;         // M
  int min_covisible = 15;  // shared points that make an outside keyframe a fixed anchor
  int max_iterations = 10;
  double cauchy_scale = 1.0;          // on whitened residuals
  double sigma_px = 1.0;              // keypoint noise at pyramid level 0
  double pyramid_scale_factor = 1.2;  // the ORB pyramid's (OrbOptions::scale_factor): noise grows per level
  bool use_imu = true;
  factors::PinholeIntrinsics intrinsics;
  imu::ImuNoise noise;
  // Stereo (set by the mapper from the rig when there is a second camera).
  bool use_second_camera = false;
  factors::PinholeIntrinsics second_intrinsics;  // cam1's pinhole, for KeyframeData::right_undistorted_px
  geometry::SE3d T_c1_c0;
  double max_second_camera_error_sigma = 4.0;
  // The camera-IMU time offset as a state (only with use_imu: without metric velocities it is not observable).
  bool estimate_time_offset = false;
  double time_offset_prior_sigma_s = 0.005;  // how far one solve may move it from the last estimate, one sigma
  double max_time_offset_s = 0.1;            // bound on the correction, either way

  [[nodiscard]] Status validate() const;
};

struct LocalBundleAdjustmentSummary {
  int window_keyframes = 0;
  int fixed_keyframes = 0;
  int anchor_keyframes = 0;  // of the fixed ones: the server's
  // KeyframeData::sequence of the window's newest keyframe, and of the oldest of the agent's own fixed keyframes
  // (none when only anchors, or nothing, are held). Far apart when the window sees a place mapped long ago again.
  std::uint64_t newest_sequence = 0;
  std::optional<std::uint64_t> oldest_fixed_sequence;
  int map_points = 0;           // optimised
  int map_points_left_out = 0;  // observed by the window but with no inverse-depth point: not optimised
  int reprojection_factors = 0;
  int anchor_factors = 0;          // included in reprojection_factors: observations by anchors
  int second_camera_factors = 0;   // included in reprojection_factors
  int second_camera_rejected = 0;  // stereo mismatches left out
  int imu_factors = 0;
  int time_offset_factors = 0;  // included in reprojection_factors: those that carried the time offset
  int iterations = 0;
  bool stopped_early = false;  // `stop` ended the solve before its last iteration
  double initial_cost = 0.0;
  double final_cost = 0.0;
};

// `stop`, when given, is asked after every iteration but the last (not before the first: at least one step is
// taken); true ends the solve there, and the result so far is written back as after the last iteration.
Result<LocalBundleAdjustmentSummary> runLocalBundleAdjustment(LocalMap& map,
                                                              const LocalBundleAdjustmentOptions& options,
                                                              const std::function<bool()>& stop = {});

}  // namespace cvislam::agent
