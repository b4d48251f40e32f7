// Tests change keyframes the way the back-end does after a global BA: a correction of each keyframe's state
// (before -> after, with velocity and biases), applied to its map through backend::applyToMission under the
// stack's locks, so that the agent's frame, the downlink queue and the map events follow as they do in a mission.
#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "server_cloud/backend/map_corrections.hpp"
#include "server_cloud/core/server_core.hpp"

namespace cvislam::server::test {

struct KeyframeStateChange {
  KeyframeId id;
  geometry::SE3d T_m_s;
  Eigen::Vector3d v_m = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
};

// Every change applied, per map, as one GBA result would be; what applyToMission reported, merged over the maps.
inline Result<backend::AppliedCorrections> correctAsTheBackend(ServerCore& core, const std::string& mission_name,
                                                               const std::vector<KeyframeStateChange>& changes) {
  const std::shared_ptr<Mission> mission = core.missions().find(mission_name);
  if (!mission) return Error{ErrorCode::kNotFound, "no mission '" + mission_name + "'"};
  std::map<MapId, std::vector<backend::KeyframeCorrection>> by_map;
  for (const KeyframeStateChange& c : changes) {
    const SharedAgentRecord shared = mission->findAgent(c.id.agent);
    if (!shared) return Error{ErrorCode::kNotFound, "no agent " + std::to_string(c.id.agent)};
    const auto record = shared->read();
    const auto held = record->keyframes.find(c.id.counter);
    if (held == record->keyframes.end()) return Error{ErrorCode::kNotFound, "no keyframe " + c.id.toString()};
    const MapId map = held->second.map;
    const std::shared_ptr<ServerMap> server_map = mission->stack().find(map);
    if (!server_map) return Error{ErrorCode::kInternal, "keyframe " + c.id.toString() + " in a vanished map"};
    const ServerKeyframe* kf = server_map->read()->keyframe(c.id);
    if (kf == nullptr) return Error{ErrorCode::kInternal, "keyframe " + c.id.toString() + " not in its map"};
    by_map[map].push_back(backend::KeyframeCorrection{c.id, kf->T_w_s, c.T_m_s, std::pair{c.v_m, c.bias}});
  }
  backend::AppliedCorrections all;
  for (const auto& [map, corrections] : by_map) {
    backend::StackLocks locks(*mission, {mission->stack().find(map)});
    const backend::AppliedCorrections applied =
        backend::applyToMission(*mission, locks, map, corrections, {}, backend::ApplyOptions{}, "global BA");
    all.changed.insert(all.changed.end(), applied.changed.begin(), applied.changed.end());
    all.keyframes_optimised += applied.keyframes_optimised;
    all.keyframes_propagated += applied.keyframes_propagated;
  }
  return all;
}

}  // namespace cvislam::server::test
