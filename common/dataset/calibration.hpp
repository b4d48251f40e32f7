// Reading and writing ASL sensor.yaml files (EuRoC's camX/sensor.yaml and imu0/sensor.yaml).
#pragma once

#include <filesystem>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::dataset {

// Reads and validates a camera sensor.yaml. Errors name the file, the key and, where known, the line.
Result<CameraCalibration> readCameraCalibration(const std::filesystem::path& sensor_yaml, const std::string& name);
Result<ImuCalibration> readImuCalibration(const std::filesystem::path& sensor_yaml);

Status writeCameraCalibration(const std::filesystem::path& sensor_yaml, const CameraCalibration& camera);
Status writeImuCalibration(const std::filesystem::path& sensor_yaml, const ImuCalibration& imu);

// Checks ranges (positive focal lengths, principal point inside the image, ...). Names the bad field.
Status validate(const CameraCalibration& camera);
Status validate(const ImuCalibration& imu);

}  // namespace cvislam::dataset
