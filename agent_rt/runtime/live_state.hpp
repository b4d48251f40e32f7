// The agent's live state (agent_rt/live/state_topics.hpp) made from tracking's results, and carried forward between
// frames by the IMU. Plain C++: the threads that publish it (agent.cpp, propagation_thread.cpp) hold the iceoryx side.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "agent_rt/live/state_topics.hpp"
#include "agent_rt/tracking/tracker.hpp"
#include "common/core/ids.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::agent {

// Tracking's status as the state topics say it.
live::StateStatus statusOf(TrackingStatus status);

// The state message of a frame tracking has just handled (kind kFrame; sequence and published time left to the
// publisher).
live::AgentStateMessage frameState(const FrameResult& r, std::int64_t t_ns, std::int64_t captured_steady_ns,
                                   AgentId agent);

// Who else wants every state (the embedding API's callback): called on the thread that made the state.
class StateListener {
 public:
  virtual ~StateListener() = default;
  virtual void onState(const live::AgentStateMessage& state) = 0;
};

// Carries the newest tracked state forward through the IMU samples that came after it: strapdown integration with
// the state's biases, each step with the rates of the sample that starts it. A new frame state takes over at once,
// and the samples already past it are integrated again from it, so a propagated state is never older than the
// newest frame's. Only metric states (IMU initialised) are carried: before that there is no gravity and no scale.
// Fixed memory: `capacity` samples are kept; allocation-free after construction.
class ImuPropagator {
 public:
  explicit ImuPropagator(std::size_t capacity);

  // A tracked frame's state. Older than the one held: ignored.
  void onFrameState(const live::AgentStateMessage& state);
  // An IMU sample (captured at `captured_steady_ns`): the state carried to its time, when there is a state to carry
  // and the sample is newer than it.
  std::optional<live::AgentStateMessage> onImu(const dataset::ImuSample& sample, std::int64_t captured_steady_ns);

 private:
  void step(const dataset::ImuSample& rates, std::int64_t to_ns);
  void keepSamplesFrom(std::int64_t t_ns);

  std::vector<dataset::ImuSample> samples_;       // time-ordered, from the one at or before the state's time
  std::optional<live::AgentStateMessage> state_;  // carried to the newest sample
  std::int64_t frame_t_ns_ = 0;                   // the time of the frame state it was carried from
  geometry::SE3d T_w_s_;
  Eigen::Vector3d v_w_ = Eigen::Vector3d::Zero();
  imu::ImuBias bias_;
};

}  // namespace cvislam::agent
