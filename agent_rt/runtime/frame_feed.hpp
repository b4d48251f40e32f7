// Where tracking's frames come from while the agent runs: a recording replayed by a loader thread
// (recording_feed.hpp), a driver's live topics (live_feed.hpp), or frames a program pushes through the embedding API
// (push_feed.hpp). Each frame arrives with its images and the IMU
// samples that cover the time since the previous one, so tracking never looks further than the frame in hand.
// One consumer, the tracking thread; next() and release() alternate.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "common/dataset/types.hpp"

namespace cvislam::agent {

struct FeedFrame {
  std::int64_t t_ns = 0;  // on the IMU's clock: the camera's stamp + the calibrated offset + time_correction_ns
  std::int64_t time_correction_ns = 0;  // the estimated correction to the calibrated offset (setTimeCorrection)
  std::uint64_t index = 0;              // position in the stream, from 0
  std::span<const std::uint8_t> left;
  std::span<const std::uint8_t> right;  // empty in mono
  // From the last sample at or before the previous good frame to the first at or after this one; empty without IMU.
  std::span<const dataset::ImuSample> imu;
  // CLOCK_MONOTONIC when the frame was taken (live: by the driver; a recording at realtime pace: when it was due;
  // otherwise when it was ready): the start of the frame-to-state latency.
  std::int64_t captured_steady_ns = 0;
  bool ok = true;                 // false: the images could not be had; `error` says why
  bool stream_restarted = false;  // the first frame of a driver that started again: nothing links it to the last
  const char* error = nullptr;
};

// What a live stream did wrong, counted (all zero for a recording).
struct FeedFaults {
  std::uint64_t frames_lost = 0;          // gaps in the driver's frame sequence: dropped by a full queue or never sent
  std::uint64_t frames_out_of_order = 0;  // not later than the frame before (late or repeated): dropped
  std::uint64_t messages_malformed = 0;   // not of its topic's layout (a frame or an IMU sample): dropped
  std::uint64_t imu_lost = 0;             // gaps in the IMU sequence
  std::uint64_t imu_out_of_order = 0;     // not later than the sample before: dropped
  std::uint64_t imu_overflow = 0;         // samples dropped because no frame came to use them
  std::uint64_t imu_wait_timeouts = 0;    // frames handed over before the IMU covered them
  std::uint64_t stalls = 0;               // times frames stopped for longer than the feed's stall time
  std::uint64_t driver_restarts = 0;      // times its frame sequence began again from 0

  [[nodiscard]] bool any() const {
    return frames_lost + frames_out_of_order + messages_malformed + imu_lost + imu_out_of_order + imu_overflow +
               imu_wait_timeouts + stalls + driver_restarts >
           0;
  }
};

class FrameFeed {
 public:
  virtual ~FrameFeed() = default;
  FrameFeed() = default;
  FrameFeed(const FrameFeed&) = delete;
  FrameFeed& operator=(const FrameFeed&) = delete;

  // Waits for the next frame; nullptr at the end of the stream, or once close() was called.
  virtual const FeedFrame* next() = 0;
  // Tracking is done with the frame next() returned (its memory may be reused).
  virtual void release() = 0;
  // No more frames are wanted: producers stop, a waiting next() returns nullptr.
  virtual void close() = 0;
  // The frames the stream holds when known in advance (a recording); 0 for a live stream.
  [[nodiscard]] virtual std::size_t knownFrames() const = 0;
  [[nodiscard]] virtual FeedFaults faults() const { return {}; }

  // A correction to the calibrated camera-IMU time offset, added to the times of the frames next() hands over from
  // now on, and to the end of the IMU interval they get (tracking's estimate; see Tracker).
  void setTimeCorrection(std::int64_t correction_ns) { time_correction_ns_ = correction_ns; }

 protected:
  std::int64_t time_correction_ns_ = 0;
};

}  // namespace cvislam::agent
