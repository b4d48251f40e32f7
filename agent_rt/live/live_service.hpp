// The iceoryx service of a live sensor topic. Included only by the .cpp files that open the topics.
#pragma once

#include <string>

#include "agent_rt/live/sensor_topics.hpp"
#include "iceoryx_posh/capro/service_description.hpp"

namespace cvislam::agent::live {

inline iox::capro::ServiceDescription liveService(const std::string& stream, const std::string& event) {
  const std::string service = kServiceName;
  return {iox::capro::IdString_t(iox::cxx::TruncateToCapacity, service.c_str(), service.size()),
          iox::capro::IdString_t(iox::cxx::TruncateToCapacity, stream.c_str(), stream.size()),
          iox::capro::IdString_t(iox::cxx::TruncateToCapacity, event.c_str(), event.size())};
}

}  // namespace cvislam::agent::live
