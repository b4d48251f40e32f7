// Camera models: pinhole with no, radial-tangential (OpenCV's 4-coefficient plumb bob) or equidistant
// (Kannala-Brandt, OpenCV's fisheye, Kalibr's "equidistant") distortion, as EuRoC's sensor.yaml describes.
//
// Frames and conventions: p_c is a point in the camera frame (z forward); normalised coordinates are
// (x/z, y/z); pixels have their centres at integer coordinates (OpenCV). "Undistorted pixels" are what an
// ideal pinhole with the same fx, fy, cx, cy would see: the reprojection factor works on those.
//
// Everything is fixed-size and allocation-free, for the agent's tracking thread.
#pragma once

#include <optional>
#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::camera {

class CameraModel {
 public:
  // Checks the calibration (positive sizes and focal lengths, finite coefficients); the message names the
  // camera and the field.
  static Result<CameraModel> create(const dataset::CameraCalibration& calibration);

  // Distorts normalised coordinates; J_d_x, when given, receives d(distorted)/d(normalised).
  [[nodiscard]] Eigen::Vector2d distort(const Eigen::Vector2d& normalized, Eigen::Matrix2d* J_d_x = nullptr) const;
  // Inverts distort() by Gauss-Newton, to 1e-12 in normalised coordinates.
  [[nodiscard]] Eigen::Vector2d undistort(const Eigen::Vector2d& distorted) const;

  // Distorts normalised coordinates and applies the intrinsics.
  [[nodiscard]] Eigen::Vector2d distortedPixel(const Eigen::Vector2d& normalized) const;
  // Projects a point in the camera frame; nothing for points at or behind z = 1 mm. J_px_p, when given,
  // receives the 2x3 Jacobian of the pixel with respect to p_c.
  [[nodiscard]] std::optional<Eigen::Vector2d> project(const Eigen::Vector3d& p_c,
                                                       Eigen::Matrix<double, 2, 3>* J_px_p = nullptr) const;
  // The unit ray (camera frame) through a pixel. Rays are taken in front of the camera (z > 0), so an
  // equidistant lens is supported up to a field of view just under 180 deg.
  [[nodiscard]] Eigen::Vector3d unproject(const Eigen::Vector2d& pixel) const;

  // A distorted (measured) pixel to the ideal pinhole pixel with the same intrinsics.
  [[nodiscard]] Eigen::Vector2d undistortPixel(const Eigen::Vector2d& pixel) const;
  // The same for many keypoints, into caller-owned storage of the same size (no allocation).
  void undistortPixels(std::span<const Eigen::Vector2d> pixels, std::span<Eigen::Vector2d> undistorted) const;

  [[nodiscard]] const dataset::CameraCalibration& calibration() const { return calibration_; }
  [[nodiscard]] int width() const { return calibration_.width; }
  [[nodiscard]] int height() const { return calibration_.height; }

 private:
  explicit CameraModel(const dataset::CameraCalibration& calibration) : calibration_(calibration) {}

  dataset::CameraCalibration calibration_;
};

}  // namespace cvislam::camera
