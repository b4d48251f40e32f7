// Taking mapping's snapshots: the map tracking matches against, the world frame (a new map, or the change of frame
// at the IMU initialisation), and the refined newest keyframe, onto which tracking's own states are moved.
#include "agent_rt/tracking/tracker_state.hpp"

namespace cvislam::agent {

using geometry::SE3d;

void Tracker::State::applyToTrackedStates(const SE3d& delta_left) {
  T_w_s = delta_left * T_w_s;
  v_w = delta_left.so3() * v_w;
}

void Tracker::State::changeEpoch(const MapSnapshotMessage& s) {
  const double scale = s.epoch_scale;
  const SE3d T = fromMsg(s.epoch_transform);
  auto apply = [&](SE3d& pose) {
    pose = SE3d(T.so3() * pose.so3(), scale * (T.so3() * pose.translation()) + T.translation());
  };
  apply(T_w_s);
  v_w = scale * (T.so3() * v_w);
  apply(keyframe.T_w_s);
  keyframe.v_w = scale * (T.so3() * keyframe.v_w);
  for (Published& p : published) {
    if (p.valid) apply(p.T_w_s);
  }
}

Tracker::State::Published* Tracker::State::findPublished(const KeyframeId& id) {
  for (Published& p : published) {
    if (p.valid && p.id == id) return &p;
  }
  return nullptr;
}

void Tracker::State::adopt(const MapSnapshotMessage* s) {
  if (s == nullptr) return;
  backlog.taken(s->keyframes_taken);
  if (s->map_id != map_id || new_map_requested) {
    if (s->map_id < map_id || (new_map_requested && s->map_id < requested_map_id)) return;  // an old map's
    if (s->point_count == 0) {
      // Mapping has started this map (on request, or itself after a failed monocular IMU initialisation)
      // but not built it yet: keep feeding it keyframes.
      if (!new_map_requested || s->map_id > requested_map_id) {
        status = TrackingStatus::kWaitingForMap;
        new_map_requested = true;
        requested_map_id = s->map_id;
        imu_initialised = false;
      }
      map_id = s->map_id;
      snapshot = s;
      if (awaiting && awaiting_id == s->newest_keyframe) awaiting = false;
      return;
    }
    map_id = s->map_id;
    epoch = s->map_epoch;
    new_map_requested = false;
    status = TrackingStatus::kTracking;
    lost_frames = 0;
    waiting_frames = 0;
  } else if (s->map_epoch != epoch) {
    if (s->map_epoch == epoch + 1) {
      changeEpoch(*s);
    } else {
      status = TrackingStatus::kRelocalising;  // missed a change of frame: find the map again
    }
    epoch = s->map_epoch;
  }
  imu_initialised = s->imu_initialised != 0;
  time_correction_target_ns = s->time_correction_ns;
  snapshot = s;

  const KeyframeStateMsg* newest = nullptr;
  for (std::uint16_t i = 0; i < s->keyframe_count; ++i) {
    if (s->keyframes[i].id == s->newest_keyframe) newest = &s->keyframes[i];
  }
  if (newest == nullptr) return;
  const SE3d T_new = fromMsg(newest->T_w_s);
  const imu::ImuBias bias_new = biasFromMsg(newest->bias);
  Published* entry = findPublished(newest->id);
  if (entry != nullptr) {
    const SE3d delta = T_new * entry->T_w_s.inverse();
    applyToTrackedStates(delta);
    for (Published& p : published) {
      if (p.valid && p.id.counter > newest->id.counter) p.T_w_s = delta * p.T_w_s;
    }
    entry->T_w_s = T_new;
    if (has_keyframe && keyframe.id == newest->id) {
      keyframe.T_w_s = T_new;
      keyframe.v_w = toVector3(newest->v_w);
      keyframe.bias = bias_new;
    } else if (has_keyframe) {
      keyframe.T_w_s = delta * keyframe.T_w_s;
      keyframe.v_w = delta.so3() * keyframe.v_w;
    }
  }
  bias = bias_new;
  if (awaiting && awaiting_id == newest->id) awaiting = false;
}

void Tracker::adoptSnapshot(const MapSnapshotMessage* snapshot) {
  s_->adopt(snapshot);
}

std::int64_t Tracker::timeCorrectionForNextFrameNs() {
  State& s = *s_;
  s.time_correction_ns += std::clamp(s.time_correction_target_ns - s.time_correction_ns, -kMaxTimeCorrectionStepNs,
                                     kMaxTimeCorrectionStepNs);
  return s.time_correction_ns;
}

}  // namespace cvislam::agent
