// Which own keyframe leaves the local map when it is full. The newest N (MapperOptions::max_keyframes) always
// stay: they are the local BA window, the keyframes new points are triangulated against and what tracking has
// just seen. Up to `place_keyframes` older ones are kept for their places rather than their age: when one must
// go, it is the one whose place an older keyframe covers best (nearest in camera position and viewing
// direction). A robot that comes back to a place then finds it mapped, its keyframes and points from the first
// visit, and tracking and local BA tie the new keyframes to them; with only the newest keyframes kept, it maps the
// place again and the drift since stays.
//
// Measured against an older keyframe only, so that of two keyframes at one place the newer goes: the older has
// been refined longer and carries the map the robot made on its first visit.
//
// The mapper keeps the newest N only while it holds the server's covisible map (mapper.cpp, makeRoomForKeyframe):
// the server's map is then the memory of the places.
#pragma once

#include <optional>
#include <vector>

#include "agent_rt/map/local_map.hpp"
#include "common/core/result.hpp"

namespace cvislam::agent {

struct KeyframeRetentionOptions {
  // Own keyframes kept besides the newest N; 0: the oldest goes. With N = 20 and keyframes at most 0.5 s apart,
  // the newest reach back 10 s; the simulated loop comes back over its start after about 40 s.
  int place_keyframes = 40;
  // Two viewing directions 1 rad apart count as far apart as two camera positions this many metres apart.
  double angle_weight_m = 1.0;

  [[nodiscard]] Status validate() const;
};

// The own keyframe to evict, from `own` (the map's own keyframes, oldest first), of which the newest `recent`
// stay: the oldest when there are fewer than two older ones or place_keyframes is 0, else the older one whose
// nearest older own keyframe is nearest. Empty when `own` is empty.
std::optional<PoolHandle> keyframeToEvict(const LocalMap& map, const std::vector<PoolHandle>& own, int recent,
                                          const KeyframeRetentionOptions& options);

}  // namespace cvislam::agent
