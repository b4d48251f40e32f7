#include "agent_rt/runtime/push_feed.hpp"

#include <algorithm>
#include <chrono>
#include <cstring>

#include "agent_rt/messages/messages.hpp"
#include "common/core/steady_clock.hpp"

namespace cvislam::agent {

PushFeed::PushFeed(const PushFeedOptions& options)
    : o_(options),
      ring_(options.ring_size, static_cast<std::size_t>(options.width) * static_cast<std::size_t>(options.height),
            options.stereo),
      imu_queue_(options.imu_queue),
      imu_window_(options.imu_queue) {}

bool PushFeed::pushImu(const dataset::ImuSample& sample) {
  if (!imu_queue_.push(sample)) {
    imu_dropped_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  doorbell_.ring();
  return true;
}

bool PushFeed::pushFrame(std::int64_t t_ns, const std::uint8_t* left, const std::uint8_t* right) {
  FrameRing::Slot* slot = o_.wait_when_full ? ring_.waitForFreeSlot() : ring_.tryFreeSlot();
  if (slot == nullptr || left == nullptr || (o_.stereo && right == nullptr)) {
    frames_dropped_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  slot->t_ns = t_ns + o_.timeshift_cam_imu_ns;
  slot->frame = pushed_.fetch_add(1, std::memory_order_relaxed);
  slot->ok = true;
  slot->captured_steady_ns = steadyNowNs();
  std::memcpy(slot->left.data(), left, slot->left.size());
  if (o_.stereo) std::memcpy(slot->right.data(), right, slot->right.size());
  ring_.produced();
  doorbell_.ring();
  return true;
}

void PushFeed::finish() {
  ring_.finish();
  doorbell_.ring();
}

void PushFeed::close() {
  ring_.close();
  doorbell_.ring();
}

void PushFeed::drainImu() {
  dataset::ImuSample sample;
  while (imu_queue_.pop(sample)) {
    if (!imu_window_.add(sample)) ++faults_.imu_out_of_order;
  }
}

const FeedFrame* PushFeed::next() {
  std::int64_t imu_deadline_ns = -1;
  while (true) {
    const std::uint32_t seen = doorbell_.seen();
    drainImu();
    if (slot_ == nullptr) {
      slot_ = ring_.tryFrame();
      // Late or repeated frames go; the next one is looked at at once.
      if (slot_ != nullptr && last_frame_t_ns_ >= 0 && slot_->t_ns <= last_frame_t_ns_) {
        ++faults_.frames_out_of_order;
        slot_ = nullptr;
        ring_.consumed();
        continue;
      }
      if (slot_ == nullptr && ring_.drained()) return nullptr;
    }
    if (slot_ != nullptr) {
      if (!o_.use_imu || imu_window_.covers(slot_->t_ns + time_correction_ns_)) break;
      const std::int64_t now_ns = steadyNowNs();
      if (imu_deadline_ns < 0) imu_deadline_ns = now_ns + static_cast<std::int64_t>(o_.imu_wait_s * 1e9);
      if (now_ns >= imu_deadline_ns) {
        ++faults_.imu_wait_timeouts;
        break;
      }
      doorbell_.waitFor(seen, std::chrono::nanoseconds(imu_deadline_ns - now_ns));
    } else {
      doorbell_.waitFor(seen, std::chrono::milliseconds(100));
    }
  }
  last_frame_t_ns_ = slot_->t_ns;
  current_ = FeedFrame{};
  current_.t_ns = slot_->t_ns + time_correction_ns_;
  current_.time_correction_ns = time_correction_ns_;
  current_.index = delivered_++;
  current_.captured_steady_ns = slot_->captured_steady_ns;
  current_.left = slot_->left;
  if (o_.stereo) current_.right = slot_->right;
  if (o_.use_imu) {
    current_.imu = imu_window_.covering(
        previous_good_t_ns_ < 0 ? current_.t_ns - kImuKeptBeforeStampNs : previous_good_t_ns_, current_.t_ns);
  }
  return &current_;
}

void PushFeed::release() {
  if (slot_ == nullptr) return;
  previous_good_t_ns_ = current_.t_ns;
  imu_window_.dropBefore(current_.t_ns);
  slot_ = nullptr;
  ring_.consumed();
}

FeedFaults PushFeed::faults() const {
  FeedFaults f = faults_;
  f.frames_lost = frames_dropped_.load(std::memory_order_relaxed);
  f.imu_lost = imu_dropped_.load(std::memory_order_relaxed);
  f.imu_overflow = imu_window_.overflowed();
  return f;
}

}  // namespace cvislam::agent
