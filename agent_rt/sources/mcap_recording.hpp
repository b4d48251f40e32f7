// A ROS 2 bag in MCAP (rosbag2's default storage) as a recording: sensor_msgs/msg/Image (mono8, or rgb8/bgr8
// turned grey) on the cam0 and cam1 topics and sensor_msgs/msg/Imu on the IMU topic, CDR-encoded. The bag
// carries no calibration: Kalibr's files give it (RecordingOptions::calibration and imu_calibration).
//
// Opening scans the file once: it keeps every IMU sample and, per image, only its time and its place among the
// file's images; the loading thread then reads the file forward a second time and decodes the images it is asked
// for. Messages are ordered by their header stamps; a message whose stamp is zero takes its log time instead,
// and that is reported once.
#pragma once

#include <memory>

#include "agent_rt/sources/recording.hpp"

namespace cvislam::agent {

Result<std::unique_ptr<Recording>> openMcapRecording(const RecordingOptions& options);

}  // namespace cvislam::agent
