// The window of tracking's motion-only visual-inertial BA (paper IV-C) and the IMU it needs. Tracking records the
// preintegrated IMU between consecutive keyframes it publishes; for each frame it then assembles the window from
// mapping's newest snapshot: the snapshot's newest keyframes whose IMU links are still held, chained, and the
// keyframe tracking published last if mapping has not returned it yet. Fixed-size storage: nothing allocates.
#pragma once

#include <array>
#include <cstddef>
#include <span>

#include <Eigen/Core>

#include "agent_rt/messages/messages.hpp"
#include "agent_rt/tracking/inertial_pose_optimizer.hpp"
#include "common/core/ids.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

// The keyframe tracking published last, as tracking holds it.
struct NewestPublishedKeyframe {
  KeyframeId id;
  std::int64_t t_ns = 0;  // its state's time; mapping moves it when it re-times keyframes to the time offset
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
};

class MotionWindowBuilder {
 public:
  // The IMU from keyframe `from` to keyframe `to`, both published by tracking; the oldest link is overwritten.
  void addLink(const KeyframeId& from, const KeyframeId& to, const imu::Preintegration& preintegration);

  // The window for a frame, oldest first, over at most n keyframes: each keyframe with its IMU to the next, the
  // last with `to_frame` (the IMU from `newest` to the frame). The first keyframe is held, so its observations
  // are left out. Shorter than 2 (n = 1, no snapshot, or a broken chain): the caller holds `newest` alone.
  // Valid until the next call.
  std::span<MotionWindowKeyframe> build(const MapSnapshotMessage* map, int n, const NewestPublishedKeyframe& newest,
                                        const imu::Preintegration& to_frame);

 private:
  struct ImuLink {
    KeyframeId from;
    KeyframeId to;
    imu::Preintegration preintegration;
    bool valid = false;
  };
  const ImuLink* findLink(const KeyframeId& from, const KeyframeId& to) const;

  std::array<ImuLink, kMaxMotionWindowKeyframes + 1> links_{};
  std::size_t links_next_ = 0;
  std::array<MotionWindowKeyframe, kMaxMotionWindowKeyframes> window_{};
  std::array<std::array<PoseObservation, kMaxKeypointsPerKeyframe>, kMaxMotionBaKeyframes> observations_{};
  std::array<std::array<std::uint8_t, kMaxKeypointsPerKeyframe>, kMaxMotionBaKeyframes> outliers_{};
};

}  // namespace cvislam::agent
