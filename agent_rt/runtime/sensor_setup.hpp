// What the agent takes from a EuRoC-format sequence before it runs: the camera models, the extrinsics, the
// IMU noise, the options that follow from them, the frames to run and, per frame, the IMU samples that
// cover it. Shared by the agent process and by the tests and benchmarks that run tracking and mapping
// inline, so that all of them see the sequence the same way.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "agent_rt/link/link.hpp"
#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/sources/recording.hpp"
#include "agent_rt/tracking/tracker.hpp"
#include "common/camera/camera_model.hpp"
#include "common/core/result.hpp"
#include "common/dataset/euroc.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

struct SensorSetup {
  camera::CameraModel left;
  std::optional<camera::CameraModel> right;  // stereo only
  geometry::SE3d T_s_c;                      // cam0 -> IMU
  geometry::SE3d T_c0_c1;                    // cam1 -> cam0 (stereo only)
  imu::ImuNoise noise;                       // sensor.yaml's densities x the inflation
};

// Fails, naming the problem, when stereo is asked of a rig without cam1 or a calibration is invalid.
// Without an IMU calibration the noise is the default model.
Result<SensorSetup> makeSensorSetup(const SensorRig& rig, bool stereo, double noise_inflation);
Result<SensorSetup> makeSensorSetup(const dataset::EurocSequence& sequence, bool stereo, double noise_inflation);

// Fills what the options take from the sensors: IMU noise, intrinsics, the ORB pyramid shared by tracking and
// mapping, and (stereo) IMU initialisation after at most 10 keyframes, since the map is metric already.
void applySensorSetup(const SensorSetup& setup, TrackerOptions& tracking, MapperOptions& mapping);

// What the link's Hello tells the server about the sensors: calibrations, extrinsics and the IMU noise as the
// agent uses it.
LinkSensors linkSensors(const SensorRig& rig, const SensorSetup& setup, bool stereo, bool uses_imu);
LinkSensors linkSensors(const dataset::EurocSequence& sequence, const SensorSetup& setup, bool stereo, bool uses_imu);

// The frames to run, in time order: stereo pairs, or every cam0 frame.
std::vector<dataset::RigFrame> framesToRun(std::span<const dataset::RigFrame> frames, bool stereo);
std::vector<dataset::RigFrame> framesToRun(const dataset::EurocSequence& sequence, bool stereo);

// The samples covering [t0_ns, t1_ns]: from the last one at or before t0 to the first one at or after t1
// (fewer at the ends of the recording). Empty when there are none.
std::span<const dataset::ImuSample> imuCovering(std::span<const dataset::ImuSample> imu, std::int64_t t0_ns,
                                                std::int64_t t1_ns);

}  // namespace cvislam::agent
