// The iceoryx services of the live sensor and state topics. Included only by the .cpp files that open the topics.
#pragma once

#include <cstdint>
#include <string>

#include "agent_rt/live/sensor_topics.hpp"
#include "agent_rt/live/state_topics.hpp"
#include "iceoryx_posh/capro/service_description.hpp"
#include "iceoryx_posh/popo/subscriber_options.hpp"

namespace cvislam::agent::live {

inline iox::capro::ServiceDescription topicService(const std::string& service, const std::string& instance,
                                                   const std::string& event) {
  return {iox::capro::IdString_t(iox::cxx::TruncateToCapacity, service.c_str(), service.size()),
          iox::capro::IdString_t(iox::cxx::TruncateToCapacity, instance.c_str(), instance.size()),
          iox::capro::IdString_t(iox::cxx::TruncateToCapacity, event.c_str(), event.size())};
}

// A sensor topic of the driver's stream NAME.
inline iox::capro::ServiceDescription liveService(const std::string& stream, const std::string& event) {
  return topicService(kServiceName, stream, event);
}

// A state topic of agent `agent`.
inline iox::capro::ServiceDescription stateService(std::uint32_t agent, const std::string& event) {
  return topicService(kStateServiceName, "agent" + std::to_string(agent), event);
}

// A reader's queue of `depth` messages on a live or state topic; when the reader falls behind the oldest go, for no
// publisher there waits for a reader.
inline iox::popo::SubscriberOptions dropOldestQueue(std::uint64_t depth) {
  iox::popo::SubscriberOptions options;
  options.queueCapacity = depth;
  options.historyRequest = 0;
  options.queueFullPolicy = iox::popo::QueueFullPolicy::DISCARD_OLDEST_DATA;
  return options;
}

}  // namespace cvislam::agent::live
