// Tracking and mapping of the agent in one thread, over a EuRoC-format sequence: for tests and benchmarks
// that look at Tracker::track() alone (allocations, latency). Mapping answers every keyframe at once, as a
// perfectly fast mapping thread would, unless it is made slow (setMappingFramesPerKeyframe); images are read
// before track() is called, as a camera driver would deliver them.
#pragma once

#include <cstdint>
#include <cstdio>
#include <deque>
#include <functional>
#include <memory>
#include <vector>

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/tracking/tracker.hpp"
#include "common/dataset/euroc.hpp"

namespace cvislam::test {

class InlineAgent {
 public:
  // Stereo uses cam1 (which the sequence must have). Options get the sequence's calibration and IMU noise.
  static Result<std::unique_ptr<InlineAgent>> create(const dataset::EurocSequence& sequence, bool stereo,
                                                     agent::TrackerOptions tracker_options = {},
                                                     agent::MapperOptions mapper_options = {});

  [[nodiscard]] std::size_t frameCount() const { return frames_.size(); }
  // Loads frame i and the IMU since the previous frame into the input (allocates: file reading).
  Status load(std::size_t i);
  // Tracks `input` next instead (a frame from elsewhere, such as a live feed); its spans must outlive track().
  void setInput(const agent::FrameInput& input) { input_ = input; }
  // Tracks the loaded frame; `around` runs just before and after track() (for counters and clocks).
  template <typename Before, typename After>
  agent::FrameResult track(Before&& before, After&& after) {
    before();
    const agent::FrameResult result = tracker_->track(input_, sink_);
    after();
    answerKeyframe();
    return result;
  }
  // Disturbances of the loaded frame, for tests: the camera covered (black images), and an offset added to its
  // accelerometer samples (as an error the IMU initialisation left would act).
  void coverCamera();
  void offsetAccelerometer(const Eigen::Vector3d& offset_s);
  [[nodiscard]] bool imuInitialised() const { return tracker_->imuInitialised(); }
  [[nodiscard]] int pendingKeyframes() const { return tracker_->pendingKeyframes(); }

  // A slow mapper: each keyframe is answered only after mapping has been busy with it for `frames` frames,
  // one keyframe at a time, in order (a mapping thread that needs that long per keyframe). 0: at once.
  void setMappingFramesPerKeyframe(int frames) { mapping_frames_per_keyframe_ = frames; }
  // Keyframes waiting for the slow mapper, the one it is busy with included.
  [[nodiscard]] std::size_t mappingBacklog() const { return queue_.size(); }

  // What countSteadyAllocations() saw once the IMU was initialised.
  struct SteadyAllocations {
    int frames = 0;
    int tracked = 0;
    int keyframes = 0;
    long allocations = 0;
  };
  // Loads and tracks every frame. Once the IMU is initialised, adds up `count()` (an allocation counter) taken
  // just before and after each track(), and prints the frames that allocated. `after_frame(i)` runs after each.
  template <typename Count, typename AfterFrame>
  Result<SteadyAllocations> countSteadyAllocations(Count&& count, AfterFrame&& after_frame) {
    SteadyAllocations out;
    for (std::size_t i = 0; i < frameCount(); ++i) {
      if (Status s = load(i); !s.ok()) return s.error();
      const bool steady = imuInitialised();
      long before = 0;
      long after = 0;
      const agent::FrameResult r = track([&] { before = count(); }, [&] { after = count(); });
      after_frame(i);
      if (!steady) continue;
      ++out.frames;
      out.tracked += r.tracked ? 1 : 0;
      out.keyframes += r.keyframe ? 1 : 0;
      out.allocations += after - before;
      if (after != before) {
        std::printf("frame %zu: %ld allocations (keyframe %d, issue %s)\n", i, after - before, r.keyframe ? 1 : 0,
                    agent::toString(r.issue));
      }
    }
    return out;
  }
  // From now on mapping also writes its map delta (what the link to the server reads) after each keyframe and
  // hands it to `sink`, on this thread.
  void onDelta(std::function<void(const agent::MapDeltaMessage&)> sink) {
    delta_sink_ = std::move(sink);
    if (!delta_) delta_ = std::make_unique<agent::MapDeltaMessage>();
  }
  // Runs `apply(mapper)` before mapping processes each keyframe (the agent's mapping thread applies the
  // downlink there).
  void beforeKeyframe(std::function<void(agent::Mapper&)> apply) { before_keyframe_ = std::move(apply); }
  // Hands each keyframe's mapper report to `report` (for local BA timings).
  void afterKeyframe(std::function<void(const agent::MapperReport&)> report) { after_keyframe_ = std::move(report); }
  [[nodiscard]] const dataset::EurocSequence& sequence() const { return sequence_; }

 private:
  class Sink final : public agent::KeyframeSink {
   public:
    Sink() : message(std::make_unique<agent::KeyframeMessage>()) {}
    agent::KeyframeMessage* loan() override { return message.get(); }
    void publish() override { published = true; }
    std::unique_ptr<agent::KeyframeMessage> message;
    bool published = false;
  };

  InlineAgent(const dataset::EurocSequence& sequence, bool stereo) : sequence_(sequence), stereo_(stereo) {}
  void answerKeyframe();
  void process(const agent::KeyframeMessage& message);

  const dataset::EurocSequence& sequence_;
  bool stereo_;
  std::vector<dataset::RigFrame> frames_;
  std::unique_ptr<agent::Tracker> tracker_;
  std::unique_ptr<agent::Mapper> mapper_;
  std::unique_ptr<agent::MapSnapshotMessage> snapshot_;
  std::unique_ptr<agent::MapDeltaMessage> delta_;
  std::function<void(const agent::MapDeltaMessage&)> delta_sink_;
  std::function<void(agent::Mapper&)> before_keyframe_;
  std::function<void(const agent::MapperReport&)> after_keyframe_;
  std::uint64_t delta_sequence_ = 0;
  Sink sink_;
  int mapping_frames_per_keyframe_ = 0;
  int mapping_busy_frames_ = 0;  // frames the slow mapper has spent on the head of the queue
  std::deque<std::unique_ptr<agent::KeyframeMessage>> queue_;
  std::vector<std::uint8_t> left_;
  std::vector<std::uint8_t> right_;
  std::vector<dataset::ImuSample> disturbed_imu_;
  agent::FrameInput input_;
  std::int64_t previous_t_ns_ = -1;
};

}  // namespace cvislam::test
