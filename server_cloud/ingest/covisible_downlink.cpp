#include "server_cloud/ingest/covisible_downlink.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <string>
#include <unordered_set>

#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::server {
namespace {

Status invalid(const std::string& what) {
  return Error{ErrorCode::kInvalidArgument, "covisible downlink: " + what};
}

bool movedBeyond(const geometry::SE3d& a, const geometry::SE3d& b, const CovisibleOptions& options) {
  const double rotation_deg = (a.so3().inverse() * b.so3()).log().norm() * 180.0 / std::numbers::pi;
  return (a.translation() - b.translation()).norm() > options.update_translation_m ||
         rotation_deg > options.update_rotation_deg;
}

void setPoint(const MapPointId& id, const Eigen::Vector3d& p_w, const ServerMapPoint& point, v1::CovisiblePoint* out) {
  out->set_agent(id.agent);
  out->set_counter(id.counter);
  for (int i = 0; i < 3; ++i) out->add_p_w(static_cast<float>(p_w[i]));
  wire::packDescriptor(point.descriptor.data(), out->mutable_orb());
  out->set_octave(point.octave);
}

}  // namespace

Status CovisibleOptions::validate() const {
  if (keyframes < 1 || keyframes > wire::kMaxCovisibleKeyframesPerMessage) {
    return invalid("keyframes must be in [1, " + std::to_string(wire::kMaxCovisibleKeyframesPerMessage) +
                   "] (what an agent takes per message)");
  }
  if (seed_keyframes < 1) return invalid("seed_keyframes must be >= 1");
  if (own_recent_excluded < 0) return invalid("own_recent_excluded must be >= 0");
  if (budget_bytes < 1024) return invalid("budget_bytes must be >= 1024");
  if (!std::isfinite(update_translation_m) || update_translation_m < 0.0 || !std::isfinite(update_rotation_deg) ||
      update_rotation_deg < 0.0) {
    return invalid("update thresholds must be finite and >= 0");
  }
  return Status::Ok();
}

CovisibleCameras covisibleCameras(const Mission& mission) {
  CovisibleCameras out;
  for (const auto& [id, sensors] : mission.sensors()) {
    const dataset::CameraCalibration& c = sensors->cam0.calibration();
    out.emplace(id, CovisibleCamera{c.fx, c.fy, c.cx, c.cy, sensors->T_s_c0});
  }
  return out;
}

std::vector<std::pair<KeyframeId, int>> selectCovisible(const MapContent& content, const std::vector<KeyframeId>& seeds,
                                                        const CovisibleOptions& options) {
  std::vector<std::pair<KeyframeId, int>> out;
  if (seeds.empty()) return out;
  const KeyframeId newest = seeds.front();
  const auto isRecentOwn = [&](const KeyframeId& id) {
    return id.agent == newest.agent && static_cast<std::int64_t>(id.counter) >
                                           static_cast<std::int64_t>(newest.counter) - options.own_recent_excluded;
  };
  std::unordered_map<KeyframeId, int> weight;
  for (std::size_t i = 0; i < seeds.size() && i < static_cast<std::size_t>(options.seed_keyframes); ++i) {
    if (content.keyframe(seeds[i]) == nullptr) continue;
    for (const auto& [other, shared] : content.covisible(seeds[i])) {
      if (isRecentOwn(other)) continue;
      const ServerKeyframe* kf = content.keyframe(other);
      // A pose graph's move waits for the GBA after it; a keyframe sent before its local BA, for its update.
      if (kf == nullptr || kf->provisional || kf->awaiting_local_ba) continue;
      if (options.foreign_refined_only && other.agent != newest.agent && !kf->refined) continue;
      if (std::find(seeds.begin(), seeds.end(), other) != seeds.end()) continue;
      weight[other] += shared;
    }
  }
  out.assign(weight.begin(), weight.end());
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) {
    if (a.second != b.second) return a.second > b.second;
    return a.first < b.first;  // a stable order between equal weights
  });
  if (out.size() > static_cast<std::size_t>(options.keyframes)) out.resize(static_cast<std::size_t>(options.keyframes));
  return out;
}

namespace {

const CovisibleCamera* cameraOf(const CovisibleCameras& cameras, AgentId agent) {
  const auto it = cameras.find(agent);
  return it == cameras.end() ? nullptr : &it->second;
}

// A keyframe as the agent gets it: its camera pose in the agent's map, and the keypoints that observe a map
// point, on an ideal pinhole of unit focal length (any agent's camera can take them from there). The points
// among them that the stream has not carried yet are appended to `new_points`, once each.
v1::CovisibleKeyframe describeKeyframe(const MapContent& content, const KeyframeId& id, const ServerKeyframe& kf,
                                       const CovisibleCamera& camera, const geometry::SE3d& T_w_c,
                                       const std::unordered_map<MapPointId, Eigen::Vector3d>& points_sent,
                                       std::vector<const ServerMapPoint*>& new_points) {
  v1::CovisibleKeyframe keyframe;
  keyframe.set_agent(id.agent);
  keyframe.set_counter(id.counter);
  keyframe.set_t_ns(kf.t_ns);
  wire::toProto(T_w_c, keyframe.mutable_t_w_c());
  std::string octaves;
  for (std::size_t k = 0; k < kf.point.size() && k < kf.keypoints.size(); ++k) {
    if (k >= kf.has_point.size() || kf.has_point[k] == 0) continue;
    const ServerMapPoint* point = content.point(kf.point[k]);
    if (point == nullptr) continue;
    const Eigen::Vector2d px = k < kf.keypoints_undistorted.size()
                                   ? kf.keypoints_undistorted[k].cast<double>()
                                   : kf.keypoints[k].px.cast<double>();  // no distortion recorded (tests)
    keyframe.add_xy(static_cast<float>((px.x() - camera.cx) / camera.fx));
    keyframe.add_xy(static_cast<float>((px.y() - camera.cy) / camera.fy));
    keyframe.add_point_agent(point->id.agent);
    keyframe.add_point_counter(point->id.counter);
    octaves.push_back(static_cast<char>(kf.keypoints[k].octave));
    if (points_sent.count(point->id) == 0 &&
        std::find(new_points.begin(), new_points.end(), point) == new_points.end()) {
      new_points.push_back(point);
    }
  }
  keyframe.set_octave(std::move(octaves));
  return keyframe;
}

}  // namespace

CovisibleReport CovisibleSender::fill(const MapContent& content, const std::vector<KeyframeId>& seeds,
                                      std::uint32_t agent_map, const geometry::SE3d& T_w_m,
                                      const CovisibleCameras& cameras, v1::CovisibleMap& out,
                                      std::uint32_t local_map_keyframes) {
  CovisibleReport report;
  out.Clear();
  if (!options_.enabled) return report;
  if (!started_ || agent_map != agent_map_) {
    // A new agent map has a new world frame: what was sent in the old one is of no use to the agent there.
    keyframes_sent_.clear();
    points_sent_.clear();
    last_selection_.clear();
    agent_map_ = agent_map;
    started_ = true;
  }
  CovisibleOptions options = options_;
  if (local_map_keyframes > 0)
    options.own_recent_excluded = static_cast<int>(std::min<std::uint32_t>(local_map_keyframes, 100000));
  const std::vector<std::pair<KeyframeId, int>> ranked = selectCovisible(content, seeds, options);
  std::vector<KeyframeId> selection;
  selection.reserve(ranked.size());
  for (const auto& [id, weight] : ranked) selection.push_back(id);

  releaseUnselected(content, selection);
  out.set_agent_map(agent_map);
  for (const KeyframeId& id : selection) {
    out.add_selected_agent(id.agent);
    out.add_selected_counter(id.counter);
  }
  report.selected = static_cast<int>(selection.size());
  addUpdates(content, selection, T_w_m, cameras, out, report);
  addNewKeyframes(content, selection, T_w_m, cameras, out, report);

  const bool same_selection = selection == last_selection_;
  last_selection_ = std::move(selection);
  if (!report.carriesData() && same_selection) out.Clear();  // nothing new to say
  return report;
}

// The agent holds only the selected keyframes it has received (and lets go of the rest): a keyframe that left
// the selection is forgotten here, to be sent in full again if it is selected again, and so are the points
// that no keyframe still held observes.
void CovisibleSender::releaseUnselected(const MapContent& content, const std::vector<KeyframeId>& selection) {
  bool released = false;
  for (auto it = keyframes_sent_.begin(); it != keyframes_sent_.end();) {
    if (std::find(selection.begin(), selection.end(), it->first) == selection.end()) {
      it = keyframes_sent_.erase(it);
      released = true;
    } else {
      ++it;
    }
  }
  if (!released) return;
  std::unordered_set<MapPointId> held;
  for (const auto& [id, T_w_c] : keyframes_sent_) {
    const ServerKeyframe* kf = content.keyframe(id);
    if (kf == nullptr) continue;
    for (std::size_t k = 0; k < kf->point.size() && k < kf->has_point.size(); ++k) {
      if (kf->has_point[k] != 0) held.insert(kf->point[k]);
    }
  }
  for (auto it = points_sent_.begin(); it != points_sent_.end();) {
    it = held.count(it->first) == 0 ? points_sent_.erase(it) : std::next(it);
  }
}

void CovisibleSender::addUpdates(const MapContent& content, const std::vector<KeyframeId>& selection,
                                 const geometry::SE3d& T_w_m, const CovisibleCameras& cameras, v1::CovisibleMap& out,
                                 CovisibleReport& report) {
  for (const KeyframeId& id : selection) {
    const auto sent = keyframes_sent_.find(id);
    if (sent == keyframes_sent_.end()) continue;
    const ServerKeyframe* kf = content.keyframe(id);
    const CovisibleCamera* camera = cameraOf(cameras, id.agent);
    // A pose graph's move waits for the GBA after it: the agent keeps the state it holds until then.
    if (kf == nullptr || camera == nullptr || kf->provisional) continue;
    const geometry::SE3d T_w_c = T_w_m * kf->T_w_s * camera->T_s_c;
    if (movedBeyond(sent->second, T_w_c, options_)) {
      v1::CovisiblePose* update = out.add_keyframe_updates();
      update->set_agent(id.agent);
      update->set_counter(id.counter);
      wire::toProto(T_w_c, update->mutable_t_w_c());
      ++report.keyframe_updates;
      sent->second = T_w_c;
    }
    for (std::size_t k = 0; k < kf->point.size(); ++k) {
      if (report.point_updates >= wire::kMaxCovisiblePointsPerMessage) break;  // the rest in the next message
      if (k >= kf->has_point.size() || kf->has_point[k] == 0) continue;
      const auto point_sent = points_sent_.find(kf->point[k]);
      if (point_sent == points_sent_.end()) continue;
      const ServerMapPoint* point = content.point(kf->point[k]);
      if (point == nullptr) continue;
      const Eigen::Vector3d p_w = T_w_m * point->p_w;
      if ((p_w - point_sent->second).norm() <= options_.update_translation_m) continue;
      out.add_point_update_agent(point->id.agent);
      out.add_point_update_counter(point->id.counter);
      for (int i = 0; i < 3; ++i) out.add_point_update_p_w(static_cast<float>(p_w[i]));
      ++report.point_updates;
      point_sent->second = p_w;
    }
  }
}

void CovisibleSender::addNewKeyframes(const MapContent& content, const std::vector<KeyframeId>& selection,
                                      const geometry::SE3d& T_w_m, const CovisibleCameras& cameras,
                                      v1::CovisibleMap& out, CovisibleReport& report) {
  std::size_t bytes = out.ByteSizeLong();
  for (std::size_t rank = 0; rank < selection.size(); ++rank) {
    const KeyframeId& id = selection[rank];
    if (keyframes_sent_.count(id) != 0) continue;
    const ServerKeyframe* kf = content.keyframe(id);
    const CovisibleCamera* camera = cameraOf(cameras, id.agent);
    // A pose graph's move waits for the GBA after it: the agent keeps the state it holds until then.
    if (kf == nullptr || camera == nullptr || kf->provisional) continue;
    const geometry::SE3d T_w_c = T_w_m * kf->T_w_s * camera->T_s_c;
    std::vector<const ServerMapPoint*> new_points;
    v1::CovisibleKeyframe keyframe = describeKeyframe(content, id, *kf, *camera, T_w_c, points_sent_, new_points);
    // Points new to the stream that an earlier keyframe of this message brings are not sent twice.
    std::vector<v1::CovisiblePoint> points;
    points.reserve(new_points.size());
    std::size_t point_bytes = 0;
    for (const ServerMapPoint* point : new_points) {
      points.emplace_back();
      setPoint(point->id, T_w_m * point->p_w, *point, &points.back());
      point_bytes += points.back().ByteSizeLong() + 3;  // + tag and length
    }
    const std::size_t keyframe_bytes = keyframe.ByteSizeLong() + 4;
    // Over the budget, this keyframe and all ranked below it wait; but a message always makes progress, so a
    // keyframe that alone is larger than the budget goes alone.
    const bool over_capacity = report.points + static_cast<int>(points.size()) > wire::kMaxCovisiblePointsPerMessage;
    if ((bytes + keyframe_bytes + point_bytes > options_.budget_bytes && report.keyframes > 0) || over_capacity) {
      // Ranked below this one, the rest waits too: the next message starts with the best keyframe not yet sent.
      for (std::size_t r = rank; r < selection.size(); ++r) report.deferred += keyframes_sent_.count(selection[r]) == 0;
      return;
    }
    bytes += keyframe_bytes + point_bytes;
    for (v1::CovisiblePoint& point : points) {
      const MapPointId pid{static_cast<AgentId>(point.agent()), point.counter()};
      points_sent_[pid] = Eigen::Vector3d(point.p_w(0), point.p_w(1), point.p_w(2));
      *out.add_points() = std::move(point);
    }
    report.points += static_cast<int>(points.size());
    ++report.keyframes;
    *out.add_keyframes() = std::move(keyframe);
    keyframes_sent_[id] = T_w_c;
  }
}

}  // namespace cvislam::server
