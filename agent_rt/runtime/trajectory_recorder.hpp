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
  // `uses_imu`: frames tracked before the IMU initialisation are marked (StampedPose::before_initialisation) in
  // both frame trajectories; their world frame was not final (in mono, not even its scale).
  TrajectoryRecorder(std::size_t frames, bool uses_imu);

  // False when the reserved room is full: the frame is not recorded.
  // `time_correction_ns`: the time-offset correction the frame's time carries.
  bool addFrame(std::int64_t t_ns, std::int64_t time_correction_ns, const FrameResult& r);
  // The keyframes' refined states; a change of world frame (map_epoch + 1) moves what was recorded before it.
  void addSnapshot(const MapSnapshotMessage& s);
  // The trajectory of tracked frames with every frame hung from its keyframe's newest pose, the trajectory
  // as tracked live, and the keyframe trajectory.
  void build(dataset::Trajectory& refined, dataset::Trajectory& online, dataset::Trajectory& keyframes) const;
  // The time of the first frame tracked in a final world frame (with the IMU: once it is initialised); -1 none.
  [[nodiscard]] std::int64_t firstInitialisedFrameTns() const { return first_initialised_t_ns_; }

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
    bool before_initialisation;
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
  bool uses_imu_ = true;
  std::int64_t first_initialised_t_ns_ = -1;
};

}  // namespace cvislam::agent
