// Which server replica serves a mission (scale-out): the seam between the sessions and the map service, which
// ask, and the replica coordinator (server_cloud/cluster/replica_coordinator.hpp), which answers from the leases.
// A server that runs alone has none: it serves every mission.
#pragma once

#include <string>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::server {

struct MissionOwner {
  bool here = true;     // this replica serves the mission
  std::string holder;   // otherwise: the replica that does (its lease holder name)
  std::string address;  // and where to reach it (host:port)
};

class MissionOwnership {
 public:
  virtual ~MissionOwnership() = default;
  // An agent's Hello names `mission`: this replica takes the mission when nobody serves it (a new mission, or
  // one whose owner's lease lapsed), loading what the store holds of it first, and otherwise says who serves it.
  virtual Result<MissionOwner> claim(const std::string& mission) = 0;
  // Who serves `mission`, without taking it (map-service reads). kNotFound when no replica ever served it.
  virtual Result<MissionOwner> owner(const std::string& mission) = 0;
  // The other replicas that serve a mission now, each once (a deployment-wide listing asks each).
  virtual Result<std::vector<MissionOwner>> others() = 0;
};

}  // namespace cvislam::server
