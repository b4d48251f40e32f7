// The IMU-rate state of a live run on its own thread: it reads the driver's IMU topic and tracking's per-frame states
// (both iceoryx), carries the newest state through each new sample (ImuPropagator), and publishes the result on the
// agent's "imu" state topic and to the listener. It waits on those topics alone, so a sample is carried the moment it
// arrives, whatever tracking is busy with. iceoryx headers stay in the .cpp.
#pragma once

#include <atomic>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "agent_rt/runtime/latency_profile.hpp"
#include "agent_rt/runtime/live_state.hpp"

namespace cvislam::agent {

struct PropagationOptions {
  std::string stream;  // the driver's stream NAME
  AgentId agent = 0;
  std::size_t imu_samples = 2048;     // kept for carrying states forward again when a frame's state arrives
  StateListener* listener = nullptr;  // also told every propagated state
};

class PropagationThread {
 public:
  // Starts the thread, which first calls `on_start` (its scheduling). `imu_to_state` gets one latency per published
  // state, from the sample's capture to its publication; it is written by this thread until the object is destroyed.
  PropagationThread(const PropagationOptions& options, LatencyRecorder& imu_to_state,
                    const std::function<void()>& on_start);
  // Stops the thread first.
  ~PropagationThread();
  // States that found no free chunk to be published in (the listener still got them). Read after stop().
  [[nodiscard]] std::uint64_t notSent() const;
  void stop();
  PropagationThread(const PropagationThread&) = delete;
  PropagationThread& operator=(const PropagationThread&) = delete;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  std::thread thread_;
};

}  // namespace cvislam::agent
