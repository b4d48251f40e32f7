#include "agent_rt/sources/recording.hpp"

#include "agent_rt/sources/euroc_recording.hpp"
#include "agent_rt/sources/mcap_recording.hpp"

namespace cvislam::agent {

Status RecordingOptions::validate() const {
  if (dataset.empty() == mcap.empty()) {
    return Error{ErrorCode::kInvalidArgument,
                 "give one recording: a folder that holds mav0 (EuRoC/ASL layout) or a ROS 2 bag in MCAP"};
  }
  if (!mcap.empty() && calibration.empty()) {
    return Error{ErrorCode::kInvalidArgument,
                 "a ROS 2 bag carries no calibration: give Kalibr's camera chain (camchain-imucam.yaml)"};
  }
  if (!mcap.empty() && require_imu && imu_calibration.empty()) {
    return Error{ErrorCode::kInvalidArgument,
                 "a ROS 2 bag carries no IMU calibration: give Kalibr's IMU file (imu.yaml), or run without the IMU"};
  }
  if (!mcap.empty() && (topics.cam0.empty() || topics.imu.empty())) {
    return Error{ErrorCode::kInvalidArgument, "the cam0 and IMU topics must be named"};
  }
  return Status::Ok();
}

Result<std::unique_ptr<Recording>> openRecording(const RecordingOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  if (!options.mcap.empty()) return openMcapRecording(options);
  return openEurocRecording(options);
}

SensorRig sensorRigOf(const dataset::EurocSequence& sequence) {
  SensorRig rig;
  rig.cam0 = sequence.cam0().calibration;
  if (sequence.cam1() != nullptr) rig.cam1 = sequence.cam1()->calibration;
  rig.imu = sequence.imuCalibration();
  return rig;
}

}  // namespace cvislam::agent
