// The local map's structural changes, as they happen, for whoever mirrors the map outside the mapping thread
// (the link to the server). LocalMap reports each change to an optional MapEventSink; positions and states are
// not events (they change in every local BA; the map delta carries them whole).
#pragma once

#include <cstdint>
#include <type_traits>

#include "common/core/ids.hpp"

namespace cvislam::agent {

enum class MapEventType : std::uint8_t {
  kPointCreated = 0,      // `point` made, observed by `keypoint` of `keyframe` (its reference)
  kObservationAdded = 1,  // `keypoint` of `keyframe` now observes `point`
  kPointsMerged = 2,      // `point` (dropped) merged into `other` (kept): its observations now observe `other`
  kPointRemoved = 3,      // `point` left the local map (see `reason`)
  kKeyframeRemoved = 4,   // `keyframe` left the local map (see `reason`); its observations went with it
};

enum class MapEventReason : std::uint8_t {
  kNone = 0,
  kCulled = 1,   // judged bad (rarely found, unconfirmed): the map should forget it
  kEvicted = 2,  // left the bounded local map (oldest keyframe out, or its last observer went): still valid
  kRemoved = 3,  // taken out by mapping (a map restart, a monocular start dropping keyframes between its views)
};

struct MapEvent {
  MapEventType type = MapEventType::kPointCreated;
  MapEventReason reason = MapEventReason::kNone;
  std::uint16_t keypoint = 0;
  KeyframeId keyframe;
  MapPointId point;
  MapPointId other;
};
static_assert(std::is_trivially_copyable_v<MapEvent>);

class MapEventSink {
 public:
  virtual ~MapEventSink() = default;
  virtual void record(const MapEvent& event) = 0;
};

}  // namespace cvislam::agent
