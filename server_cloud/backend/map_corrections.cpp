#include "server_cloud/backend/map_corrections.hpp"

#include <algorithm>
#include <set>
#include <utility>

namespace cvislam::server::backend {

StackLocks::StackLocks(Mission& mission, const std::vector<std::shared_ptr<ServerMap>>& maps) {
  std::set<AgentId> agents;
  for (const auto& map : maps) {
    const auto content = map->read();
    agents.insert(content->agents().begin(), content->agents().end());
  }
  // Found first and locked after: the mission's agent map is not to be locked while a record is.
  std::vector<std::pair<AgentId, SharedAgentRecord>> found;
  for (AgentId agent : agents) {
    if (SharedAgentRecord shared = mission.findAgent(agent)) found.emplace_back(agent, std::move(shared));
  }
  records_.reserve(found.size());
  for (const auto& [agent, shared] : found) {
    records_.push_back(shared->write());
    by_agent_.emplace(agent, &*records_.back());
  }
  std::vector<std::shared_ptr<ServerMap>> sorted = maps;
  std::sort(sorted.begin(), sorted.end(), [](const auto& a, const auto& b) { return a->id() < b->id(); });
  sorted.erase(std::unique(sorted.begin(), sorted.end()), sorted.end());
  for (const auto& map : sorted) {
    maps_.push_back(map->write());
    by_map_.emplace(map->id(), &*maps_.back());
  }
}

namespace {

// A map's keyframes moved (a GBA's or a loop's corrections): one event for the map service's watchers.
void appendCorrected(Mission& mission, MapId map, const AppliedCorrections& applied, const char* cause) {
  if (applied.changed.empty()) return;
  MissionEvent corrected;
  corrected.kind = MissionEvent::Kind::kMapCorrected;
  corrected.map = map;
  corrected.keyframes = static_cast<std::uint32_t>(applied.changed.size());
  corrected.cause = cause;
  mission.events().append(std::move(corrected));
}

// Brings the records up to date after `applied` changed the map: each agent map's T_m_w follows its frame's
// change (its newest corrected keyframes'), and every changed keyframe is queued for the downlink.
void updateRecords(std::map<AgentId, AgentRecord*>& records, const AppliedCorrections& applied) {
  for (const auto& [key, change] : applied.frame_change) {
    const auto it = records.find(key.first);
    if (it == records.end()) continue;
    const auto agent_map = it->second->agent_maps.find(key.second);
    if (agent_map != it->second->agent_maps.end()) agent_map->second.T_m_w = change * agent_map->second.T_m_w;
  }
  for (const KeyframeId& id : applied.changed) {
    const auto it = records.find(id.agent);
    if (it != records.end()) it->second->corrections.insert(id.counter);
  }
}

}  // namespace

AppliedCorrections applyToMission(Mission& mission, StackLocks& locks, MapId map,
                                  const std::vector<KeyframeCorrection>& keyframes,
                                  const std::vector<PointCorrection>& points, const ApplyOptions& options,
                                  const char* cause) {
  const AppliedCorrections applied = applyCorrections(locks.map(map), keyframes, points, options);
  updateRecords(locks.records(), applied);
  appendCorrected(mission, map, applied, cause);
  return applied;
}

}  // namespace cvislam::server::backend
