// The whitened pinhole projection every reprojection factor ends with (reprojection_factor.cpp,
// inverse_depth_point_factor.cpp): one place for the "in front of the camera" test and d(residual)/dh.
#pragma once

#include <Eigen/Core>

#include "common/factors/pinhole_intrinsics.hpp"

namespace cvislam::factors::detail {

// Projects h (the point in the observing camera, up to a positive scale), writes the whitened residual
// (pi(h) - keypoint) / sigma and returns d(residual)/dh; false when h is not in front (h_z <= kMinProjectionDepth |h|).
inline bool projectWhitened(const Eigen::Vector3d& h, const Eigen::Vector2d& keypoint_px, const PinholeIntrinsics& K,
                            double inv_sigma, double* residuals, Eigen::Matrix<double, 2, 3>& d_r_d_h) {
  if (!(h.z() > kMinProjectionDepth * h.norm())) return false;
  const double inv_z = 1.0 / h.z();
  const double u = K.fx * h.x() * inv_z + K.cx;
  const double v = K.fy * h.y() * inv_z + K.cy;
  residuals[0] = inv_sigma * (u - keypoint_px.x());
  residuals[1] = inv_sigma * (v - keypoint_px.y());
  d_r_d_h << K.fx * inv_z, 0.0, -K.fx * h.x() * inv_z * inv_z,  //
      0.0, K.fy * inv_z, -K.fy * h.y() * inv_z * inv_z;
  d_r_d_h *= inv_sigma;
  return true;
}

}  // namespace cvislam::factors::detail
