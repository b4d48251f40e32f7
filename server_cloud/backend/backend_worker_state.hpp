// What backend_worker.cpp (the control thread: fusion, merges, loops, redundancy) and backend_gba.cpp (the GBA
// thread) share of the worker's insides. Not for other code: the worker's interface is backend_worker.hpp.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <random>
#include <vector>

#include "common/core/steady_clock.hpp"
#include "server_cloud/backend/backend_worker.hpp"

namespace cvislam::server::backend {

using Clock = std::chrono::steady_clock;

// A merge's GBA frees the whole map when what the merge changed is more than this share of it: the solve then costs
// nearly as much either way, and the whole map's is the better one.
inline constexpr double kWindowMaxFreeFraction = 0.6;

// Every agent's sensors, copied from their records one at a time.
inline AgentSensorsMap sensorsOf(const Mission& mission) {
  AgentSensorsMap out;
  for (const SharedAgentRecord& shared : mission.agents()) {
    const auto record = shared->read();
    if (record->sensors) out.emplace(record->id, *record->sensors);
  }
  return out;
}

struct BackendWorker::MissionState {
  std::map<MapId, std::vector<LoopEdge>> loops;  // every loop closed per map, for later pose graphs
  std::map<AgentId, std::uint32_t> last_loop_query;
  std::map<MapId, int> keyframes_since_redundancy;
  std::map<MapId, int> keyframes_since_gba;
  std::map<MapId, MapId> merged_into;  // maps that went, and the map each went into
  std::mt19937_64 rng;
  BackendStats stats;  // under the worker's mutex
};

}  // namespace cvislam::server::backend
