// The IMU initialisation of a map (the paper's section IV-C): the trailing run of IMU-linked keyframes aligned with
// the IMU, the map moved into the metric, gravity-aligned frame. When the camera-IMU time offset is estimated, the
// keyframes made before it are re-timed to it: their poses came from vision alone, so they are the poses at the
// times the images were really taken, and it is their times and the IMU between them that must move, not the poses.
#pragma once

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/mapping/mapper_state.hpp"

namespace cvislam::agent {

// Keeps the keyframe message's IMU samples, when the time offset is estimated: the re-timing needs those before
// and after the keyframes, and a keyframe's preintegration from a re-timed one may start before its message's
// first sample. Bounded: the oldest samples go first.
void keepImuHistory(Mapper::State& s, const KeyframeMessage& msg);

// kNotFound while there are too few IMU-linked keyframes; other errors when the alignment refuses the motion.
Status initialiseImu(Mapper::State& s, MapperReport& report);

}  // namespace cvislam::agent
