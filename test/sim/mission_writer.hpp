// Writes a planned mission: one EuRoC/ASL dataset folder per agent (DIR/agent0, DIR/agent1, ...) with cam0
// (and optionally cam1) images, imu0 and state_groundtruth_estimate0, plus DIR/mission.yaml describing it.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "test/sim/imu_simulator.hpp"
#include "test/sim/presets.hpp"
#include "test/sim/texture.hpp"

namespace cvislam::sim {

struct MissionWriterOptions {
  std::filesystem::path out_dir;
  std::uint64_t seed = 0;
  dataset::CameraCalibration cam0;  // defaults to EuRoC cam0 when created through defaultWriterOptions()
  dataset::CameraCalibration cam1;
  bool stereo = false;  // also render cam1
  dataset::ImuCalibration imu;
  ImuSimulatorOptions imu_options;
  double pixel_noise_sigma = 0.0;   // grey levels; 0 = none
  double exposure_amplitude = 0.0;  // relative gain change, e.g. 0.2 = +-20 %, smooth over ~15 s; 0 = none
  // The cameras' clock against the IMU's, as an unsynchronised robot has it: an image taken at IMU time t is
  // stamped t - shift, so t_imu = t_cam + shift (Kalibr's timeshift_cam_imu). Ground truth stays on the IMU's clock.
  std::int64_t camera_time_shift_ns = 0;
  bool overwrite = false;
  std::int64_t start_time_ns = 1'600'000'000'000'000'000;  // shared mission clock
  TextureOptions texture;
  // Agents rendered at once, each on its own thread (the output does not depend on it).
  int threads = 1;
  // Called after each rendered frame: agent index, frames done, frames total (one call at a time).
  std::function<void(std::size_t, std::size_t, std::size_t)> progress;

  [[nodiscard]] Status validate() const;
};

MissionWriterOptions defaultWriterOptions();

// Writes every agent of the plan; fails (naming the file) at the first write error.
Status writeMission(const MissionPlan& plan, const MissionWriterOptions& options);

// Plans and writes a preset in one call, with the default writer (EuRoC cameras and IMU, no pixel noise); the
// simulator's seed is used for both. For tests that need a short mission on disk.
Status renderPreset(const std::string& preset, std::uint64_t seed, double duration_s, bool stereo,
                    const std::filesystem::path& out_dir, int threads = 1);

}  // namespace cvislam::sim
