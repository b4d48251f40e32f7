// Frames of a recording (a EuRoC folder, a ROS 2 bag) for tracking: a loader thread decodes the images ahead into a
// ring of preallocated slots, and each frame is handed over with the recording's IMU samples that cover it. At
// realtime pace a frame is handed over no earlier than its sensor time says (times `rate`), as a camera would.
#pragma once

#include <functional>
#include <thread>
#include <vector>

#include "agent_rt/runtime/frame_feed.hpp"
#include "agent_rt/runtime/frame_ring.hpp"
#include "agent_rt/sources/recording.hpp"

namespace cvislam::agent {

struct RecordingFeedOptions {
  bool stereo = false;
  bool use_imu = true;
  bool realtime = false;  // hand frames over at sensor pace
  double rate = 1.0;      // realtime: 2 plays twice as fast
  int ring_size = 4;      // frames decoded ahead
};

class RecordingFeed final : public FrameFeed {
 public:
  // Starts the loader thread, which first calls `on_loader_start` (its scheduling). `recording` and `frames` must
  // outlive the feed.
  RecordingFeed(Recording& recording, const std::vector<dataset::RigFrame>& frames, const RecordingFeedOptions& options,
                const std::function<void()>& on_loader_start);
  ~RecordingFeed() override;

  const FeedFrame* next() override;
  void release() override;
  void close() override;
  [[nodiscard]] std::size_t knownFrames() const override { return frames_.size(); }

 private:
  void load();

  Recording& recording_;
  const std::vector<dataset::RigFrame>& frames_;
  RecordingFeedOptions options_;
  FrameRing ring_;
  FeedFrame current_;
  std::int64_t previous_good_t_ns_ = -1;
  std::int64_t first_due_steady_ns_ = -1;
  std::thread loader_;
};

}  // namespace cvislam::agent
