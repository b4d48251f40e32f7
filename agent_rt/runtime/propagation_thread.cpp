#include "agent_rt/runtime/propagation_thread.hpp"

#include <cstdio>

#include "agent_rt/live/live_service.hpp"
#include "agent_rt/live/sensor_topics.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/mepoo/chunk_header.hpp"
#include "iceoryx_posh/popo/publisher.hpp"
#include "iceoryx_posh/popo/subscriber.hpp"
#include "iceoryx_posh/popo/untyped_subscriber.hpp"
#include "iceoryx_posh/popo/user_trigger.hpp"
#include "iceoryx_posh/popo/wait_set.hpp"

namespace cvislam::agent {
namespace {

iox::popo::SubscriberOptions queueOf(std::uint64_t depth) {
  iox::popo::SubscriberOptions options;
  options.queueCapacity = depth;
  options.queueFullPolicy = iox::popo::QueueFullPolicy::DISCARD_OLDEST_DATA;
  return options;
}

iox::popo::PublisherOptions newestKept() {
  iox::popo::PublisherOptions options;
  options.historyCapacity = 1;  // a reader that comes late still gets the newest state
  options.subscriberTooSlowPolicy = iox::popo::ConsumerTooSlowPolicy::DISCARD_OLDEST_DATA;
  return options;
}

}  // namespace

struct PropagationThread::Impl {
  Impl(const PropagationOptions& o, LatencyRecorder& latencies)
      : options(o),
        imu_to_state(latencies),
        propagator(o.imu_samples),
        imu(live::liveService(o.stream, live::kImuEvent), queueOf(iox::MAX_SUBSCRIBER_QUEUE_CAPACITY)),
        frame_states(live::stateService(o.agent, live::kStateFramesEvent), queueOf(8)),
        publisher(live::stateService(o.agent, live::kStateImuEvent), newestKept()) {}

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
    state.sequence = sequence++;
    auto loaned = publisher.loan();
    state.published_steady_ns = steadyNowNs();
    if (!loaned.has_error()) {
      *loaned.value().get() = state;
      loaned.value().publish();
    } else {
      ++not_sent;
    }
    imu_to_state.add(state.published_steady_ns - state.captured_steady_ns);
    if (options.listener != nullptr) options.listener->onState(state);
  }

  PropagationOptions options;
  LatencyRecorder& imu_to_state;
  ImuPropagator propagator;
  iox::popo::UntypedSubscriber imu;
  iox::popo::Subscriber<live::AgentStateMessage> frame_states;
  iox::popo::Publisher<live::AgentStateMessage> publisher;
  iox::popo::UserTrigger stop;
  iox::popo::WaitSet<3> wait;
  std::atomic<bool> stopping{false};
  std::uint64_t sequence = 0;
  std::uint64_t not_sent = 0;
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
  return impl_->not_sent;
}

}  // namespace cvislam::agent
