// The IMU-rate state for IMU samples pushed by a program (the embedding API), on a thread of its own: the program's
// IMU thread and tracking's frame states reach it through bounded queues, a futex doorbell wakes it, and it carries
// the newest frame state through each sample (ImuPropagator) and tells the listener. Nothing the producers call
// allocates, locks or waits; what a full queue refuses is counted.
#pragma once

#include <atomic>
#include <cstdint>
#include <thread>

#include "agent_rt/runtime/doorbell.hpp"
#include "agent_rt/runtime/live_state.hpp"
#include "agent_rt/runtime/spsc_queue.hpp"

namespace cvislam::agent {

class PushedPropagation {
 public:
  // `listener` is told every propagated state, on this object's thread.
  PushedPropagation(StateListener& listener, std::size_t imu_samples = 4096);
  ~PushedPropagation();
  PushedPropagation(const PushedPropagation&) = delete;
  PushedPropagation& operator=(const PushedPropagation&) = delete;

  // From the program's IMU thread.
  void pushImu(const dataset::ImuSample& sample, std::int64_t captured_steady_ns);
  // From tracking's thread, every frame's state.
  void onFrameState(const live::AgentStateMessage& state);
  // Samples and frame states refused by a full queue.
  [[nodiscard]] std::uint64_t dropped() const { return dropped_.load(std::memory_order_relaxed); }

 private:
  struct Sample {
    dataset::ImuSample imu;
    std::int64_t captured_steady_ns = 0;
  };
  void run();

  StateListener& listener_;
  ImuPropagator propagator_;
  SpscQueue<Sample> samples_;
  SpscQueue<live::AgentStateMessage> frame_states_;
  Doorbell doorbell_;
  std::atomic<bool> stopping_{false};
  std::atomic<std::uint64_t> dropped_{0};
  std::uint64_t sequence_ = 0;
  std::thread thread_;
};

}  // namespace cvislam::agent
