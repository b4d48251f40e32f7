// A small, deterministic ROS 2 bag for the MCAP tests, the interop check against the npm implementation and the
// fuzz seeds: /imu0 (sensor_msgs/msg/Imu) at 200 Hz, /cam0/image_raw (sensor_msgs/msg/Image, mono8) at 20 Hz, and
// /notes (JSON, no schema), with one attachment and one metadata record.
#pragma once

#include <cstdint>
#include <string>

#include "common/core/result.hpp"
#include "common/mcap/reader.hpp"
#include "common/mcap/writer.hpp"

namespace cvislam::mcap::test {

struct SampleOptions {
  int imu_messages = 40;
  int imu_per_image = 10;  // 200 Hz IMU, 20 Hz camera
  std::uint32_t width = 32;
  std::uint32_t height = 24;
  std::uint64_t start_ns = 1403715273262142976ULL;  // EuRoC V1_01's first camera stamp
  bool attachment_and_metadata = true;
};

Status writeSample(Writer& writer, const SampleOptions& options = {});
// The same written with `writer_options` into memory.
Result<std::vector<std::uint8_t>> sampleBytes(const WriterOptions& writer_options, const SampleOptions& options = {});

// One line per message, "topic sequence log_time publish_time bytes crc32", in file order: what two readers of one
// file must agree on (the interop check's node script prints the same form).
std::string messageLine(const MessageView& message);
// Every message's line; an error if the scan fails.
Result<std::string> listMessages(Reader& reader);

}  // namespace cvislam::mcap::test
