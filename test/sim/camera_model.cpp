#include "test/sim/camera_model.hpp"

#include <cmath>

#include <Eigen/LU>

namespace cvislam::sim {

namespace {

geometry::SE3d fromRowMajor(const double (&m)[12]) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) T(r, c) = m[r * 4 + c];
  }
  return geometry::SE3d(T);
}

}  // namespace

dataset::CameraCalibration eurocCam0() {
  dataset::CameraCalibration cam;
  cam.name = "cam0";
  cam.width = 752;
  cam.height = 480;
  cam.rate_hz = 20.0;
  cam.fx = 458.654;
  cam.fy = 457.296;
  cam.cx = 367.215;
  cam.cy = 248.375;
  cam.distortion = dataset::DistortionModel::kRadialTangential;
  cam.distortion_coefficients = {-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05};
  const double T_b_c_rows[12] = {0.0148655429818,  -0.999880929698,  0.00414029679422, -0.0216401454975,
                                 0.999557249008,   0.0149672133247,  0.025715529948,   -0.064676986768,
                                 -0.0257744366974, 0.00375618835797, 0.999660727178,   0.00981073058949};
  cam.T_b_c = fromRowMajor(T_b_c_rows);
  // No colon in comments: writeCameraCalibration() writes them as plain YAML scalars.
  cam.comment = "cvislam_sim, EuRoC cam0 (MT9M034) calibration";
  return cam;
}

dataset::CameraCalibration eurocCam1() {
  dataset::CameraCalibration cam = eurocCam0();
  cam.name = "cam1";
  cam.fx = 457.587;
  cam.fy = 456.134;
  cam.cx = 379.999;
  cam.cy = 255.238;
  cam.distortion_coefficients = {-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05};
  const double T_b_c_rows[12] = {0.0125552670891,  -0.999755099723, 0.0182237714554, -0.0198435579556,
                                 0.999598781151,   0.0130119051815, 0.0251588363115, 0.0453689425024,
                                 -0.0253898008918, 0.0179005838253, 0.999517347078,  0.00786212447038};
  cam.T_b_c = fromRowMajor(T_b_c_rows);
  cam.comment = "cvislam_sim, EuRoC cam1 (MT9M034) calibration";
  return cam;
}

dataset::ImuCalibration eurocImu() {
  dataset::ImuCalibration imu;
  imu.rate_hz = 200.0;
  imu.gyro_noise_density = 1.6968e-04;
  imu.gyro_random_walk = 1.9393e-05;
  imu.accel_noise_density = 2.0e-3;
  imu.accel_random_walk = 3.0e-3;
  imu.T_b_i = geometry::SE3d();
  imu.comment = "cvislam_sim, EuRoC VI-Sensor IMU (ADIS16448) noise figures";
  return imu;
}

Result<CameraModel> CameraModel::create(const dataset::CameraCalibration& calibration) {
  if (calibration.distortion != dataset::DistortionModel::kNone &&
      calibration.distortion != dataset::DistortionModel::kRadialTangential) {
    return Error{ErrorCode::kInvalidArgument,
                 calibration.name +
                     ": the simulator renders pinhole cameras with radial-tangential or no "
                     "distortion, not " +
                     std::string(dataset::toString(calibration.distortion))};
  }
  if (calibration.width <= 0 || calibration.height <= 0 || calibration.fx <= 0.0 || calibration.fy <= 0.0) {
    return Error{ErrorCode::kInvalidArgument, calibration.name + ": resolution and focal lengths must be positive"};
  }
  return CameraModel(calibration);
}

Eigen::Vector2d CameraModel::distort(const Eigen::Vector2d& x, Eigen::Matrix2d* J_d_x) const {
  if (calibration_.distortion == dataset::DistortionModel::kNone) {
    if (J_d_x) J_d_x->setIdentity();
    return x;
  }
  const auto& k = calibration_.distortion_coefficients;
  const double k1 = k[0], k2 = k[1], p1 = k[2], p2 = k[3];
  const double u = x.x(), v = x.y();
  const double r2 = u * u + v * v;
  const double radial = 1.0 + k1 * r2 + k2 * r2 * r2;
  Eigen::Vector2d d(u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u),
                    v * radial + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v);
  if (J_d_x) {
    const double d_radial_d_r2 = k1 + 2.0 * k2 * r2;
    (*J_d_x)(0, 0) = radial + u * d_radial_d_r2 * 2.0 * u + 2.0 * p1 * v + p2 * 6.0 * u;
    (*J_d_x)(0, 1) = u * d_radial_d_r2 * 2.0 * v + 2.0 * p1 * u + p2 * 2.0 * v;
    (*J_d_x)(1, 0) = v * d_radial_d_r2 * 2.0 * u + p1 * 2.0 * u + 2.0 * p2 * v;
    (*J_d_x)(1, 1) = radial + v * d_radial_d_r2 * 2.0 * v + p1 * 6.0 * v + 2.0 * p2 * u;
  }
  return d;
}

Eigen::Vector2d CameraModel::distortedPixel(const Eigen::Vector2d& normalized) const {
  const Eigen::Vector2d d = distort(normalized, nullptr);
  return {calibration_.fx * d.x() + calibration_.cx, calibration_.fy * d.y() + calibration_.cy};
}

std::optional<Eigen::Vector2d> CameraModel::project(const Eigen::Vector3d& p_c) const {
  constexpr double kMinDepthM = 1e-3;
  if (p_c.z() < kMinDepthM) return std::nullopt;
  return distortedPixel(p_c.head<2>() / p_c.z());
}

Eigen::Vector3d CameraModel::unproject(const Eigen::Vector2d& pixel) const {
  const Eigen::Vector2d target((pixel.x() - calibration_.cx) / calibration_.fx,
                               (pixel.y() - calibration_.cy) / calibration_.fy);
  Eigen::Vector2d x = target;
  constexpr int kMaxIterations = 50;
  for (int i = 0; i < kMaxIterations; ++i) {
    Eigen::Matrix2d J;
    const Eigen::Vector2d residual = distort(x, &J) - target;
    if (residual.squaredNorm() < 1e-24) break;
    x -= J.partialPivLu().solve(residual);
  }
  return Eigen::Vector3d(x.x(), x.y(), 1.0).normalized();
}

}  // namespace cvislam::sim
