// One of the agent's state topics (agent_rt/live/state_topics.hpp) as the threads that publish on it use it: each
// message (a state, or the health message) numbered and stamped at publication, and counted when no chunk was
// free, for a message is never waited for. A reader that comes late still gets the newest one. Holds an iceoryx
// publisher: for the runtime's .cpp files only.
#pragma once

#include <cstdint>

#include "agent_rt/live/live_service.hpp"
#include "agent_rt/live/state_topics.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/popo/publisher.hpp"

namespace cvislam::agent {

template <typename Message = live::AgentStateMessage>
class StatePublisher {
 public:
  StatePublisher(std::uint32_t agent, const char* event) : publisher_(live::stateService(agent, event), newestKept()) {}

  // Numbers and stamps `state` (published_steady_ns), and publishes it if a chunk is free.
  void publish(Message& state) {
    state.sequence = sequence_++;
    auto loaned = publisher_.loan();
    state.published_steady_ns = steadyNowNs();
    if (loaned.has_error()) {
      ++not_sent_;
      return;
    }
    *loaned.value().get() = state;
    loaned.value().publish();
  }

  // States that found no free chunk.
  [[nodiscard]] std::uint64_t notSent() const { return not_sent_; }

 private:
  static iox::popo::PublisherOptions newestKept() {
    iox::popo::PublisherOptions options;
    options.historyCapacity = 1;
    options.subscriberTooSlowPolicy = iox::popo::ConsumerTooSlowPolicy::DISCARD_OLDEST_DATA;
    return options;
  }

  iox::popo::Publisher<Message> publisher_;
  std::uint64_t sequence_ = 0;
  std::uint64_t not_sent_ = 0;
};

}  // namespace cvislam::agent
