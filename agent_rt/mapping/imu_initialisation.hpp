// The IMU initialisation of a map (the paper's section IV-C): the trailing run of IMU-linked keyframes aligned with
// the IMU, the map moved into the metric, gravity-aligned frame. When the camera-IMU time offset is estimated, the
// keyframes made before it are re-timed to it: their poses came from vision alone, so they are the poses at the
// times the images were really taken, and it is their times and the IMU between them that must move, not the poses.
#pragma once

#include <span>
#include <vector>

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/mapping/mapper_state.hpp"

namespace cvislam::agent {

// Keeps the keyframe message's IMU samples, when the time offset is estimated: the re-timing needs those before
// and after the keyframes, and a keyframe's preintegration from a re-timed one may start before its message's
// first sample. Bounded: the oldest samples go first.
void keepImuHistory(Mapper::State& s, const KeyframeMessage& msg);

// Integrates again the links that the IMU did not cover when they were built (KeyframeData::
// preintegration_incomplete), where the kept samples now do: a positive offset moves the newest keyframe's time
// past the IMU delivered with it, and a keyframe re-timed into the IMU's span can link to the one before it.
void completeImuLinks(Mapper::State& s, const std::vector<PoolHandle>& order);

// kf's preintegration from `previous` over `samples`, linearised at the previous keyframe's bias. False, with kf
// unchanged, when the samples do not cover the interval or leave a gap.
bool integrateImuLink(const Mapper::State& s, const KeyframeData& previous, std::span<const dataset::ImuSample> samples,
                      KeyframeData& kf);

// With the time offset estimated, a keyframe whose previous one was stamped before the first IMU sample (the camera
// ran ahead of the IMU by up to the offset's bound): the link with the first sample held back to the previous
// keyframe, so that the IMU initialisation's chain can start at the map's first keyframe. It stands on unmeasured
// IMU (the caller marks it incomplete): the re-timing at that initialisation integrates it again over the samples
// the images' true times lie between. False when the gap is longer than the bound or there is no history.
bool linkFromBeforeFirstSample(const Mapper::State& s, const KeyframeData& previous, KeyframeData& kf);

// kNotFound while there are too few IMU-linked keyframes, and before imu_init_keyframes while a monocular map's scale
// has not settled or the alignment refuses; other errors when the alignment refuses the motion at the full count.
Status initialiseImu(Mapper::State& s, MapperReport& report);

}  // namespace cvislam::agent
