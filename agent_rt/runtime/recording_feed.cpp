#include "agent_rt/runtime/recording_feed.hpp"

#include <chrono>

#include "agent_rt/messages/messages.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "common/core/steady_clock.hpp"
#include "common/trace/trace.hpp"

namespace cvislam::agent {
RecordingFeed::RecordingFeed(Recording& recording, const std::vector<dataset::RigFrame>& frames,
                             const RecordingFeedOptions& options, const std::function<void()>& on_loader_start)
    : recording_(recording),
      frames_(frames),
      options_(options),
      ring_(
          options.ring_size,
          static_cast<std::size_t>(recording.rig().cam0.width) * static_cast<std::size_t>(recording.rig().cam0.height),
          options.stereo) {
  loader_ = std::thread([this, on_loader_start] {
    if (on_loader_start) on_loader_start();
    load();
  });
}

RecordingFeed::~RecordingFeed() {
  close();
  if (loader_.joinable()) loader_.join();
}

// The loader thread's work: every frame's images into the ring, until the end or until tracking closes it.
void RecordingFeed::load() {
  for (std::size_t i = 0; i < frames_.size(); ++i) {
    FrameRing::Slot* slot = ring_.waitForFreeSlot();
    if (slot == nullptr) return;  // tracking stopped
    const trace::Span span("load_frame", {{"frame", static_cast<std::int64_t>(i)}});
    slot->t_ns = frames_[i].t_ns;
    slot->frame = i;
    slot->ok = true;
    slot->error.clear();
    Status st = recording_.loadImageInto(0, frames_[i].cam0, slot->left);
    if (st.ok() && options_.stereo) st = recording_.loadImageInto(1, *frames_[i].cam1, slot->right);
    if (!st.ok()) {
      slot->ok = false;
      slot->error = st.error().toString();
    }
    ring_.produced();
  }
  ring_.finish();
}

const FeedFrame* RecordingFeed::next() {
  const FrameRing::Slot* slot = ring_.waitForFrame();
  if (slot == nullptr) return nullptr;
  std::int64_t now_ns = steadyNowNs();
  if (options_.realtime) {
    if (first_due_steady_ns_ < 0) first_due_steady_ns_ = now_ns;
    const double since_first_ns = static_cast<double>(slot->t_ns - frames_.front().t_ns) / options_.rate;
    const std::int64_t due_ns = first_due_steady_ns_ + static_cast<std::int64_t>(since_first_ns);
    if (due_ns > now_ns) {
      std::this_thread::sleep_for(std::chrono::nanoseconds(due_ns - now_ns));
    }
    now_ns = due_ns;
  }
  current_ = FeedFrame{};
  current_.t_ns = slot->t_ns + time_correction_ns_;
  current_.time_correction_ns = time_correction_ns_;
  current_.index = slot->frame;
  current_.captured_steady_ns = now_ns;
  current_.ok = slot->ok;
  current_.error = slot->ok ? nullptr : slot->error.c_str();
  if (slot->ok) {
    current_.left = slot->left;
    if (options_.stereo) current_.right = slot->right;
    if (options_.use_imu) {
      current_.imu = imuCovering(recording_.imu(),
                                 previous_good_t_ns_ < 0 ? current_.t_ns - kImuKeptBeforeStampNs : previous_good_t_ns_,
                                 current_.t_ns);
    }
  }
  return &current_;
}

void RecordingFeed::release() {
  if (current_.ok) previous_good_t_ns_ = current_.t_ns;
  ring_.consumed();
}

void RecordingFeed::close() {
  ring_.close();
}

}  // namespace cvislam::agent
