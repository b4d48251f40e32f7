#include "agent_rt/runtime/sensor_setup.hpp"

#include <algorithm>

namespace cvislam::agent {

Result<SensorSetup> makeSensorSetup(const SensorRig& rig, bool stereo, double noise_inflation) {
  if (stereo && !rig.cam1) {
    return Error{ErrorCode::kInvalidArgument,
                 "stereo needs a second camera (cam1), which the recording does not have: "
                 "use mono"};
  }
  const dataset::CameraCalibration& c0 = rig.cam0;
  auto left = camera::CameraModel::create(c0);
  if (!left) return left.error().withContext("cam0 calibration");
  SensorSetup setup{*left, std::nullopt, geometry::SE3d(), geometry::SE3d(), imu::ImuNoise{}};
  if (stereo) {
    auto right = camera::CameraModel::create(*rig.cam1);
    if (!right) return right.error().withContext("cam1 calibration");
    setup.right.emplace(*right);
    setup.T_c0_c1 = c0.T_b_c.inverse() * rig.cam1->T_b_c;
  }
  const dataset::ImuCalibration imu = rig.imu.value_or(dataset::ImuCalibration{});
  setup.T_s_c = imu.T_b_i.inverse() * c0.T_b_c;
  setup.noise = imu::ImuNoise::fromCalibration(imu);
  setup.noise.gyro_noise_density *= noise_inflation;
  setup.noise.accel_noise_density *= noise_inflation;
  setup.noise.gyro_random_walk *= noise_inflation;
  setup.noise.accel_random_walk *= noise_inflation;
  return setup;
}

Result<SensorSetup> makeSensorSetup(const dataset::EurocSequence& sequence, bool stereo, double noise_inflation) {
  return makeSensorSetup(sensorRigOf(sequence), stereo, noise_inflation);
}

void applySensorSetup(const SensorSetup& setup, TrackerOptions& tracking, MapperOptions& mapping) {
  const dataset::CameraCalibration& c = setup.left.calibration();
  tracking.noise = setup.noise;
  mapping.ba.noise = setup.noise;
  mapping.ba.intrinsics = {c.fx, c.fy, c.cx, c.cy};
  mapping.ba.pyramid_scale_factor = static_cast<double>(tracking.orb.scale_factor);
  mapping.orb = tracking.orb;
  if (setup.right) mapping.imu_init_keyframes = std::min(mapping.imu_init_keyframes, 10);
}

std::vector<dataset::RigFrame> framesToRun(std::span<const dataset::RigFrame> frames, bool stereo) {
  std::vector<dataset::RigFrame> out;
  for (const dataset::RigFrame& f : frames) {
    if (!stereo || f.cam1) out.push_back(f);
  }
  return out;
}

std::vector<dataset::RigFrame> framesToRun(const dataset::EurocSequence& sequence, bool stereo) {
  return framesToRun(sequence.rigFrames(), stereo);
}

std::span<const dataset::ImuSample> imuCovering(std::span<const dataset::ImuSample> imu, std::int64_t t0_ns,
                                                std::int64_t t1_ns) {
  auto first = std::upper_bound(imu.begin(), imu.end(), t0_ns,
                                [](std::int64_t t, const dataset::ImuSample& s) { return t < s.t_ns; });
  if (first != imu.begin()) --first;
  auto last = std::lower_bound(imu.begin(), imu.end(), t1_ns,
                               [](const dataset::ImuSample& s, std::int64_t t) { return s.t_ns < t; });
  if (last != imu.end()) ++last;
  if (!(first < last)) return {};
  return {&*first, static_cast<std::size_t>(last - first)};
}

LinkSensors linkSensors(const SensorRig& rig, const SensorSetup& setup, bool stereo, bool uses_imu) {
  LinkSensors sensors;
  sensors.stereo = stereo;
  sensors.uses_imu = uses_imu;
  sensors.cam0 = rig.cam0;
  sensors.T_s_c0 = setup.T_s_c;
  if (stereo && rig.cam1) {
    sensors.cam1 = *rig.cam1;
    sensors.T_s_c1 = setup.T_s_c * setup.T_c0_c1;
  }
  sensors.imu_noise = setup.noise;
  if (rig.imu) sensors.imu_rate_hz = rig.imu->rate_hz;
  return sensors;
}

LinkSensors linkSensors(const dataset::EurocSequence& sequence, const SensorSetup& setup, bool stereo, bool uses_imu) {
  return linkSensors(sensorRigOf(sequence), setup, stereo, uses_imu);
}

}  // namespace cvislam::agent
