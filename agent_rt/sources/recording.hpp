// Where a recorded run's sensor data comes from: the one seam between the agent's runtime and its inputs.
// A recording has its rig (calibrations), its IMU samples and its camera frames in time order, and decodes one
// frame's image into caller-owned storage at a time. Implementations: a EuRoC/ASL folder (euroc_recording.hpp) and
// a ROS 2 bag in MCAP (mcap_recording.hpp).
//
// Calibrations come from the recording itself (EuRoC's sensor.yaml files) or, overriding them, from Kalibr's
// camera chain and IMU files. A camera's timeshift_cam_imu moves its frames onto the IMU's clock
// (t_imu = t_cam + shift) before anything else sees them.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include "common/core/diagnostics.hpp"
#include "common/core/result.hpp"
#include "common/dataset/euroc.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::agent {

// The sensors as the agent needs them: cam0, cam1 when there is one, and the IMU when it is calibrated.
struct SensorRig {
  dataset::CameraCalibration cam0;
  std::optional<dataset::CameraCalibration> cam1;
  std::optional<dataset::ImuCalibration> imu;
  // t_imu = t_cam + shift (Kalibr's timeshift_cam_imu). A recording's frames are already moved by it.
  std::int64_t timeshift_cam_imu_ns = 0;
};

class Recording {
 public:
  virtual ~Recording() = default;
  Recording() = default;
  Recording(const Recording&) = delete;
  Recording& operator=(const Recording&) = delete;

  [[nodiscard]] virtual const SensorRig& rig() const = 0;
  // On the IMU's clock, time-ordered.
  [[nodiscard]] virtual std::span<const dataset::ImuSample> imu() const = 0;
  // cam0 frames in time order (on the IMU's clock), each with its cam1 partner when there is one.
  [[nodiscard]] virtual std::span<const dataset::RigFrame> rigFrames() const = 0;
  // What was found wrong but survivable when it was opened.
  [[nodiscard]] virtual const Diagnostics& diagnostics() const = 0;
  // What it is, for messages: "EuRoC folder /data/V1_01".
  [[nodiscard]] virtual std::string describe() const = 0;
  // A recording the project's simulator made (its IMU noise is exactly what its calibration says).
  [[nodiscard]] virtual bool simulated() const = 0;
  // Decodes frame `frame` of camera `camera` (0 or 1; the index in its camera's stream, as RigFrame holds it)
  // into `pixels` (width x height of that camera). One thread at a time.
  [[nodiscard]] virtual Status loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels) = 0;
};

// The topics of a ROS 2 bag the agent reads (Kalibr's EuRoC bags name them so).
struct McapTopics {
  std::string cam0 = "/cam0/image_raw";
  std::string cam1 = "/cam1/image_raw";
  std::string imu = "/imu0";
};

struct RecordingOptions {
  std::filesystem::path dataset;  // a folder that holds mav0 (EuRoC/ASL), or
  std::filesystem::path mcap;     // a ROS 2 bag in MCAP (its calibration from the Kalibr files below)
  McapTopics topics;
  std::filesystem::path calibration;      // Kalibr camchain-imucam.yaml: replaces the cameras' sensor.yaml
  std::filesystem::path imu_calibration;  // Kalibr imu.yaml: replaces imu0/sensor.yaml
  bool require_imu = true;                // a recording without IMU samples is an error

  [[nodiscard]] Status validate() const;
};

Result<std::unique_ptr<Recording>> openRecording(const RecordingOptions& options);

// The rig of a EuRoC sequence as its sensor.yaml files describe it.
SensorRig sensorRigOf(const dataset::EurocSequence& sequence);

}  // namespace cvislam::agent
