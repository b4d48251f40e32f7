// Kalibr's calibration files applied to a recording's rig, whatever the recording.
#pragma once

#include <cstdint>

#include "agent_rt/sources/recording.hpp"

namespace cvislam::agent {

// Replaces the rig's cameras with `options.calibration`'s chain (cam0; cam1 when the rig has one: a rig with
// cam1 and a chain without it loses cam1) and its IMU with `options.imu_calibration`'s. Kalibr's body is the IMU,
// so with a camera chain the IMU-to-body transform becomes the identity. Each camera's resolution must be the
// recording's. Returns the shift that moves camera times onto the IMU's clock (cam0's timeshift_cam_imu; 0
// without a chain).
Result<std::int64_t> applyKalibrFiles(const RecordingOptions& options, SensorRig& rig);

// The rig of a live stream, which has nothing but the calibration files: cam0, cam1 when the chain has it, the IMU
// when `imu_calibration` is given, and cam0's timeshift_cam_imu (cam1's must agree within 1 ms).
Result<SensorRig> rigFromKalibrFiles(const std::filesystem::path& calibration,
                                     const std::filesystem::path& imu_calibration);

}  // namespace cvislam::agent
