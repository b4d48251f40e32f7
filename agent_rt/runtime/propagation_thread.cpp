#include "agent_rt/runtime/propagation_thread.hpp"

#include <cstdio>

#include "agent_rt/live/live_service.hpp"
#include "agent_rt/live/sensor_topics.hpp"
#include "agent_rt/runtime/state_publisher.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/mepoo/chunk_header.hpp"
#include "iceoryx_posh/popo/subscriber.hpp"
#include "iceoryx_posh/popo/untyped_subscriber.hpp"
#include "iceoryx_posh/popo/user_trigger.hpp"
#include "iceoryx_posh/popo/wait_set.hpp"

namespace cvislam::agent {
struct PropagationThread::Impl {
  Impl(const PropagationOptions& o, LatencyRecorder& latencies)
      : options(o),
        imu_to_state(latencies),
        propagator(o.imu_samples),
        imu(live::liveService(o.stream, live::kImuEvent), live::dropOldestQueue(iox::MAX_SUBSCRIBER_QUEUE_CAPACITY)),
        frame_states(live::stateService(o.agent, live::kStateFramesEvent), live::dropOldestQueue(8)),
        publisher(o.agent, live::kStateImuEvent) {}

  void run() {
    if (wait.attachState(imu, iox::popo::SubscriberState::HAS_DATA).has_error() ||
        wait.attachState(frame_states, iox::popo::SubscriberState::HAS_DATA).has_error() ||
        wait.attachEvent(stop).has_error()) {
      std::fprintf(stderr, "[state] iceoryx refused to wait on the IMU and state topics: no IMU-rate state\n");
      return;
    }
    while (!stopping.load()) {
      (void)wait.wait();
      takeFrameStates();
      takeImu();
    }
  }

  void takeFrameStates() {
    while (true) {
      auto taken = frame_states.take();
      if (taken.has_error()) return;
      propagator.onFrameState(*taken.value());
    }
  }

  void takeImu() {
    while (true) {
      auto taken = imu.take();
      if (taken.has_error()) return;
      const void* chunk = taken.value();
      const auto& m = *static_cast<const live::ImuMessage*>(chunk);
      const bool valid = iox::mepoo::ChunkHeader::fromUserPayload(chunk)->userPayloadSize() >= sizeof(m) &&
                         m.magic == live::kImuMagic && m.version == live::kTopicVersion;
      if (valid) {
        dataset::ImuSample sample;
        sample.t_ns = m.t_ns;
        sample.gyro_s = {m.gyro_s[0], m.gyro_s[1], m.gyro_s[2]};
        sample.accel_s = {m.accel_s[0], m.accel_s[1], m.accel_s[2]};
        if (auto state = propagator.onImu(sample, m.captured_steady_ns)) publish(*state);
      }
      imu.release(chunk);
    }
  }

  void publish(live::AgentStateMessage& state) {
    publisher.publish(state);
    imu_to_state.add(state.published_steady_ns - state.captured_steady_ns);
    if (options.listener != nullptr) options.listener->onState(state);
  }

  PropagationOptions options;
  LatencyRecorder& imu_to_state;
  ImuPropagator propagator;
  iox::popo::UntypedSubscriber imu;
  iox::popo::Subscriber<live::AgentStateMessage> frame_states;
  StatePublisher<> publisher;
  iox::popo::UserTrigger stop;
  iox::popo::WaitSet<3> wait;
  std::atomic<bool> stopping{false};
};

PropagationThread::PropagationThread(const PropagationOptions& options, LatencyRecorder& imu_to_state,
                                     const std::function<void()>& on_start)
    : impl_(std::make_unique<Impl>(options, imu_to_state)) {
  thread_ = std::thread([this, on_start] {
    if (on_start) on_start();
    impl_->run();
  });
}

PropagationThread::~PropagationThread() {
  stop();
}

void PropagationThread::stop() {
  impl_->stopping.store(true);
  impl_->stop.trigger();
  if (thread_.joinable()) thread_.join();
}

std::uint64_t PropagationThread::notSent() const {
  return impl_->publisher.notSent();
}

}  // namespace cvislam::agent
