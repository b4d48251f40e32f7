#include "common/camera/camera_model.hpp"

#include <cmath>
#include <string>

#include <Eigen/LU>

#include "common/core/check.hpp"

namespace cvislam::camera {

using Eigen::Matrix2d;
using Eigen::Vector2d;
using Eigen::Vector3d;

Result<CameraModel> CameraModel::create(const dataset::CameraCalibration& calibration) {
  const auto fail = [&](const std::string& what) {
    return Error{ErrorCode::kInvalidArgument, "camera '" + calibration.name + "': " + what};
  };
  if (calibration.width <= 0 || calibration.height <= 0) return fail("the resolution must be positive");
  if (!(calibration.fx > 0.0) || !(calibration.fy > 0.0) || !std::isfinite(calibration.fx) ||
      !std::isfinite(calibration.fy)) {
    return fail("the focal lengths fx, fy must be positive and finite");
  }
  if (!std::isfinite(calibration.cx) || !std::isfinite(calibration.cy)) {
    return fail("the principal point cx, cy must be finite");
  }
  for (const double k : calibration.distortion_coefficients) {
    if (!std::isfinite(k)) return fail("a distortion coefficient is not finite");
  }
  return CameraModel(calibration);
}

Vector2d CameraModel::distort(const Vector2d& x, Matrix2d* J_d_x) const {
  const auto& k = calibration_.distortion_coefficients;
  switch (calibration_.distortion) {
    case dataset::DistortionModel::kNone:
      if (J_d_x != nullptr) J_d_x->setIdentity();
      return x;
    case dataset::DistortionModel::kRadialTangential: {
      const double k1 = k[0];
      const double k2 = k[1];
      const double p1 = k[2];
      const double p2 = k[3];
      const double u = x.x();
      const double v = x.y();
      const double r2 = u * u + v * v;
      const double radial = 1.0 + k1 * r2 + k2 * r2 * r2;
      Vector2d d(u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u),
                 v * radial + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v);
      if (J_d_x != nullptr) {
        const double d_radial_d_r2 = k1 + 2.0 * k2 * r2;
        (*J_d_x)(0, 0) = radial + 2.0 * u * u * d_radial_d_r2 + 2.0 * p1 * v + 6.0 * p2 * u;
        (*J_d_x)(0, 1) = 2.0 * u * v * d_radial_d_r2 + 2.0 * p1 * u + 2.0 * p2 * v;
        (*J_d_x)(1, 0) = 2.0 * u * v * d_radial_d_r2 + 2.0 * p1 * u + 2.0 * p2 * v;
        (*J_d_x)(1, 1) = radial + 2.0 * v * v * d_radial_d_r2 + 6.0 * p1 * v + 2.0 * p2 * u;
      }
      return d;
    }
    case dataset::DistortionModel::kEquidistant: {
      // theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), theta = atan(r); x_d = theta_d / r x.
      const double r = x.norm();
      if (r < 1e-10) {  // theta_d / r -> 1
        if (J_d_x != nullptr) J_d_x->setIdentity();
        return x;
      }
      const double theta = std::atan(r);
      const double t2 = theta * theta;
      const double poly = 1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])));
      const double theta_d = theta * poly;
      const double scale = theta_d / r;
      if (J_d_x != nullptr) {
        const double d_poly_d_theta = theta * (2.0 * k[0] + t2 * (4.0 * k[1] + t2 * (6.0 * k[2] + t2 * 8.0 * k[3])));
        const double d_theta_d_d_r = (poly + theta * d_poly_d_theta) / (1.0 + r * r);
        const double d_scale_d_r = (d_theta_d_d_r - scale) / r;
        *J_d_x = scale * Matrix2d::Identity() + (d_scale_d_r / r) * x * x.transpose();
      }
      return scale * x;
    }
  }
  return x;
}

Vector2d CameraModel::undistort(const Vector2d& distorted) const {
  if (calibration_.distortion == dataset::DistortionModel::kNone) return distorted;
  Vector2d x = distorted;
  constexpr int kMaxIterations = 50;
  for (int i = 0; i < kMaxIterations; ++i) {
    Matrix2d J;
    const Vector2d residual = distort(x, &J) - distorted;
    if (residual.squaredNorm() < 1e-24) break;
    x -= J.partialPivLu().solve(residual);
  }
  return x;
}

Vector2d CameraModel::distortedPixel(const Vector2d& normalized) const {
  const Vector2d d = distort(normalized);
  return {calibration_.fx * d.x() + calibration_.cx, calibration_.fy * d.y() + calibration_.cy};
}

std::optional<Vector2d> CameraModel::project(const Vector3d& p_c, Eigen::Matrix<double, 2, 3>* J_px_p) const {
  constexpr double kMinDepthM = 1e-3;
  if (p_c.z() < kMinDepthM) return std::nullopt;
  const double inv_z = 1.0 / p_c.z();
  const Vector2d normalized = p_c.head<2>() * inv_z;
  Matrix2d J_d_x;
  const Vector2d d = distort(normalized, J_px_p != nullptr ? &J_d_x : nullptr);
  if (J_px_p != nullptr) {
    Eigen::Matrix<double, 2, 3> J_x_p;
    J_x_p << inv_z, 0.0, -normalized.x() * inv_z,  //
        0.0, inv_z, -normalized.y() * inv_z;
    *J_px_p = Eigen::Vector2d(calibration_.fx, calibration_.fy).asDiagonal() * J_d_x * J_x_p;
  }
  return Vector2d(calibration_.fx * d.x() + calibration_.cx, calibration_.fy * d.y() + calibration_.cy);
}

Vector3d CameraModel::unproject(const Vector2d& pixel) const {
  const Vector2d x = undistort(
      Vector2d((pixel.x() - calibration_.cx) / calibration_.fx, (pixel.y() - calibration_.cy) / calibration_.fy));
  return Vector3d(x.x(), x.y(), 1.0).normalized();
}

Vector2d CameraModel::undistortPixel(const Vector2d& pixel) const {
  const Vector2d x = undistort(
      Vector2d((pixel.x() - calibration_.cx) / calibration_.fx, (pixel.y() - calibration_.cy) / calibration_.fy));
  return {calibration_.fx * x.x() + calibration_.cx, calibration_.fy * x.y() + calibration_.cy};
}

void CameraModel::undistortPixels(std::span<const Vector2d> pixels, std::span<Vector2d> undistorted) const {
  CVISLAM_CHECK(pixels.size() == undistorted.size(), "undistortPixels: output must be as long as the input");
  for (std::size_t i = 0; i < pixels.size(); ++i) undistorted[i] = undistortPixel(pixels[i]);
}

}  // namespace cvislam::camera
