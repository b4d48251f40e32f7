#include "server_cloud/stack/map_content.hpp"

#include <algorithm>
#include <string>

namespace cvislam::server {

int ServerKeyframe::observationCount() const {
  return static_cast<int>(std::count(has_point.begin(), has_point.end(), std::uint8_t{1}));
}

namespace {
const std::unordered_map<KeyframeId, int> kNoNeighbours;

Error notFound(const std::string& what) {
  return Error{ErrorCode::kNotFound, what};
}
}  // namespace

Status MapContent::addKeyframe(ServerKeyframe keyframe) {
  if (keyframes_.count(keyframe.id) != 0) {
    return Error{ErrorCode::kAlreadyExists, "keyframe " + keyframe.id.toString() + " is already in the map"};
  }
  const std::size_t n = keyframe.keypoints.size();
  keyframe.point.assign(n, MapPointId{});
  keyframe.has_point.assign(n, 0);
  agents_.insert(keyframe.id.agent);
  const KeyframeId id = keyframe.id;
  keyframes_.emplace(id, std::move(keyframe));
  return Status::Ok();
}

Status MapContent::addPoint(ServerMapPoint point) {
  if (points_.count(point.id) != 0) {
    return Error{ErrorCode::kAlreadyExists, "map point " + point.id.toString() + " is already in the map"};
  }
  if (keyframes_.count(point.reference) == 0) {
    return notFound("map point " + point.id.toString() + ": reference keyframe " + point.reference.toString() +
                    " is not in the map");
  }
  point.observations.clear();
  const MapPointId id = point.id;
  points_.emplace(id, std::move(point));
  return Status::Ok();
}

void MapContent::addCovisibility(const KeyframeId& a, const KeyframeId& b, int delta) {
  auto& row_a = covisibility_[a];
  int& w = row_a[b];
  const bool was_edge = w > 0;
  w += delta;
  covisibility_[b][a] = w;
  if (w <= 0) {
    row_a.erase(b);
    covisibility_[b].erase(a);
    if (row_a.empty()) covisibility_.erase(a);
    if (auto it = covisibility_.find(b); it != covisibility_.end() && it->second.empty()) covisibility_.erase(it);
    if (was_edge) --edges_;
  } else if (!was_edge) {
    ++edges_;
  }
}

void MapContent::link(ServerKeyframe& kf, std::uint16_t keypoint, ServerMapPoint& point) {
  for (const auto& o : point.observations) addCovisibility(kf.id, o.keyframe, +1);
  point.observations.push_back({kf.id, keypoint});
  kf.point[keypoint] = point.id;
  kf.has_point[keypoint] = 1;
}

void MapContent::unlink(ServerKeyframe& kf, std::uint16_t keypoint) {
  if (kf.has_point[keypoint] == 0) return;
  const MapPointId id = kf.point[keypoint];
  kf.has_point[keypoint] = 0;
  auto it = points_.find(id);
  if (it == points_.end()) return;
  auto& obs = it->second.observations;
  obs.erase(
      std::remove_if(obs.begin(), obs.end(), [&](const ServerMapPoint::Observation& o) { return o.keyframe == kf.id; }),
      obs.end());
  for (const auto& o : obs) addCovisibility(kf.id, o.keyframe, -1);
}

Status MapContent::addObservation(const KeyframeId& keyframe, std::uint16_t keypoint, const MapPointId& point) {
  auto kf = keyframes_.find(keyframe);
  if (kf == keyframes_.end()) return notFound("keyframe " + keyframe.toString() + " is not in the map");
  auto p = points_.find(resolvePoint(point));
  if (p == points_.end()) return notFound("map point " + point.toString() + " is not in the map");
  if (keypoint >= kf->second.keypoints.size()) {
    return Error{ErrorCode::kInvalidArgument, "keyframe " + keyframe.toString() + " has " +
                                                  std::to_string(kf->second.keypoints.size()) + " keypoints, not " +
                                                  std::to_string(keypoint + 1)};
  }
  ServerKeyframe& k = kf->second;
  if (k.has_point[keypoint] != 0 && k.point[keypoint] == p->first) return Status::Ok();
  for (const auto& o : p->second.observations) {
    if (o.keyframe == keyframe) {
      return Error{ErrorCode::kAlreadyExists, "keyframe " + keyframe.toString() + " observes map point " +
                                                  p->first.toString() + " already, at keypoint " +
                                                  std::to_string(o.keypoint)};
    }
  }
  unlink(k, keypoint);
  link(k, keypoint, p->second);
  return Status::Ok();
}

Status MapContent::mergePoints(const MapPointId& drop_id, const MapPointId& keep_id) {
  if (drop_id == keep_id) {
    return Error{ErrorCode::kInvalidArgument, "map point " + drop_id.toString() + " merged into itself"};
  }
  // Either may have been merged away by the server already: the points they became.
  const MapPointId drop = resolvePoint(drop_id);
  const MapPointId keep = resolvePoint(keep_id);
  if (drop == keep && points_.count(drop) != 0) return Status::Ok();
  auto d = points_.find(drop);
  if (d == points_.end()) return notFound("merge: map point " + drop_id.toString() + " is not in the map");
  auto k = points_.find(keep);
  if (k == points_.end()) return notFound("merge: map point " + keep.toString() + " is not in the map");
  const std::vector<ServerMapPoint::Observation> moved = d->second.observations;
  for (const auto& o : moved) {
    ServerKeyframe& kf = keyframes_.at(o.keyframe);
    unlink(kf, o.keypoint);
    const bool observes_keep =
        std::any_of(k->second.observations.begin(), k->second.observations.end(),
                    [&](const ServerMapPoint::Observation& ko) { return ko.keyframe == o.keyframe; });
    if (!observes_keep) link(kf, o.keypoint, k->second);
  }
  points_.erase(d);
  aliases_[drop] = keep;
  return Status::Ok();
}

MapPointId MapContent::resolvePoint(const MapPointId& id) const {
  MapPointId current = id;
  // Chains stay short (a point is merged away once); the bound guards against a cycle.
  for (int hops = 0; hops < 64 && points_.count(current) == 0; ++hops) {
    const auto it = aliases_.find(current);
    if (it == aliases_.end()) break;
    current = it->second;
  }
  return current;
}

void MapContent::absorb(MapContent& other, const geometry::SE3d& T_this_other) {
  for (auto& [id, kf] : other.keyframes_) {
    kf.T_w_s = T_this_other * kf.T_w_s;
    kf.v_w = T_this_other.so3() * kf.v_w;
    keyframes_.emplace(id, std::move(kf));
  }
  for (auto& [id, p] : other.points_) {
    p.p_w = T_this_other * p.p_w;
    points_.emplace(id, std::move(p));
  }
  for (auto& [id, links] : other.covisibility_) covisibility_.emplace(id, std::move(links));
  for (auto& [from, to] : other.aliases_) aliases_.emplace(from, to);
  edges_ += other.edges_;
  agents_.insert(other.agents_.begin(), other.agents_.end());
  other.keyframes_.clear();
  other.points_.clear();
  other.covisibility_.clear();
  other.aliases_.clear();
  other.edges_ = 0;
  other.agents_.clear();
}

Status MapContent::removePoint(const MapPointId& id) {
  auto p = points_.find(id);
  if (p == points_.end()) return notFound("map point " + id.toString() + " is not in the map");
  const std::vector<ServerMapPoint::Observation> observations = p->second.observations;
  for (const auto& o : observations) unlink(keyframes_.at(o.keyframe), o.keypoint);
  points_.erase(id);
  return Status::Ok();
}

Status MapContent::removeKeyframe(const KeyframeId& id, std::vector<MapPointId>* removed_points) {
  auto it = keyframes_.find(id);
  if (it == keyframes_.end()) return notFound("keyframe " + id.toString() + " is not in the map");
  ServerKeyframe& kf = it->second;
  std::vector<MapPointId> touched;
  for (std::size_t k = 0; k < kf.has_point.size(); ++k) {
    if (kf.has_point[k] == 0) continue;
    touched.push_back(kf.point[k]);
    unlink(kf, static_cast<std::uint16_t>(k));
  }
  for (const MapPointId& pid : touched) {
    auto p = points_.find(pid);
    if (p == points_.end()) continue;
    if (p->second.observations.empty()) {
      // No observer left, whichever keyframe it refers to.
      if (removed_points != nullptr) removed_points->push_back(pid);
      points_.erase(p);
    } else if (p->second.reference == id) {
      p->second.reference = p->second.observations.front().keyframe;
    }
  }
  // Points whose reference was this keyframe but which it did not observe (should not happen) go too.
  for (auto p = points_.begin(); p != points_.end();) {
    if (p->second.reference == id) {
      if (p->second.observations.empty()) {
        if (removed_points != nullptr) removed_points->push_back(p->first);
        p = points_.erase(p);
        continue;
      }
      p->second.reference = p->second.observations.front().keyframe;
    }
    ++p;
  }
  for (auto& [other_id, other] : keyframes_) {
    if (other.imu_from && *other.imu_from == id) {
      other.imu_from.reset();
      other.preintegration.reset();
      other.imu.clear();
    }
  }
  keyframes_.erase(it);
  return Status::Ok();
}

const ServerKeyframe* MapContent::keyframe(const KeyframeId& id) const {
  auto it = keyframes_.find(id);
  return it == keyframes_.end() ? nullptr : &it->second;
}
ServerKeyframe* MapContent::keyframe(const KeyframeId& id) {
  auto it = keyframes_.find(id);
  return it == keyframes_.end() ? nullptr : &it->second;
}
const ServerMapPoint* MapContent::point(const MapPointId& id) const {
  auto it = points_.find(id);
  return it == points_.end() ? nullptr : &it->second;
}
ServerMapPoint* MapContent::point(const MapPointId& id) {
  auto it = points_.find(id);
  return it == points_.end() ? nullptr : &it->second;
}

int MapContent::covisibility(const KeyframeId& a, const KeyframeId& b) const {
  auto row = covisibility_.find(a);
  if (row == covisibility_.end()) return 0;
  auto w = row->second.find(b);
  return w == row->second.end() ? 0 : w->second;
}

const std::unordered_map<KeyframeId, int>& MapContent::covisible(const KeyframeId& id) const {
  auto row = covisibility_.find(id);
  return row == covisibility_.end() ? kNoNeighbours : row->second;
}

Status MapContent::checkConsistency() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInternal, what}; };
  std::unordered_map<KeyframeId, std::unordered_map<KeyframeId, int>> expected;
  std::size_t links = 0;
  for (const auto& [id, kf] : keyframes_) {
    if (kf.point.size() != kf.keypoints.size() || kf.has_point.size() != kf.keypoints.size()) {
      return bad("keyframe " + id.toString() + ": per-keypoint arrays differ in size");
    }
    for (std::size_t k = 0; k < kf.has_point.size(); ++k) {
      if (kf.has_point[k] == 0) continue;
      ++links;
      const ServerMapPoint* p = point(kf.point[k]);
      if (p == nullptr) return bad("keyframe " + id.toString() + " observes missing point " + kf.point[k].toString());
      const auto matches = std::count_if(p->observations.begin(), p->observations.end(),
                                         [&, observer = id](const auto& o) {  // clang 14 cannot capture a binding
                                           return o.keyframe == observer && o.keypoint == k;
                                         });
      if (matches != 1) return bad("point " + p->id.toString() + " does not list keyframe " + id.toString() + " once");
    }
  }
  std::size_t back_links = 0;
  for (const auto& [id, p] : points_) {
    if (keyframes_.count(p.reference) == 0) return bad("point " + id.toString() + " has a missing reference");
    back_links += p.observations.size();
    for (std::size_t i = 0; i < p.observations.size(); ++i) {
      for (std::size_t j = i + 1; j < p.observations.size(); ++j) {
        if (p.observations[i].keyframe == p.observations[j].keyframe) {
          return bad("point " + id.toString() + " observed twice by one keyframe");
        }
        ++expected[p.observations[i].keyframe][p.observations[j].keyframe];
        ++expected[p.observations[j].keyframe][p.observations[i].keyframe];
      }
    }
  }
  if (links != back_links) return bad("observation counts differ between keyframes and points");
  std::size_t edges = 0;
  for (const auto& [a, row] : expected) {
    for (const auto& [b, w] : row) {
      if (covisibility(a, b) != w) {
        return bad("covisibility " + a.toString() + "-" + b.toString() + " is " + std::to_string(covisibility(a, b)) +
                   ", expected " + std::to_string(w));
      }
      ++edges;
    }
  }
  if (edges / 2 != edges_)
    return bad("edge count " + std::to_string(edges_) + ", expected " + std::to_string(edges / 2));
  for (const auto& [a, row] : covisibility_) {
    for (const auto& [b, w] : row) {
      if (w <= 0 || expected[a][b] != w) return bad("stale covisibility " + a.toString() + "-" + b.toString());
    }
  }
  return Status::Ok();
}

}  // namespace cvislam::server
