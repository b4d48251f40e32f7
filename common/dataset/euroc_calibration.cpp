#include "common/dataset/euroc_calibration.hpp"

#include <Eigen/Core>

namespace cvislam::dataset {

namespace {

geometry::SE3d fromRowMajor(const double (&m)[12]) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) T(r, c) = m[r * 4 + c];
  }
  return geometry::SE3d(T);
}

}  // namespace

CameraCalibration eurocCam0() {
  CameraCalibration cam;
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
  cam.comment = "cvislam_sim, EuRoC cam0 (MT9M034) calibration";
  return cam;
}

CameraCalibration eurocCam1() {
  CameraCalibration cam = eurocCam0();
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

ImuCalibration eurocImu() {
  ImuCalibration imu;
  imu.rate_hz = 200.0;
  imu.gyro_noise_density = 1.6968e-04;
  imu.gyro_random_walk = 1.9393e-05;
  imu.accel_noise_density = 2.0e-3;
  imu.accel_random_walk = 3.0e-3;
  imu.T_b_i = geometry::SE3d();
  imu.comment = "cvislam_sim, EuRoC VI-Sensor IMU (ADIS16448) noise figures";
  return imu;
}

}  // namespace cvislam::dataset
