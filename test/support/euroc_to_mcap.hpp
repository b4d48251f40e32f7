// A EuRoC/ASL folder written as a ROS 2 bag in MCAP, as a robot's recorder would: cam0 and cam1 as
// sensor_msgs/msg/Image (mono8) on /cam0/image_raw and /cam1/image_raw, imu0 as sensor_msgs/msg/Imu on /imu0,
// header stamps from the folder's times, in time order. For tests of the agent's MCAP source.
#pragma once

#include <filesystem>
#include <string>

#include "common/core/result.hpp"
#include "common/mcap/records.hpp"

namespace cvislam::test {

struct EurocToMcapOptions {
  mcap::Compression compression = mcap::Compression::kZstd;
  bool use_chunks = true;
  std::string image_encoding = "mono8";  // or "rgb8" / "bgr8": grey repeated in three channels
  bool zero_header_stamps = false;       // stamps left at 0, log times carry the time
};

Status writeEurocAsMcap(const std::filesystem::path& euroc_folder, const std::filesystem::path& mcap_file,
                        const EurocToMcapOptions& options = {});

}  // namespace cvislam::test
