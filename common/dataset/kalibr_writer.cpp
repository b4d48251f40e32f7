#include <cstdio>

#include "common/dataset/kalibr.hpp"

namespace cvislam::dataset {
namespace {

std::string number(double v) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.17g", v);
  return text;
}

std::string cameraYaml(const CameraCalibration& c, double timeshift_s, const geometry::SE3d& T_b_i) {
  // Kalibr's T_cam_imu maps IMU coordinates into the camera.
  const Eigen::Matrix4d T = (c.T_b_c.inverse() * T_b_i).matrix();
  std::string out = c.name + ":\n  T_cam_imu:\n";
  for (int r = 0; r < 4; ++r) {
    out += "  - [";
    for (int k = 0; k < 4; ++k) out += number(T(r, k)) + (k < 3 ? ", " : "]\n");
  }
  out += "  camera_model: pinhole\n";
  out += "  distortion_coeffs: [" + number(c.distortion_coefficients[0]) + ", " + number(c.distortion_coefficients[1]) +
         ", " + number(c.distortion_coefficients[2]) + ", " + number(c.distortion_coefficients[3]) + "]\n";
  out += std::string("  distortion_model: ") +
         (c.distortion == DistortionModel::kEquidistant ? "equidistant" : "radtan") + "\n";
  out += "  intrinsics: [" + number(c.fx) + ", " + number(c.fy) + ", " + number(c.cx) + ", " + number(c.cy) + "]\n";
  out += "  resolution: [" + std::to_string(c.width) + ", " + std::to_string(c.height) + "]\n";
  out += "  rostopic: /" + c.name + "/image_raw\n";
  out += "  timeshift_cam_imu: " + number(timeshift_s) + "\n";
  return out;
}

}  // namespace

std::string kalibrCamchainYaml(const CameraCalibration& cam0, const std::optional<CameraCalibration>& cam1,
                               std::int64_t timeshift_cam_imu_ns, const geometry::SE3d& T_b_i) {
  const double timeshift_s = static_cast<double>(timeshift_cam_imu_ns) * 1e-9;
  std::string out = cameraYaml(cam0, timeshift_s, T_b_i);
  if (cam1) out += cameraYaml(*cam1, timeshift_s, T_b_i);
  return out;
}

std::string kalibrImuYaml(const ImuCalibration& imu, bool nested_imu) {
  const std::string indent = nested_imu ? "  " : "";
  std::string out = nested_imu ? "imu0:\n" : "";
  out += indent + "T_i_b:\n";
  for (int r = 0; r < 4; ++r)
    out += indent + "- [" + (r == 0 ? "1" : "0") + ", " + (r == 1 ? "1" : "0") + ", " + (r == 2 ? "1" : "0") + ", " +
           (r == 3 ? "1" : "0") + "]\n";
  out += indent + "accelerometer_noise_density: " + number(imu.accel_noise_density) + "\n";
  out += indent + "accelerometer_random_walk: " + number(imu.accel_random_walk) + "\n";
  out += indent + "gyroscope_noise_density: " + number(imu.gyro_noise_density) + "\n";
  out += indent + "gyroscope_random_walk: " + number(imu.gyro_random_walk) + "\n";
  out += indent + "model: calibrated\n";
  out += indent + "rostopic: /imu0\n";
  out += indent + "time_offset: 0.0\n";
  out += indent + "update_rate: " + number(imu.rate_hz) + "\n";
  return out;
}

}  // namespace cvislam::dataset
