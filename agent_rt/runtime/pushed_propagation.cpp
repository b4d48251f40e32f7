#include "agent_rt/runtime/pushed_propagation.hpp"

#include <chrono>

#include "common/core/steady_clock.hpp"

namespace cvislam::agent {

PushedPropagation::PushedPropagation(StateListener& listener, std::size_t imu_samples)
    : listener_(listener), propagator_(imu_samples), samples_(imu_samples), frame_states_(64) {
  thread_ = std::thread([this] { run(); });
}

PushedPropagation::~PushedPropagation() {
  stopping_.store(true);
  doorbell_.ring();
  if (thread_.joinable()) thread_.join();
}

void PushedPropagation::pushImu(const dataset::ImuSample& sample, std::int64_t captured_steady_ns) {
  if (!samples_.push({sample, captured_steady_ns})) {
    dropped_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  doorbell_.ring();
}

void PushedPropagation::onFrameState(const live::AgentStateMessage& state) {
  if (!frame_states_.push(state)) {
    dropped_.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  doorbell_.ring();
}

void PushedPropagation::run() {
  live::AgentStateMessage frame_state;
  Sample sample;
  while (!stopping_.load()) {
    const std::uint32_t seen = doorbell_.seen();
    bool any = false;
    // Frame states first: a sample after a frame is carried from that frame.
    while (frame_states_.pop(frame_state)) {
      propagator_.onFrameState(frame_state);
      any = true;
    }
    while (samples_.pop(sample)) {
      any = true;
      auto state = propagator_.onImu(sample.imu, sample.captured_steady_ns);
      if (!state) continue;
      state->sequence = sequence_++;
      state->published_steady_ns = steadyNowNs();
      listener_.onState(*state);
    }
    // The timeout only lets a stop in; rings wake it.
    if (!any) doorbell_.waitFor(seen, std::chrono::milliseconds(100));
  }
}

}  // namespace cvislam::agent
