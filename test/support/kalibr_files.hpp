// Kalibr calibration files made from the project's own calibrations, for tests (common/dataset/kalibr.hpp writes
// them): a camera chain (cam0, and cam1 when given) and an IMU file, as Kalibr writes them.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::test {

// `timeshift_s` goes into every camera; `nested_imu` puts the IMU's keys under imu0 (newer Kalibr) rather than
// at the top level (older Kalibr).
std::string kalibrCamchainYaml(const dataset::CameraCalibration& cam0,
                               const std::optional<dataset::CameraCalibration>& cam1, double timeshift_s = 0.0);
std::string kalibrImuYaml(const dataset::ImuCalibration& imu, bool nested_imu = true);

// Kalibr files equal to a EuRoC sequence's cam0, cam1 and imu0 sensor.yaml, written to `camchain` and `imu_yaml`
// (folders created).
Status writeKalibrFilesOf(const std::filesystem::path& euroc_sequence, const std::filesystem::path& camchain,
                          const std::filesystem::path& imu_yaml);

}  // namespace cvislam::test
