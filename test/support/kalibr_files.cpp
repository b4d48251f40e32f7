#include "test/support/kalibr_files.hpp"

#include <cmath>
#include <fstream>

#include "common/dataset/calibration.hpp"
#include "common/dataset/kalibr.hpp"

namespace cvislam::test {

std::string kalibrCamchainYaml(const dataset::CameraCalibration& cam0,
                               const std::optional<dataset::CameraCalibration>& cam1, double timeshift_s) {
  return dataset::kalibrCamchainYaml(cam0, cam1, static_cast<std::int64_t>(std::llround(timeshift_s * 1e9)));
}

std::string kalibrImuYaml(const dataset::ImuCalibration& imu, bool nested_imu) {
  return dataset::kalibrImuYaml(imu, nested_imu);
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
  for (const auto& [path, text] : {std::pair{camchain, dataset::kalibrCamchainYaml(*cam0, *cam1)},
                                   std::pair{imu_yaml, dataset::kalibrImuYaml(*imu)}}) {
    std::filesystem::create_directories(path.parent_path());
    std::ofstream out(path);
    out << text;
    if (!out) return Error{ErrorCode::kIoError, "cannot write " + path.string()};
  }
  return Status::Ok();
}

}  // namespace cvislam::test
