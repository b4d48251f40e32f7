#include "agent_rt/runtime/live_feed.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <optional>
#include <vector>

#include "agent_rt/live/live_service.hpp"
#include "agent_rt/messages/messages.hpp"
#include "agent_rt/runtime/imu_window.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/mepoo/chunk_header.hpp"
#include "iceoryx_posh/popo/untyped_subscriber.hpp"
#include "iceoryx_posh/popo/wait_set.hpp"

namespace cvislam::agent {
namespace {

using live::FrameHeader;
using live::ImuMessage;

// How deep the frame queue is: the frame being tracked's successor and one more. A deeper queue would only make
// tracking later, never more complete.
constexpr std::uint64_t kFrameQueue = 2;
constexpr std::uint64_t kImuQueue = iox::MAX_SUBSCRIBER_QUEUE_CAPACITY;
constexpr auto kStopSlice = std::chrono::milliseconds(100);

class LiveFeed final : public FrameFeed {
 public:
  explicit LiveFeed(const LiveFeedOptions& options)
      : o_(options),
        frames_(live::liveService(options.stream, live::kFramesEvent), live::dropOldestQueue(kFrameQueue)),
        imu_(live::liveService(options.stream, live::kImuEvent), live::dropOldestQueue(kImuQueue)),
        imu_window_(options.imu_buffer_samples) {}
  ~LiveFeed() override { releaseHeld(); }

  Status attach() {
    if (wait_.attachEvent(frames_, iox::popo::SubscriberEvent::DATA_RECEIVED).has_error() ||
        wait_.attachState(imu_, iox::popo::SubscriberState::HAS_DATA).has_error()) {
      return Error{ErrorCode::kInternal, "iceoryx refused to wait on the live topics of '" + o_.stream + "'"};
    }
    return Status::Ok();
  }

  const FeedFrame* next() override {
    std::int64_t imu_deadline_ns = -1;
    while (!ended_ && !stopped()) {
      drainImu();
      if (held_ == nullptr && !takeFrame()) {
        if (ended_) break;
        watchStream();
        wait(std::min<std::chrono::nanoseconds>(
            kStopSlice, std::chrono::nanoseconds(static_cast<std::int64_t>(o_.stall_after_s * 1e9))));
        continue;
      }
      if (!o_.use_imu || !current_.ok || imu_window_.covers(current_.t_ns)) return deliver();
      const std::int64_t now_ns = steadyNowNs();
      if (imu_deadline_ns < 0) imu_deadline_ns = now_ns + static_cast<std::int64_t>(o_.imu_wait_s * 1e9);
      if (now_ns >= imu_deadline_ns) {
        ++faults_.imu_wait_timeouts;
        return deliver();
      }
      wait(std::min<std::chrono::nanoseconds>(std::chrono::nanoseconds(imu_deadline_ns - now_ns), kStopSlice));
    }
    return nullptr;
  }

  void release() override {
    if (current_.ok && held_ != nullptr) {
      previous_good_t_ns_ = current_.t_ns;
      imu_window_.dropBefore(current_.t_ns);
    }
    releaseHeld();
  }

  void close() override { closed_.store(true); }
  [[nodiscard]] std::size_t knownFrames() const override { return 0; }
  [[nodiscard]] FeedFaults faults() const override {
    FeedFaults f = faults_;
    f.imu_overflow = imu_window_.overflowed();
    return f;
  }

 private:
  [[nodiscard]] bool stopped() const { return closed_.load() || (o_.stop != nullptr && o_.stop->load()); }

  void wait(std::chrono::nanoseconds timeout) {
    (void)wait_.timedWait(iox::units::Duration::fromNanoseconds(static_cast<std::uint64_t>(timeout.count())));
  }

  void releaseHeld() {
    if (held_ != nullptr) frames_.release(held_);
    held_ = nullptr;
  }

  // Takes queued frames until one is usable (held, with current_ filled but for its IMU); false when none is.
  bool takeFrame() {
    while (true) {
      auto taken = frames_.take();
      if (taken.has_error()) return false;
      const void* chunk = taken.value();
      const std::uint32_t bytes = iox::mepoo::ChunkHeader::fromUserPayload(chunk)->userPayloadSize();
      if (bytes < sizeof(FrameHeader)) {
        refuse(chunk, faults_.messages_malformed, "a frame message shorter than its header");
        continue;
      }
      const auto& header = *static_cast<const FrameHeader*>(chunk);
      if (header.magic != live::kFrameMagic || header.version != live::kTopicVersion) {
        refuse(chunk, faults_.messages_malformed, "a frame message of another layout or version");
        continue;
      }
      noteArrival();
      countSequence(header.sequence);
      if ((header.flags & live::kEndOfStream) != 0U) {
        frames_.release(chunk);
        ended_ = true;
        if (!o_.quiet) std::fprintf(stderr, "[live] '%s': the driver ended the stream\n", o_.stream.c_str());
        return false;
      }
      const std::int64_t t_ns = header.t_ns + o_.timeshift_cam_imu_ns;
      if (last_frame_t_ns_ >= 0 && t_ns <= last_frame_t_ns_) {
        refuse(chunk, faults_.frames_out_of_order, "a frame not later than the one before");
        continue;
      }
      last_frame_t_ns_ = t_ns;
      held_ = chunk;
      fill(header, bytes);
      return true;
    }
  }

  // A new sequence below the expected one is a driver that started again; above it, frames that never arrived.
  void countSequence(std::uint64_t sequence) {
    if (seen_frame_) {
      if (sequence < next_sequence_) {
        ++faults_.driver_restarts;
        // A restarted driver may start its clock anew: its frames follow its own, not the old ones'.
        last_frame_t_ns_ = -1;
        previous_good_t_ns_ = -1;
        restarted_ = true;
        if (!o_.quiet) std::fprintf(stderr, "[live] '%s': the driver started again\n", o_.stream.c_str());
      } else {
        faults_.frames_lost += sequence - next_sequence_;
      }
    }
    seen_frame_ = true;
    next_sequence_ = sequence + 1;
  }

  void fill(const FrameHeader& header, std::uint32_t bytes) {
    current_ = FeedFrame{};
    current_.t_ns = last_frame_t_ns_ + time_correction_ns_;
    current_.time_correction_ns = time_correction_ns_;
    current_.index = frames_delivered_;
    current_.captured_steady_ns = header.captured_steady_ns;
    current_.stream_restarted = restarted_;
    restarted_ = false;
    const std::size_t pixels = static_cast<std::size_t>(o_.width) * static_cast<std::size_t>(o_.height);
    const std::uint32_t cameras_needed = o_.stereo ? 2 : 1;
    if (header.width != static_cast<std::uint32_t>(o_.width) ||
        header.height != static_cast<std::uint32_t>(o_.height) || header.cameras < cameras_needed ||
        header.cameras > 2 || bytes < live::frameChunkBytes(header.width, header.height, header.cameras)) {
      std::snprintf(error_, sizeof(error_),
                    "the frame is %ux%u with %u camera(s) in %u bytes; cam0 is calibrated at %dx%d%s", header.width,
                    header.height, header.cameras, bytes, o_.width, o_.height,
                    o_.stereo ? " and stereo needs 2 cameras" : "");
      current_.ok = false;
      current_.error = error_;
      return;
    }
    const auto* base = static_cast<const std::uint8_t*>(static_cast<const void*>(&header)) + sizeof(FrameHeader);
    current_.left = {base, pixels};
    if (o_.stereo) current_.right = {base + pixels, pixels};
  }

  const FeedFrame* deliver() {
    if (current_.ok && o_.use_imu) {
      current_.imu = imu_window_.covering(
          previous_good_t_ns_ < 0 ? current_.t_ns - kImuKeptBeforeStampNs : previous_good_t_ns_, current_.t_ns);
    }
    ++frames_delivered_;
    return &current_;
  }

  void refuse(const void* chunk, std::uint64_t& counter, const char* what) {
    frames_.release(chunk);
    if (counter++ == 0 && !o_.quiet) {
      std::fprintf(stderr, "[live] '%s': dropped %s (counted in summary.json from now on)\n", o_.stream.c_str(), what);
    }
  }

  void drainImu() {
    while (true) {
      auto taken = imu_.take();
      if (taken.has_error()) return;
      const void* chunk = taken.value();
      const std::uint32_t bytes = iox::mepoo::ChunkHeader::fromUserPayload(chunk)->userPayloadSize();
      const auto* message = static_cast<const ImuMessage*>(chunk);
      if (bytes >= sizeof(ImuMessage) && message->magic == live::kImuMagic && message->version == live::kTopicVersion) {
        addImu(*message);
      } else {
        ++faults_.messages_malformed;
      }
      imu_.release(chunk);
    }
  }

  void addImu(const ImuMessage& m) {
    if (seen_imu_ && m.sequence > next_imu_sequence_) faults_.imu_lost += m.sequence - next_imu_sequence_;
    // A driver that started again counts from 0 and may start its clock anew: what it sent before is of no use.
    if (seen_imu_ && m.sequence < next_imu_sequence_) imu_window_.clear();
    seen_imu_ = true;
    next_imu_sequence_ = m.sequence + 1;
    dataset::ImuSample s;
    s.t_ns = m.t_ns;
    s.gyro_s = {m.gyro_s[0], m.gyro_s[1], m.gyro_s[2]};
    s.accel_s = {m.accel_s[0], m.accel_s[1], m.accel_s[2]};
    if (!imu_window_.add(s)) ++faults_.imu_out_of_order;
  }

  // Says that the feed waits for its first frame, and when frames stop for longer than stall_after_s and come back.
  // (iceoryx's subscription state cannot tell whether a driver is there: with several publishers allowed, a
  // subscription is granted before any offers.)
  void watchStream() {
    const std::int64_t now_ns = steadyNowNs();
    if (last_arrival_ns_ < 0) {
      if (!said_waiting_ && !o_.quiet) {
        std::fprintf(stderr, "[live] waiting for a driver to publish on '%s' (cvislam_sensor_publisher --name %s)\n",
                     o_.stream.c_str(), o_.stream.c_str());
      }
      said_waiting_ = true;
      return;
    }
    if (!stalled_ && now_ns - last_arrival_ns_ > static_cast<std::int64_t>(o_.stall_after_s * 1e9)) {
      stalled_ = true;
      ++faults_.stalls;
      if (!o_.quiet) {
        std::fprintf(stderr, "[live] '%s': no frame for %.1f s; waiting for the camera\n", o_.stream.c_str(),
                     static_cast<double>(now_ns - last_arrival_ns_) * 1e-9);
      }
    }
  }

  void noteArrival() {
    const std::int64_t now_ns = steadyNowNs();
    if (last_arrival_ns_ < 0 && !o_.quiet) std::fprintf(stderr, "[live] '%s': frames coming in\n", o_.stream.c_str());
    if (stalled_ && !o_.quiet) {
      std::fprintf(stderr, "[live] '%s': frames again after %.1f s\n", o_.stream.c_str(),
                   static_cast<double>(now_ns - last_arrival_ns_) * 1e-9);
    }
    stalled_ = false;
    last_arrival_ns_ = now_ns;
  }

  LiveFeedOptions o_;
  iox::popo::UntypedSubscriber frames_;
  iox::popo::UntypedSubscriber imu_;
  iox::popo::WaitSet<2> wait_;
  ImuWindow imu_window_;
  const void* held_ = nullptr;
  FeedFrame current_;
  char error_[192] = {};
  FeedFaults faults_;
  std::int64_t previous_good_t_ns_ = -1;
  std::int64_t last_frame_t_ns_ = -1;
  std::uint64_t next_sequence_ = 0;
  std::uint64_t next_imu_sequence_ = 0;
  std::uint64_t frames_delivered_ = 0;
  bool seen_frame_ = false;
  bool seen_imu_ = false;
  bool ended_ = false;
  bool said_waiting_ = false;
  bool restarted_ = false;  // the next frame is the restarted driver's first
  bool stalled_ = false;
  std::int64_t last_arrival_ns_ = -1;
  std::atomic<bool> closed_{false};
};

}  // namespace

Status LiveFeedOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, what}; };
  if (stream.empty() || stream.size() > live::kMaxStreamNameLength) {
    return bad("the live stream name must have 1 to " + std::to_string(live::kMaxStreamNameLength) + " characters");
  }
  if (width <= 0 || height <= 0) return bad("the live stream needs cam0's resolution from the calibration");
  if (!(imu_wait_s >= 0.0 && imu_wait_s <= 1.0)) return bad("imu_wait_s must be in [0, 1] s");
  if (imu_buffer_samples < 64) return bad("imu_buffer_samples must be at least 64");
  if (!(stall_after_s > 0.0)) return bad("stall_after_s must be > 0");
  return Status::Ok();
}

Result<std::unique_ptr<FrameFeed>> openLiveFeed(const LiveFeedOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto feed = std::make_unique<LiveFeed>(options);
  if (Status s = feed->attach(); !s.ok()) return s.error();
  return std::unique_ptr<FrameFeed>(std::move(feed));
}

}  // namespace cvislam::agent
