// What the server sends down, applied to the local map between keyframes (mapper.hpp: Mapper::applyDownlink):
// the covisible map as anchors, and corrections of the agent's own keyframes.
#include <algorithm>
#include <cmath>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "agent_rt/mapping/mapper_state.hpp"
#include "agent_rt/messages/conversions.hpp"

namespace cvislam::agent {

using Eigen::Vector2d;
using Eigen::Vector3d;
using geometry::SE3d;

KeyframeStateMsg Mapper::State::toLocal(const KeyframeStateMsg& c) const {
  KeyframeStateMsg out = c;
  out.T_w_s = toMsg(T_local_server * fromMsg(c.T_w_s));
  out.v_w = toArray(T_local_server.so3() * toVector3(c.v_w));
  return out;
}

std::pair<double, double> Mapper::State::correct(KeyframeData& kf, const KeyframeStateMsg& c) {
  const SE3d T_w_s = fromMsg(c.T_w_s);
  const double step_m = (T_w_s.translation() - kf.T_w_s.translation()).norm();
  const double step_deg = (kf.T_w_s.so3().inverse() * T_w_s.so3()).log().norm() * 180.0 / M_PI;
  kf.T_w_s = T_w_s;
  kf.v_w = toVector3(c.v_w);
  kf.bias = biasFromMsg(c.bias);
  return {step_m, step_deg};
}

void Mapper::State::applyPendingCorrections() {
  if (pending_corrections.empty()) return;
  const std::vector<PoolHandle> own = keyframesBySequence();
  const auto window = static_cast<std::size_t>(options.ba.window);
  for (std::size_t i = 0; i + window < own.size(); ++i) {
    KeyframeData& kf = *map.keyframes().get(own[i]);
    const auto found = pending_corrections.find(kf.id);
    if (found == pending_corrections.end()) continue;
    (void)correct(kf, found->second);
    pending_corrections.erase(found);
  }
}

namespace {

bool overCapacity(const AnchorMessage& msg) {
  return msg.selected_count > kMaxAnchorKeyframesPerMessage || msg.keyframe_count > kMaxAnchorKeyframesPerMessage ||
         msg.keyframe_update_count > kMaxAnchorKeyframesPerMessage || msg.point_count > kMaxAnchorPointsPerMessage ||
         msg.point_update_count > kMaxAnchorPointsPerMessage || msg.correction_count > kMaxAnchorCorrectionsPerMessage;
}

// The agent's own keyframes by id: their handle, and whether they are outside the local BA window.
using OwnKeyframes = std::unordered_map<KeyframeId, std::pair<PoolHandle, bool>>;

OwnKeyframes ownKeyframes(const Mapper::State& s) {
  const std::vector<PoolHandle> own = s.keyframesBySequence();
  const auto window = static_cast<std::size_t>(s.options.ba.window);
  const std::size_t outside = own.size() > window ? own.size() - window : 0;
  OwnKeyframes by_id;
  for (std::size_t i = 0; i < own.size(); ++i) {
    by_id.emplace(s.map.keyframes().get(own[i])->id, std::pair{own[i], i < outside});
  }
  return by_id;
}

// The frame: the newest own keyframe the server corrected keeps its local pose, so T_local_server moves, and what
// came down before (anchors, pending corrections) moves with it.
void followServerFrame(Mapper::State& s, const AnchorMessage& msg, const OwnKeyframes& by_id, DownlinkReport& report) {
  const KeyframeStateMsg* newest = nullptr;
  std::uint64_t newest_sequence = 0;
  for (std::uint16_t i = 0; i < msg.correction_count; ++i) {
    const auto found = by_id.find(msg.corrections[i].id);
    if (found == by_id.end()) continue;
    const std::uint64_t sequence = s.map.keyframes().get(found->second.first)->sequence;
    if (newest == nullptr || sequence > newest_sequence) {
      newest = &msg.corrections[i];
      newest_sequence = sequence;
    }
  }
  if (newest == nullptr) return;
  const KeyframeData& kf = *s.map.keyframes().get(by_id.at(newest->id).first);
  const SE3d T_new = kf.T_w_s * fromMsg(newest->T_w_s).inverse();
  const SE3d change = T_new * s.T_local_server.inverse();
  report.frame_change_m = change.translation().norm();
  s.map.keyframes().forEach([&](PoolHandle, KeyframeData& anchor) {
    if (anchor.anchor) anchor.T_w_s = change * anchor.T_w_s;
  });
  for (auto& [key, pending] : s.pending_corrections) {
    pending.T_w_s = toMsg(change * fromMsg(pending.T_w_s));
    pending.v_w = toArray(change.so3() * toVector3(pending.v_w));
  }
  s.T_local_server = T_new;
}

// Corrections of the agent's own keyframes: those outside the local BA window take the server's state now, those
// in it when they leave it.
void applyCorrections(Mapper::State& s, const AnchorMessage& msg, DownlinkReport& report) {
  const OwnKeyframes by_id = ownKeyframes(s);
  followServerFrame(s, msg, by_id, report);
  for (std::uint16_t i = 0; i < msg.correction_count; ++i) {
    const KeyframeStateMsg c = s.toLocal(msg.corrections[i]);
    const auto found = by_id.find(c.id);
    if (found == by_id.end()) {
      ++report.corrections_skipped;
      continue;
    }
    if (!found->second.second) {
      s.pending_corrections[c.id] = c;
      ++report.corrections_deferred;
      continue;
    }
    s.pending_corrections.erase(c.id);
    const auto [step_m, step_deg] = s.correct(*s.map.keyframes().get(found->second.first), c);
    report.largest_correction_m = std::max(report.largest_correction_m, step_m);
    report.largest_correction_deg = std::max(report.largest_correction_deg, step_deg);
    ++report.corrections_applied;
  }
}

// Why the covisible map cannot be used now; empty when it can.
std::string covisibleSkipReason(const Mapper::State& s, const AnchorMessage& msg, bool ready) {
  if (!s.options.downlink.use_anchors) return "anchors are switched off (downlink.use_anchors)";
  if (!ready) return "the local map's frame is not final yet";
  if (msg.agent_map != s.map_id) {
    return "the covisible map is in agent map " + std::to_string(msg.agent_map) + ", the local map is map " +
           std::to_string(s.map_id);
  }
  return {};
}

// Anchors no longer selected leave (the server sends them again in full when it selects them again); their points
// go with them unless an own keyframe observes them too. Returns every keyframe still held, by id.
std::unordered_map<KeyframeId, PoolHandle> releaseUnselected(Mapper::State& s,
                                                             const std::unordered_set<KeyframeId>& selected,
                                                             DownlinkReport& report) {
  std::unordered_map<KeyframeId, PoolHandle> keyframe_by_id;
  std::vector<PoolHandle> released;
  s.map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (kf.anchor && selected.count(kf.id) == 0) {
      released.push_back(h);
    } else {
      keyframe_by_id.emplace(kf.id, h);
    }
  });
  for (PoolHandle h : released) {
    if (s.map.removeKeyframe(h, MapEventReason::kEvicted).ok()) ++report.anchors_released;
  }
  return keyframe_by_id;
}

// Moves a server point to p_w, kept as a bearing and inverse distance in its reference camera; false when the
// position is behind that camera or not finite.
bool setPointPosition(Mapper::State& s, PoolHandle h, const Vector3d& p_w) {
  MapPointData& p = *s.map.mapPoints().get(h);
  const KeyframeData* reference = s.map.keyframes().get(p.reference);
  if (reference == nullptr) return false;
  const Vector3d p_c = s.cameraPose(*reference).inverse() * p_w;
  if (!(p_c.z() > 0.0) || !p_c.allFinite()) return false;
  p.bearing_c = p_c.normalized();
  p.inverse_depth = 1.0 / p_c.norm();
  return true;
}

// Updates of the anchors' poses and the server points' positions sent before.
void applyUpdates(Mapper::State& s, const AnchorMessage& msg,
                  const std::unordered_map<KeyframeId, PoolHandle>& keyframe_by_id, DownlinkReport& report) {
  for (std::uint16_t i = 0; i < msg.keyframe_update_count; ++i) {
    const auto found = keyframe_by_id.find(msg.keyframe_updates[i].id);
    KeyframeData* kf = found != keyframe_by_id.end() ? s.map.keyframes().get(found->second) : nullptr;
    if (kf == nullptr || !kf->anchor) {
      ++report.unknown_references;
      continue;
    }
    kf->T_w_s = s.T_local_server * fromMsg(msg.keyframe_updates[i].T_w_c) * s.T_s_c.inverse();
    ++report.anchor_poses_updated;
  }
  s.rebuildPointIndex();
  for (std::uint32_t i = 0; i < msg.point_update_count; ++i) {
    const auto found = s.point_index.find(msg.point_updates[i].id);
    const MapPointData* p = found != s.point_index.end() ? s.map.mapPoints().get(found->second) : nullptr;
    if (p == nullptr || !p->from_server) {  // own points are the agent's to refine
      if (p == nullptr) ++report.unknown_references;
      continue;
    }
    if (setPointPosition(s, found->second, s.T_local_server * toVector3(msg.point_updates[i].p_w))) {
      ++report.points_updated;
    }
  }
}

// An anchor keyframe as the local map keeps it. Local BA reads an anchor's undistorted keypoints (through the
// agent's own pinhole) and their octaves; nothing matches against an anchor's image, so its keypoints carry the
// same pixel.
void fillAnchorKeyframe(Mapper::State& s, const AnchorMessage& msg, const AnchorKeyframeMsg& a, KeyframeData& kf) {
  const dataset::CameraCalibration& cam = s.left.calibration();
  kf.id = a.id;
  kf.t_ns = a.t_ns;
  kf.T_w_s = s.T_local_server * fromMsg(a.T_w_c) * s.T_s_c.inverse();
  kf.v_w.setZero();
  kf.bias = imu::ImuBias();
  kf.anchor = true;
  kf.has_preintegration = false;
  kf.keypoint_count = std::min<std::uint16_t>(a.observation_count, kMaxKeypointsPerKeyframe);
  for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
    const AnchorObservationMsg& o = a.observations[k];
    const double x = o.x;
    const double y = o.y;
    kf.undistorted_px[k] = Vector2d(cam.fx * x + cam.cx, cam.fy * y + cam.cy);
    kf.keypoints[k] = features::Keypoint{kf.undistorted_px[k].cast<float>(), 0.0F, 0.0F, o.octave};
    const auto in_message = s.message_point.find(o.point);
    kf.descriptors[k] =
        in_message != s.message_point.end() ? msg.points[in_message->second].descriptor : features::Descriptor{};
    kf.has_right[k] = false;
  }
}

// The points an inserted anchor observes: linked when held already, made from the message otherwise (within the
// budget of server points).
void linkAnchorPoints(Mapper::State& s, const AnchorMessage& msg, const AnchorKeyframeMsg& a, PoolHandle h,
                      int& server_points, DownlinkReport& report) {
  const SE3d T_c_w = s.cameraPose(*s.map.keyframes().get(h)).inverse();
  const std::uint16_t keypoints = s.map.keyframes().get(h)->keypoint_count;
  for (std::uint16_t k = 0; k < keypoints; ++k) {
    const MapPointId& id = a.observations[k].point;
    if (const auto held = s.point_index.find(id); held != s.point_index.end()) {
      if (s.map.addObservation(h, k, held->second).ok()) ++report.points_linked;
      continue;
    }
    const auto in_message = s.message_point.find(id);
    if (in_message == s.message_point.end()) {
      ++report.unknown_references;
      continue;
    }
    if (server_points >= s.options.downlink.max_anchor_points) {
      ++report.points_over_capacity;
      continue;
    }
    const AnchorPointMsg& m = msg.points[in_message->second];
    const Vector3d p_c = T_c_w * (s.T_local_server * toVector3(m.p_w));
    if (!(p_c.z() > 0.0)) {
      ++report.unknown_references;
      continue;
    }
    auto created = s.map.createMapPoint(h, k, p_c.normalized(), p_c.norm(), id);
    if (!created) {
      ++report.points_over_capacity;
      continue;
    }
    MapPointData& p = *s.map.mapPoints().get(*created);
    p.from_server = true;
    p.descriptor = m.descriptor;
    p.octave = m.octave;
    s.point_index.emplace(id, *created);
    ++server_points;
    ++report.points_added;
  }
}

// New anchor keyframes, in the server's rank order, with the points they observe; returns the anchors held.
int addAnchors(Mapper::State& s, const AnchorMessage& msg, const std::unordered_set<KeyframeId>& selected,
               std::unordered_map<KeyframeId, PoolHandle>& keyframe_by_id, DownlinkReport& report) {
  s.message_point.clear();
  for (std::uint32_t i = 0; i < msg.point_count; ++i) s.message_point.emplace(msg.points[i].id, i);
  int anchors = s.anchorCount();
  int server_points = 0;
  s.map.mapPoints().forEach([&](PoolHandle, const MapPointData& p) { server_points += p.from_server ? 1 : 0; });
  for (std::uint16_t i = 0; i < msg.keyframe_count; ++i) {
    const AnchorKeyframeMsg& a = msg.keyframes[i];
    if (selected.count(a.id) == 0) continue;        // not selected now: of no use
    if (keyframe_by_id.count(a.id) != 0) continue;  // held already (sent twice, or one of the own)
    if (anchors >= s.options.downlink.max_anchor_keyframes) {
      ++report.anchors_over_capacity;
      continue;
    }
    fillAnchorKeyframe(s, msg, a, s.scratch);
    auto inserted = s.map.insertKeyframe(s.scratch);
    if (!inserted) {
      ++report.anchors_over_capacity;
      continue;
    }
    keyframe_by_id.emplace(a.id, *inserted);
    ++anchors;
    ++report.anchors_added;
    linkAnchorPoints(s, msg, a, *inserted, server_points, report);
  }
  return anchors;
}

}  // namespace

Result<DownlinkReport> Mapper::applyDownlink(const AnchorMessage& msg) {
  State& s = *s_;
  DownlinkReport report;
  // Within a stream, messages apply in order; a new stream (a reconnection) starts its sequences again.
  if (s.downlink_seen &&
      (msg.stream < s.downlink_stream || (msg.stream == s.downlink_stream && msg.sequence <= s.downlink_sequence))) {
    report.stale = true;
    report.anchors_held = s.anchorCount();
    return report;
  }
  if (overCapacity(msg)) return Error{ErrorCode::kDataError, "downlink message over the message's capacities: refused"};
  s.downlink_seen = true;
  s.downlink_stream = msg.stream;
  s.downlink_sequence = msg.sequence;
  const bool ready = s.frameFinal();
  if (ready && s.options.downlink.apply_corrections && msg.correction_count > 0) {
    applyCorrections(s, msg, report);
  } else {
    report.corrections_skipped = msg.correction_count;
  }
  if (msg.has_covisible != 0) report.skipped = covisibleSkipReason(s, msg, ready);
  if (msg.has_covisible == 0 || !report.skipped.empty()) {
    report.anchors_held = s.anchorCount();
    return report;
  }
  const std::unordered_set<KeyframeId> selected(msg.selected.begin(), msg.selected.begin() + msg.selected_count);
  std::unordered_map<KeyframeId, PoolHandle> keyframe_by_id = releaseUnselected(s, selected, report);
  applyUpdates(s, msg, keyframe_by_id, report);
  report.anchors_held = addAnchors(s, msg, selected, keyframe_by_id, report);
  return report;
}

}  // namespace cvislam::agent
