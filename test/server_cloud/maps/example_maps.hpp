// Server maps filled directly (no agents, no gRPC) for the map service's tests and benchmark: a mission whose
// stack holds a map shared by two agents and a map of a third, with points, observations, descriptors and
// states that are all different, from a seeded generator.
#pragma once

#include <cstdint>
#include <string>

#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::test {

struct ExampleMissionOptions {
  std::string name = "survey";
  std::uint32_t keyframes_per_agent = 12;  // agents 1 and 2 in map 0, agent 3 in map 1 (half as many)
  std::uint32_t points_per_keyframe = 30;  // new points each keyframe makes
  std::uint16_t keypoints_per_keyframe = 200;
  std::uint32_t seed = 7;
};

// Makes the mission in `missions` (it must not exist yet): map 0, opened for agent 1's map 0, with the keyframes
// of agents 1 and 2 interleaved in time; map 1, opened for agent 3's map 0. Each keyframe observes its own new
// points and the previous keyframe's of its map, so neighbours are covisible. Every third keyframe is refined.
void fillExampleMission(server::MissionRegistry& missions, const ExampleMissionOptions& options = {});

}  // namespace cvislam::test
