// A pinhole camera's intrinsics in pixels, as the factors, the pose optimisers and the bundle adjustments take
// them, and the depth below which a projection is not evaluated. Free of Ceres, so that the headers that pass
// intrinsics around do not pull Ceres into every file that includes them.
#pragma once

namespace cvislam::factors {

struct PinholeIntrinsics {
  double fx = 458.654;
  double fy = 457.296;
  double cx = 367.215;
  double cy = 248.375;
};

// Residuals whose point lies closer to the image plane than this (h_z <= kMinDepth * |h|) are reported as
// not evaluable, so Ceres rejects the step that put the point behind the camera.
inline constexpr double kMinProjectionDepth = 1e-6;

}  // namespace cvislam::factors
