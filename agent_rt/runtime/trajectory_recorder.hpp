// What the agent writes as trajectories: every frame's result and the newest refined pose of every keyframe,
// moved along when the world frame changes (IMU initialisation), and at the end the trajectories built from them.
// Tracking's thread owns it; memory is reserved for the sequence's frames at construction.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "agent_rt/messages/messages.hpp"
#include "agent_rt/tracking/tracker.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::agent {

class TrajectoryRecorder {
 public:
  explicit TrajectoryRecorder(std::size_t frames);

  // False when the reserved room is full: the frame is not recorded.
  // `time_correction_ns`: the time-offset correction the frame's time carries.
  bool addFrame(std::int64_t t_ns, std::int64_t time_correction_ns, const FrameResult& r);
  // The keyframes' refined states; a change of world frame (map_epoch + 1) moves what was recorded before it.
  void addSnapshot(const MapSnapshotMessage& s);
  // The trajectory of tracked frames with every frame hung from its keyframe's newest pose, the trajectory
  // as tracked live, and the keyframe trajectory.
  void build(dataset::Trajectory& refined, dataset::Trajectory& online, dataset::Trajectory& keyframes) const;

 private:
  struct Frame {
    std::int64_t t_ns;
    std::int64_t time_correction_ns;
    geometry::SE3d T_w_s;
    geometry::SE3d T_ref_s;
    std::uint32_t reference;
    bool has_reference;
    bool tracked;
    bool keyframe;
    std::uint32_t map_id;
    std::uint32_t epoch;
  };
  struct Keyframe {
    bool valid = false;
    std::int64_t t_ns = 0;
    std::int64_t time_correction_ns = 0;
    geometry::SE3d T_w_s;
    std::uint32_t map_id = 0;
    std::uint32_t epoch = 0;
  };
  std::vector<Frame> frames_;
  std::vector<Keyframe> keyframes_;
  std::uint32_t map_id_ = 0;
  std::uint32_t epoch_ = 0;
};

}  // namespace cvislam::agent
