// Frames from a driver's live topics (agent_rt/live/sensor_topics.hpp) for tracking, read in place from shared
// memory. IMU samples are gathered as they come; a frame is handed over once an IMU sample at or after its time
// has arrived (or after `imu_wait_s`, counted), with the samples that cover it. Frames queue two deep: when
// tracking falls behind, the oldest frame goes, and the gap in the driver's sequence numbers counts it. A camera that
// stops is waited for, and said so; a driver that starts again is followed; its end-of-stream message ends the feed.
//
// The feed runs on the tracking thread and allocates nothing after open. iceoryx headers stay in the .cpp.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "agent_rt/runtime/frame_feed.hpp"
#include "common/core/result.hpp"

namespace cvislam::agent {

struct LiveFeedOptions {
  std::string stream;  // the topics' NAME
  int width = 0;       // cam0's calibrated resolution: frames of another size are refused
  int height = 0;
  bool stereo = false;
  bool use_imu = true;
  std::int64_t timeshift_cam_imu_ns = 0;  // t_imu = t_cam + shift
  double imu_wait_s = 0.02;               // how long a frame waits for the IMU sample that closes its interval
  std::size_t imu_buffer_samples = 4096;  // IMU kept between frames (4 s at 1 kHz)
  double stall_after_s = 1.0;             // no frame for this long: the camera has stopped (said and counted)
  bool quiet = false;
  const std::atomic<bool>* stop = nullptr;  // a waiting next() returns nullptr once it is set

  [[nodiscard]] Status validate() const;
};

// Subscribes to the stream's topics; this process must be attached to RouDi.
Result<std::unique_ptr<FrameFeed>> openLiveFeed(const LiveFeedOptions& options);

}  // namespace cvislam::agent
