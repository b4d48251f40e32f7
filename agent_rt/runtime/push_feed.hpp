// Frames and IMU samples pushed by the program the agent is embedded in (cvislam/agent.hpp), for tracking: the
// program's camera and IMU threads push, the tracking thread takes. Frames are copied into a ring of preallocated
// slots and IMU samples into a fixed queue, so pushing never allocates and, unless asked to, never waits: a full
// ring or queue drops what is pushed and counts it. A frame is handed over once an IMU sample at or after its time
// has come (or after imu_wait_s), with the samples that cover it, as from a recording.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "agent_rt/runtime/doorbell.hpp"
#include "agent_rt/runtime/frame_feed.hpp"
#include "agent_rt/runtime/frame_ring.hpp"
#include "agent_rt/runtime/imu_window.hpp"
#include "agent_rt/runtime/spsc_queue.hpp"

namespace cvislam::agent {

struct PushFeedOptions {
  int width = 0;  // cam0's calibrated resolution
  int height = 0;
  bool stereo = false;
  bool use_imu = true;
  std::int64_t timeshift_cam_imu_ns = 0;  // t_imu = t_cam + shift
  int ring_size = 4;                      // frames waiting for tracking
  std::size_t imu_queue = 4096;           // samples waiting for tracking
  double imu_wait_s = 0.02;
  bool wait_when_full = false;  // pushFrame waits for room instead of dropping (replaying a recording)
};

class PushFeed final : public FrameFeed {
 public:
  explicit PushFeed(const PushFeedOptions& options);

  // The program's side: frames from one thread, IMU from one thread (the same or another).
  // False when the queue was full and the sample was dropped.
  bool pushImu(const dataset::ImuSample& sample);
  // Copies width x height bytes from `left` (and `right` in stereo); false when dropped (ring full, or after
  // finish()).
  bool pushFrame(std::int64_t t_ns, const std::uint8_t* left, const std::uint8_t* right);
  // No more frames: tracking ends once it has taken those pushed.
  void finish();

  // Tracking's side.
  const FeedFrame* next() override;
  void release() override;
  void close() override;
  [[nodiscard]] std::size_t knownFrames() const override { return 0; }
  [[nodiscard]] FeedFaults faults() const override;

 private:
  void drainImu();

  PushFeedOptions o_;
  FrameRing ring_;
  Doorbell doorbell_;
  SpscQueue<dataset::ImuSample> imu_queue_;
  std::atomic<std::uint64_t> frames_dropped_{0};
  std::atomic<std::uint64_t> imu_dropped_{0};
  std::atomic<std::uint64_t> pushed_{0};
  ImuWindow imu_window_;
  FeedFrame current_;
  FrameRing::Slot* slot_ = nullptr;
  FeedFaults faults_;
  std::int64_t previous_good_t_ns_ = -1;
  std::int64_t last_frame_t_ns_ = -1;
  std::uint64_t delivered_ = 0;
};

}  // namespace cvislam::agent
