// The monocular map's start. The reference keyframe's keypoints are followed through every keyframe tracking sends
// while there is no map: each is searched for in a window around where it was in the keyframe before, turned by
// the gyro's rotation in between. Once the reference and the newest keyframe see the followed keypoints with
// enough parallax, their two views make the map (up to scale), and the keyframes between take their poses from
// its points. They stay in the map: their IMU links make the chain the IMU initialisation aligns from the
// reference on, so the map can be metric the moment it has enough keyframes, not that many keyframes later.
// When the view moves on so far that too few of the reference's keypoints are still followed, the newest keyframe
// becomes the reference, and the keyframes before it stay as long as they share enough keypoints with it to be
// placed on the map's points: a slow start that loses its reference keeps the motion it has seen.
#pragma once

#include <cstdint>

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/mapping/mapper_state.hpp"

namespace cvislam::agent {

// The newest keyframe (`handle`) of a monocular map without its two-view start: followed from the reference, and
// the start tried. The reference starts over at this keyframe when too few of its keypoints are still followed
// (keeping the keyframes before it that share enough of them), or when the keyframes waiting for the start would
// fill the map's share of own keyframes (the ones kept from an earlier reference go first).
void tryMonocularStart(Mapper::State& s, PoolHandle handle, MapperReport& report);

}  // namespace cvislam::agent
