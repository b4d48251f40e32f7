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

void Tracker::State::retimeNewestKeyframe(std::int64_t t_ns) {
  keyframe.t_ns = t_ns;
  keyframe_imu_first = std::min(keyframe_imu_first, lastImuAtOrBefore(t_ns));
  pre_keyframe.reset(bias);
  pre_keyframe_end_ns = t_ns;
  if (!imu_ok_since_keyframe || last_t_ns <= t_ns) return;  // the next frame integrates from t_ns
  for (std::uint32_t i = 0; i < keyframe_imu_count; ++i) imu_scratch[i] = fromMsg(keyframe_imu[i]);
  const std::span<const dataset::ImuSample> samples(imu_scratch.data(), keyframe_imu_count);
  if (pre_keyframe.integrateInterval(samples, t_ns, last_t_ns).ok()) {
    pre_keyframe_end_ns = last_t_ns;
  } else {
    imu_ok_since_keyframe = false;  // no IMU kept from that far back: the frames go without it to the next keyframe
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
      if (newest->t_ns != keyframe.t_ns) {
        bias = bias_new;
        retimeNewestKeyframe(newest->t_ns);
      }
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

std::int64_t Tracker::State::nextTimeCorrectionNs() {
  const std::int64_t max_back_ns = camera_interval_ns > 0 ? camera_interval_ns / 2 : kMaxTimeCorrectionStepBackNs;
  time_correction_ns += std::max(time_correction_target_ns - time_correction_ns, -max_back_ns);
  return time_correction_ns;
}

std::int64_t Tracker::timeCorrectionForNextFrameNs() {
  return s_->nextTimeCorrectionNs();
}

}  // namespace cvislam::agent
