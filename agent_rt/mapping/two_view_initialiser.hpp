// Monocular map initialisation from two keyframes (CVI-SLAM IV-C, as ORB-SLAM): the essential matrix from
// matched bearings by RANSAC (OpenCV calib3d, five-point), the relative pose with the cheirality check, and
// the inlier points triangulated. The translation has unit length: the scale is unknown until the IMU is
// initialised. OpenCV stays inside the .cpp.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::agent {

struct TwoViewOptions {
  double ransac_threshold_px = 1.0;  // Sampson distance, converted with the focal length
  double focal_px = 458.0;
  double confidence = 0.999;
  int min_inliers = 50;
  double min_median_parallax_deg = 1.0;
};

struct TwoViewResult {
  geometry::SE3d T_c0_c1;             // |t| = 1
  std::vector<std::uint8_t> inlier;   // per match: triangulated, in front of both, enough parallax
  std::vector<Eigen::Vector3d> p_c0;  // per match (valid where inlier), in camera 0
  int inliers = 0;
  double median_parallax_deg = 0.0;
};

// bearings0[i] and bearings1[i] are a match (unit or z = 1 vectors in each camera).
Result<TwoViewResult> initialiseTwoView(std::span<const Eigen::Vector3d> bearings0,
                                        std::span<const Eigen::Vector3d> bearings1, const TwoViewOptions& options);

}  // namespace cvislam::agent
