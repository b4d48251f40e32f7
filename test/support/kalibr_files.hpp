// Kalibr calibration files made from the project's own calibrations, for tests: a camera chain (cam0, and cam1
// when given) and an IMU file, as Kalibr writes them.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include "common/dataset/types.hpp"

namespace cvislam::test {

// `timeshift_s` goes into every camera; `nested_imu` puts the IMU's keys under imu0 (newer Kalibr) rather than
// at the top level (older Kalibr).
std::string kalibrCamchainYaml(const dataset::CameraCalibration& cam0,
                               const std::optional<dataset::CameraCalibration>& cam1, double timeshift_s = 0.0);
std::string kalibrImuYaml(const dataset::ImuCalibration& imu, bool nested_imu = true);

}  // namespace cvislam::test
