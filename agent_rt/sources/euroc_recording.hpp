// A EuRoC/ASL folder as a recording: mav0/cam0, cam1 (optional) and imu0, their sensor.yaml files and CSV
// lists, images decoded from PNG by the agent's own decoder (no OpenCV).
#pragma once

#include <memory>

#include "agent_rt/sources/recording.hpp"

namespace cvislam::agent {

// `options.dataset` is the folder; the Kalibr files of `options`, when given, replace the sensor.yaml ones.
Result<std::unique_ptr<Recording>> openEurocRecording(const RecordingOptions& options);

}  // namespace cvislam::agent
