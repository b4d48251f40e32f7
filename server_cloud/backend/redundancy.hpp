// Redundancy detection and removal (CVI-SLAM IV-E): keyframes picked at random are removed when what they see
// is seen well enough by their covisible neighbours, so that maps grow with the explored place and not with the
// time spent in it.
//
// A keyframe is redundant when at least `redundant_fraction` of its map points are observed by at least
// `min_other_observers` other keyframes. It stays when removing it would leave more than `max_imu_gap_s`
// between the two keyframes its IMU link joins, and when it is among its agent's `keep_newest` keyframes (the
// agent's local BA still refines those, and its next keyframe links to the newest). The two preintegrations
// around a removed keyframe are joined by integrating the raw IMU again from the earlier keyframe. Points left
// with fewer than `min_point_observations` observations go too.
#pragma once

#include <cstdint>
#include <random>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/stack/map_content.hpp"

namespace cvislam::server::backend {

struct RedundancyOptions {
  bool enabled = true;
  double redundant_fraction = 0.9;
  int min_other_observers = 3;
  double max_imu_gap_s = 2.0;
  int keep_newest = 10;
  int checks_per_round = 20;
  int min_point_observations = 2;
  std::uint64_t seed = 1;

  [[nodiscard]] Status validate() const;
};

struct RedundancyReport {
  int checked = 0;
  int redundant = 0;
  int kept_for_imu_gap = 0;
  std::vector<KeyframeId> removed_keyframes;
  std::vector<MapPointId> removed_points;
};

// Checks up to checks_per_round random keyframes of `map` and removes the redundant ones.
RedundancyReport removeRedundantKeyframes(MapContent& map, const AgentSensorsMap& sensors,
                                          const RedundancyOptions& options, std::mt19937_64& rng);

// The fraction of the keyframe's points that at least min_other_observers other keyframes observe (0 without points).
double coveredFraction(const MapContent& map, const KeyframeId& id, const RedundancyOptions& options);

// Whether `id` is redundant by the point rule alone (for tests and statistics).
bool isRedundant(const MapContent& map, const KeyframeId& id, const RedundancyOptions& options);

}  // namespace cvislam::server::backend
