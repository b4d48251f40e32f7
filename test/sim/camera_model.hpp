// The simulator's camera: EuRoC calibration defaults, projection with radial-tangential distortion, and the
// inverse (pixel -> ray) that the renderer tabulates once per camera.
#pragma once

#include <optional>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::sim {

// EuRoC MAV calibration (ASL sensor.yaml of cam0, cam1, imu0), built in so that the simulator does not
// need ../shared/data. test/sim/camera_model_test.cpp checks them against the shared sensor.yaml files.
dataset::CameraCalibration eurocCam0();
dataset::CameraCalibration eurocCam1();
dataset::ImuCalibration eurocImu();

// Pinhole + radial-tangential (or no) distortion. Pixel centres are at integer coordinates (OpenCV).
class CameraModel {
 public:
  // Only kNone and kRadialTangential are supported; create() says so for other models.
  static Result<CameraModel> create(const dataset::CameraCalibration& calibration);

  // Distorts normalised coordinates (x/z, y/z) and applies the intrinsics.
  [[nodiscard]] Eigen::Vector2d distortedPixel(const Eigen::Vector2d& normalized) const;
  // Projects a point in the camera frame; nothing for points at or behind z = 1 mm.
  [[nodiscard]] std::optional<Eigen::Vector2d> project(const Eigen::Vector3d& p_c) const;
  // The unit ray (camera frame) through a pixel position; inverts the distortion by Gauss-Newton to
  // 1e-12 in normalised coordinates.
  [[nodiscard]] Eigen::Vector3d unproject(const Eigen::Vector2d& pixel) const;

  [[nodiscard]] const dataset::CameraCalibration& calibration() const { return calibration_; }
  [[nodiscard]] int width() const { return calibration_.width; }
  [[nodiscard]] int height() const { return calibration_.height; }

 private:
  explicit CameraModel(const dataset::CameraCalibration& calibration) : calibration_(calibration) {}
  // Distortion of normalised coordinates and its 2x2 Jacobian.
  [[nodiscard]] Eigen::Vector2d distort(const Eigen::Vector2d& x, Eigen::Matrix2d* J_d_x) const;

  dataset::CameraCalibration calibration_;
};

}  // namespace cvislam::sim
