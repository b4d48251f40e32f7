#include "agent_rt/runtime/trajectory_recorder.hpp"

#include <algorithm>

#include "agent_rt/messages/conversions.hpp"

namespace cvislam::agent {

using geometry::SE3d;

TrajectoryRecorder::TrajectoryRecorder(std::size_t frames, bool uses_imu) : uses_imu_(uses_imu) {
  frames_.reserve(frames);
  keyframes_.resize(frames + 1);
}

bool TrajectoryRecorder::addFrame(std::int64_t t_ns, std::int64_t time_correction_ns, const FrameResult& r) {
  const bool before_initialisation = uses_imu_ && !r.imu_initialised;
  // Noted even when the room is full (a long live run): the summary's time does not depend on what was kept.
  if (r.tracked && !before_initialisation && first_initialised_t_ns_ < 0) first_initialised_t_ns_ = t_ns;
  if (frames_.size() == frames_.capacity()) return false;
  frames_.push_back({t_ns, time_correction_ns, r.T_w_s, r.T_ref_s, r.has_reference ? r.reference.counter : 0U,
                     r.has_reference, r.tracked, r.keyframe, before_initialisation, r.map_id, r.map_epoch});
  return true;
}

void TrajectoryRecorder::addSnapshot(const MapSnapshotMessage& s) {
  if (s.map_id == map_id_ && s.map_epoch == epoch_ + 1) {
    // The world frame changed (IMU initialisation): move what was recorded in the old one.
    const SE3d T = fromMsg(s.epoch_transform);
    const double scale = s.epoch_scale;
    for (Keyframe& kf : keyframes_) {
      if (kf.valid && kf.map_id == s.map_id && kf.epoch == epoch_) {
        kf.T_w_s = SE3d(T.so3() * kf.T_w_s.so3(), scale * (T.so3() * kf.T_w_s.translation()) + T.translation());
        kf.epoch = s.map_epoch;
        // Re-timed to the time offset estimated at this change, as mapping re-times the keyframes it holds: a pose
        // from before the IMU is the camera's when the image was taken. (Those mapping holds are overwritten
        // below with what it made of them.)
        kf.t_ns += s.time_correction_ns - kf.time_correction_ns;
        kf.time_correction_ns = s.time_correction_ns;
      }
    }
    for (Frame& f : frames_) {
      if (f.map_id == s.map_id && f.epoch == epoch_) {
        f.T_ref_s.translation() *= scale;
        f.T_w_s = SE3d(T.so3() * f.T_w_s.so3(), scale * (T.so3() * f.T_w_s.translation()) + T.translation());
        f.epoch = s.map_epoch;
      }
    }
  }
  map_id_ = s.map_id;
  epoch_ = s.map_epoch;
  for (std::uint16_t i = 0; i < s.keyframe_count; ++i) {
    const KeyframeStateMsg& m = s.keyframes[i];
    if (s.keyframe_is_anchor[i] != 0) continue;  // the server's: not one of this agent's keyframes to record
    if (m.id.counter >= keyframes_.size()) continue;
    Keyframe& kf = keyframes_[m.id.counter];
    kf = {true, m.t_ns, m.time_correction_ns, fromMsg(m.T_w_s), s.map_id, s.map_epoch};
  }
}

void TrajectoryRecorder::build(dataset::Trajectory& refined, dataset::Trajectory& online,
                               dataset::Trajectory& keyframes) const {
  for (const Frame& f : frames_) {
    const bool refinable = f.has_reference && f.reference < keyframes_.size() && keyframes_[f.reference].valid &&
                           keyframes_[f.reference].map_id == f.map_id && keyframes_[f.reference].epoch == f.epoch;
    // Tracked frames, and keyframes made before the map existed once mapping has placed them (a monocular
    // start drops the keyframes between its two views: those are left out).
    if (!f.tracked && !(f.keyframe && refinable)) continue;
    online.push_back({f.t_ns, f.T_w_s, f.before_initialisation});
    if (!refinable) {
      refined.push_back({f.t_ns, f.T_w_s, f.before_initialisation});
      continue;
    }
    // Tracking placed the frame against its keyframe image to image, so hung from the keyframe's state the
    // frame's pose is the one at the time its image carries on the keyframe's clock: the camera's stamp plus
    // the keyframe's time correction. The two differ for frames tracked before the time offset was estimated
    // (or while the frames' correction was still catching up) whose keyframe mapping has re-timed since.
    const Keyframe& kf = keyframes_[f.reference];
    refined.push_back(
        {f.t_ns - f.time_correction_ns + kf.time_correction_ns, kf.T_w_s * f.T_ref_s, f.before_initialisation});
  }
  std::sort(refined.begin(), refined.end(), [](const auto& a, const auto& b) { return a.t_ns < b.t_ns; });
  for (const Keyframe& kf : keyframes_) {
    if (kf.valid) keyframes.push_back({kf.t_ns, kf.T_w_s});
  }
  std::sort(keyframes.begin(), keyframes.end(), [](const auto& a, const auto& b) { return a.t_ns < b.t_ns; });
}

}  // namespace cvislam::agent
