// The live sensor topics: what a camera/IMU driver publishes for `cvislam_agent --live NAME`, as plain structs
// (no iceoryx here). Each sensor stream is an iceoryx topic of service "cvislam_sensors", instance NAME:
//
//   event "frames": one chunk per camera exposure: a FrameHeader followed at once by the pixels, cam0's rows then,
//                   for a stereo pair, cam1's (both 8-bit grey, width x height, no padding). A driver loans the chunk
//                   at the size frameChunkBytes() gives, writes the image into it and publishes it: the agent
//                   tracks on that memory without copying it. The last chunk of a stream is a header alone with
//                   kEndOfStream set.
//   event "imu":    one ImuMessage per IMU sample (200-1000 Hz).
//
// Times: t_ns is the sensor's timestamp, cameras on their own clock (the calibration's timeshift_cam_imu moves them
// onto the IMU's), both in nanoseconds. captured_steady_ns is CLOCK_MONOTONIC when the driver got the data; the
// agent measures its latencies from it. sequence counts each stream's messages from 0, so that a receiver sees a
// gap as a loss.
#pragma once

#include <cstddef>
#include <cstdint>

namespace cvislam::agent::live {

inline constexpr const char* kServiceName = "cvislam_sensors";
inline constexpr const char* kFramesEvent = "frames";
inline constexpr const char* kImuEvent = "imu";

// The longest stream name iceoryx takes as an instance.
inline constexpr std::size_t kMaxStreamNameLength = 100;

inline constexpr std::uint32_t kFrameMagic = 0x46535643;  // "CVSF" in little-endian memory
inline constexpr std::uint32_t kImuMagic = 0x49535643;    // "CVSI"
inline constexpr std::uint32_t kTopicVersion = 1;

enum FrameFlags : std::uint32_t {
  kEndOfStream = 1U << 0,  // no image: the driver has nothing more to send
};

struct FrameHeader {
  std::uint32_t magic = kFrameMagic;
  std::uint32_t version = kTopicVersion;
  std::uint64_t sequence = 0;
  std::int64_t t_ns = 0;
  std::int64_t captured_steady_ns = 0;
  std::uint32_t width = 0;
  std::uint32_t height = 0;
  std::uint32_t cameras = 1;  // 1: cam0 only; 2: a stereo pair
  std::uint32_t flags = 0;
};
static_assert(sizeof(FrameHeader) % 8 == 0, "the pixels follow the header at an 8-byte boundary");

struct ImuMessage {
  std::uint32_t magic = kImuMagic;
  std::uint32_t version = kTopicVersion;
  std::uint64_t sequence = 0;
  std::int64_t t_ns = 0;
  std::int64_t captured_steady_ns = 0;
  double gyro_s[3] = {0.0, 0.0, 0.0};   // angular rate in the IMU frame [rad/s]
  double accel_s[3] = {0.0, 0.0, 0.0};  // specific force in the IMU frame [m/s^2]
};

// The bytes of one frame chunk: header and pixels.
constexpr std::size_t frameChunkBytes(std::uint32_t width, std::uint32_t height, std::uint32_t cameras) {
  return sizeof(FrameHeader) + static_cast<std::size_t>(width) * height * cameras;
}

}  // namespace cvislam::agent::live
