// Reading the calibrations Kalibr writes: the camera chain (camchain-imucam.yaml: cam0, cam1, ... with their
// intrinsics, distortion, resolution, T_cam_imu and timeshift_cam_imu) and the IMU file (imu.yaml: noise
// densities, random walks and update_rate, under imu0 or at the top level).
//
// Frames: Kalibr's body is the IMU. T_cam_imu maps IMU coordinates into the camera, so the camera-to-body
// transform EuRoC calls T_BS is its inverse; the IMU-to-body transform is the identity.
// Time: Kalibr's timeshift_cam_imu is the shift with t_imu = t_cam + timeshift_cam_imu.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::dataset {

struct KalibrCamera {
  CameraCalibration calibration;  // name "cam0", "cam1", ...; rate_hz is not in the file (the default stays)
  std::int64_t timeshift_cam_imu_ns = 0;
  std::string rostopic;  // empty when the file names none
};

// Every camera of the chain, cam0 first. Errors name the file, the camera, the key and the line.
Result<std::vector<KalibrCamera>> readKalibrCamchain(const std::filesystem::path& yaml);

struct KalibrImu {
  ImuCalibration calibration;
  std::string rostopic;
};

Result<KalibrImu> readKalibrImu(const std::filesystem::path& yaml);

// Writing them, for a rig known from elsewhere (a EuRoC sequence's sensor.yaml files) that is to run where only
// Kalibr's files are read (a live stream). `T_b_i` is the IMU in the body frame (EuRoC: the identity), so that each
// camera's T_cam_imu is relative to the IMU as Kalibr's is. Numbers are written with all their digits.
std::string kalibrCamchainYaml(const CameraCalibration& cam0, const std::optional<CameraCalibration>& cam1,
                               std::int64_t timeshift_cam_imu_ns = 0, const geometry::SE3d& T_b_i = {});
std::string kalibrImuYaml(const ImuCalibration& imu, bool nested_imu = true);

}  // namespace cvislam::dataset
