// Missions: the world layout and one smooth trajectory per agent, for a named preset or for replayed flights.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "test/sim/trajectory.hpp"
#include "test/sim/world.hpp"

namespace cvislam::sim {

struct AgentPlan {
  std::string name;    // agent0, agent1, ...
  std::string source;  // what the motion comes from (a preset or a ground-truth file)
  BodyTrajectory trajectory;
};

struct MissionPlan {
  std::string preset;
  WorldLayout layout;
  std::vector<AgentPlan> agents;
  double duration_s = 0.0;
};

struct MissionPlanOptions {
  std::string preset = "loop";  // loop, overlap2, hall4, hall8, aggressive, euroc-mh; or "replay"
  std::uint64_t seed = 0;
  double duration_s = 60.0;                   // per agent
  std::vector<std::filesystem::path> replay;  // ground-truth files (TUM) to replay, one agent each
  std::filesystem::path data_dir;             // for euroc-mh: holds euroc-groundtruth/MH_0x_*.txt
  double min_clearance_m = 0.8;               // obstacles closer than this to any agent's path are left out
};

// The preset names, in the order --help lists them.
const std::vector<std::string>& presetNames();

// The data folder: $CVISLAM_DATA_DIR if set, else the build's default (<repo>/../shared/data).
std::filesystem::path defaultDataDir();

Result<MissionPlan> planMission(const MissionPlanOptions& options);

// A preset's plan with every other option at its default, as most tests and tools want it.
Result<MissionPlan> planPreset(const std::string& preset, std::uint64_t seed, double duration_s);

}  // namespace cvislam::sim
