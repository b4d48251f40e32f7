#include "agent_rt/mapping/map_delta_writer.hpp"

#include <algorithm>

#include "agent_rt/messages/conversions.hpp"

namespace cvislam::agent {

KeyframeStateMsg toStateMsg(const KeyframeData& kf) {
  KeyframeStateMsg m;
  m.id = kf.id;
  m.t_ns = kf.t_ns;
  m.time_correction_ns = kf.time_correction_ns;
  m.T_w_s = toMsg(kf.T_w_s);
  m.v_w = toArray(kf.v_w);
  m.bias = toMsg(kf.bias);
  return m;
}

MapDeltaWriter::MapDeltaWriter() {
  created_.reserve(kMaxMapEventsPerKeyframe);
}

void MapDeltaWriter::start(MapDeltaMessage& delta) {
  delta_ = &delta;
  delta.event_count = 0;
  delta.events_lost = 0;
}

void MapDeltaWriter::record(const MapEvent& event) {
  if (delta_->event_count < delta_->events.size()) {
    delta_->events[delta_->event_count++] = event;
  } else {
    ++delta_->events_lost;
  }
}

void MapDeltaWriter::finish(const LocalMap& map, const KeyframeMessage& msg, const MapFrame& frame, KeyframePart part) {
  MapDeltaMessage& delta = *delta_;
  delta.map_id = frame.map_id;
  delta.map_epoch = frame.epoch;
  delta.ready = frame.ready ? 1 : 0;
  delta.t_ns = msg.state.t_ns;
  delta.has_keyframe = 0;
  delta.keyframe_before_local_ba = 0;
  delta.keypoint_count = 0;
  delta.imu_count = 0;
  delta.keyframe_count = 0;
  map.keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
    if (kf.anchor) return;  // the server's, not this agent's to send
    KeyframeStateMsg& m = delta.keyframes[delta.keyframe_count++];
    m = toStateMsg(kf);
    if (part == KeyframePart::kStateOnly || !(kf.id == msg.state.id)) return;
    // The keyframe just processed, in full, with its links as they are now.
    delta.has_keyframe = 1;
    delta.keyframe_before_local_ba = part == KeyframePart::kBeforeLocalBa ? 1 : 0;
    delta.keyframe_map_id = frame.keyframe_map_id;
    delta.keyframe = m;
    delta.has_imu_link = kf.has_preintegration ? 1 : 0;
    delta.imu_from = kf.preintegration_from;
    delta.keypoint_count = kf.keypoint_count;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      delta.keypoints[k] = msg.keypoints[k];
      delta.descriptors[k] = kf.descriptors[k];
      delta.has_right[k] = kf.has_right[k] ? 1 : 0;
      delta.right_px[k] = {static_cast<float>(kf.right_undistorted_px[k].x()),
                           static_cast<float>(kf.right_undistorted_px[k].y())};
      delta.right_octave[k] = kf.right_octave[k];
      const MapPointData* p = kf.has_map_point[k] ? map.mapPoints().get(kf.map_point[k]) : nullptr;
      if (p != nullptr && p->from_server) p = nullptr;
      delta.has_observation[k] = p != nullptr ? 1 : 0;
      if (p != nullptr) delta.observation[k] = p->id;
    }
    delta.imu_count = std::min<std::uint32_t>(msg.imu_count, static_cast<std::uint32_t>(delta.imu.size()));
    std::copy_n(msg.imu.begin(), delta.imu_count, delta.imu.begin());
  });
  // Points made with this keyframe, found among all points while their positions are written.
  created_.clear();
  for (std::uint16_t i = 0; i < delta.event_count; ++i) {
    if (delta.events[i].type == MapEventType::kPointCreated) created_.push_back(delta.events[i].point);
  }
  std::sort(created_.begin(), created_.end());
  delta.point_count = 0;
  delta.new_point_count = 0;
  map.mapPoints().forEach([&](PoolHandle h, const MapPointData& p) {
    if (p.from_server) return;
    const auto p_w = map.pointInWorld(h);
    if (!p_w || !p_w->allFinite()) return;
    const std::array<float, 3> position{static_cast<float>(p_w->x()), static_cast<float>(p_w->y()),
                                        static_cast<float>(p_w->z())};
    delta.points[delta.point_count++] = {p.id, position};
    if (!std::binary_search(created_.begin(), created_.end(), p.id)) return;
    if (delta.new_point_count >= delta.new_points.size()) return;
    const KeyframeData* reference = map.keyframes().get(p.reference);
    if (reference == nullptr) return;
    NewPointMsg& n = delta.new_points[delta.new_point_count++];
    n.id = p.id;
    n.reference = reference->id;
    n.p_w = position;
    n.descriptor = p.descriptor;
    n.octave = p.octave;
  });
}

}  // namespace cvislam::agent
