// How the back-end changes a mission's maps: the locks it takes (the agent records of the maps' agents, then the
// maps, in the stack's order) and the one path by which corrections reach a map, its agents' records and the map
// service's watchers. A GBA, a loop closure and the tests all go through applyToMission().
#pragma once

#include <map>
#include <memory>
#include <vector>

#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::server::backend {

// The agent records of some agents and some maps, locked for writing in the stack's order.
class StackLocks {
 public:
  StackLocks(Mission& mission, const std::vector<std::shared_ptr<ServerMap>>& maps);
  StackLocks(const StackLocks&) = delete;
  StackLocks& operator=(const StackLocks&) = delete;

  [[nodiscard]] MapContent& map(MapId id) { return *by_map_.at(id); }
  [[nodiscard]] std::map<AgentId, AgentRecord*>& records() { return by_agent_; }

 private:
  std::vector<Synchronized<AgentRecord>::WriteLocked> records_;
  std::vector<decltype(std::declval<ServerMap&>().write())> maps_;
  std::map<AgentId, AgentRecord*> by_agent_;
  std::map<MapId, MapContent*> by_map_;
};

// Applies corrections to one map with `locks` held (they must hold `map`): the map's keyframes and points move
// (applyCorrections), each agent map's T_m_w follows its newest corrected keyframes, every changed keyframe is
// queued for its agent's downlink, and the map service's watchers get one event naming `cause`.
AppliedCorrections applyToMission(Mission& mission, StackLocks& locks, MapId map,
                                  const std::vector<KeyframeCorrection>& keyframes,
                                  const std::vector<PointCorrection>& points, const ApplyOptions& options,
                                  const char* cause);

}  // namespace cvislam::server::backend
