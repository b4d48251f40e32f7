#include "test/support/kalibr_files.hpp"

#include <cstdio>
#include <fstream>

#include "common/dataset/calibration.hpp"

namespace cvislam::test {
namespace {

std::string number(double v) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.17g", v);
  return text;
}

std::string cameraYaml(const dataset::CameraCalibration& c, double timeshift_s) {
  // Kalibr's T_cam_imu maps IMU (body) coordinates into the camera.
  const Eigen::Matrix4d T = c.T_b_c.inverse().matrix();
  std::string out = c.name + ":\n  T_cam_imu:\n";
  for (int r = 0; r < 4; ++r) {
    out += "  - [";
    for (int k = 0; k < 4; ++k) out += number(T(r, k)) + (k < 3 ? ", " : "]\n");
  }
  out += "  camera_model: pinhole\n";
  out += "  distortion_coeffs: [" + number(c.distortion_coefficients[0]) + ", " + number(c.distortion_coefficients[1]) +
         ", " + number(c.distortion_coefficients[2]) + ", " + number(c.distortion_coefficients[3]) + "]\n";
  out += std::string("  distortion_model: ") +
         (c.distortion == dataset::DistortionModel::kEquidistant ? "equidistant" : "radtan") + "\n";
  out += "  intrinsics: [" + number(c.fx) + ", " + number(c.fy) + ", " + number(c.cx) + ", " + number(c.cy) + "]\n";
  out += "  resolution: [" + std::to_string(c.width) + ", " + std::to_string(c.height) + "]\n";
  out += "  rostopic: /" + c.name + "/image_raw\n";
  out += "  timeshift_cam_imu: " + number(timeshift_s) + "\n";
  return out;
}

}  // namespace

std::string kalibrCamchainYaml(const dataset::CameraCalibration& cam0,
                               const std::optional<dataset::CameraCalibration>& cam1, double timeshift_s) {
  std::string out = cameraYaml(cam0, timeshift_s);
  if (cam1) out += cameraYaml(*cam1, timeshift_s);
  return out;
}

std::string kalibrImuYaml(const dataset::ImuCalibration& imu, bool nested_imu) {
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

Status writeKalibrFilesOf(const std::filesystem::path& euroc_sequence, const std::filesystem::path& camchain,
                          const std::filesystem::path& imu_yaml) {
  const std::filesystem::path mav0 = euroc_sequence / "mav0";
  auto cam0 = dataset::readCameraCalibration(mav0 / "cam0" / "sensor.yaml", "cam0");
  if (!cam0) return cam0.error();
  auto cam1 = dataset::readCameraCalibration(mav0 / "cam1" / "sensor.yaml", "cam1");
  if (!cam1) return cam1.error();
  auto imu = dataset::readImuCalibration(mav0 / "imu0" / "sensor.yaml");
  if (!imu) return imu.error();
  for (const auto& [path, text] :
       {std::pair{camchain, kalibrCamchainYaml(*cam0, *cam1)}, std::pair{imu_yaml, kalibrImuYaml(*imu)}}) {
    std::filesystem::create_directories(path.parent_path());
    std::ofstream out(path);
    out << text;
    if (!out) return Error{ErrorCode::kIoError, "cannot write " + path.string()};
  }
  return Status::Ok();
}

}  // namespace cvislam::test
