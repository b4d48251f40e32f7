#include "server_cloud/backend/map_fusion.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <unordered_set>

#include "common/features/orb.hpp"

namespace cvislam::server::backend {

using geometry::SE3d;

Status FusionOptions::validate() const {
  if (neighbours < 0) return Error{ErrorCode::kInvalidArgument, "fusion.neighbours must be >= 0"};
  if (!(search_radius_px > 0.0)) return Error{ErrorCode::kInvalidArgument, "fusion.search_radius_px must be positive"};
  if (max_descriptor_distance < 0 || max_descriptor_distance > 256) {
    return Error{ErrorCode::kInvalidArgument, "fusion.max_descriptor_distance must be in [0, 256]"};
  }
  if (!(pyramid_scale_factor >= 1.0)) {
    return Error{ErrorCode::kInvalidArgument, "fusion.pyramid_scale_factor must be >= 1"};
  }
  return Status::Ok();
}

double yawOf(const Eigen::Matrix3d& R) {
  return std::atan2(R(1, 0), R(0, 0));
}

SE3d fourDofTransform(const SE3d& T_to_from, const Eigen::Vector3d& p_from_anchor) {
  const double yaw = yawOf(T_to_from.rotationMatrix());
  const geometry::SO3d R_yaw = geometry::SO3d::exp(Eigen::Vector3d(0.0, 0.0, yaw));
  const Eigen::Vector3d p_to_anchor = T_to_from * p_from_anchor;
  return SE3d(R_yaw, p_to_anchor - (R_yaw * p_from_anchor));
}

std::vector<KeyframeId> neighbourhood(const MapContent& map, const KeyframeId& keyframe, int count) {
  std::vector<KeyframeId> out;
  if (map.keyframe(keyframe) == nullptr) return out;
  out.push_back(keyframe);
  std::vector<std::pair<int, KeyframeId>> neighbours;
  for (const auto& [n, shared] : map.covisible(keyframe)) neighbours.emplace_back(shared, n);
  std::sort(neighbours.begin(), neighbours.end(),
            [](const auto& a, const auto& b) { return a.first != b.first ? a.first > b.first : a.second < b.second; });
  for (std::size_t i = 0; i < neighbours.size() && static_cast<int>(i) < count; ++i) {
    out.push_back(neighbours[i].second);
  }
  return out;
}

std::vector<MapPointId> pointsOf(const MapContent& map, const std::vector<KeyframeId>& keyframes) {
  std::vector<MapPointId> out;
  std::unordered_set<MapPointId> seen;
  for (const KeyframeId& id : keyframes) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (kf == nullptr) continue;
    for (std::size_t k = 0; k < kf->has_point.size(); ++k) {
      if (kf->has_point[k] != 0 && seen.insert(kf->point[k]).second) out.push_back(kf->point[k]);
    }
  }
  return out;
}

namespace {

// Links `keypoint` of `keyframe` to `point`, or fuses the point the keypoint observes with it.
void linkOrFuse(MapContent& map, const KeyframeId& keyframe, std::uint16_t keypoint, const MapPointId& point,
                int& linked, int& fused) {
  const ServerKeyframe* kf = map.keyframe(keyframe);
  const ServerMapPoint* p = map.point(map.resolvePoint(point));
  if (kf == nullptr || p == nullptr) return;
  if (kf->has_point[keypoint] == 0) {
    if (map.addObservation(keyframe, keypoint, p->id).ok()) ++linked;
    return;
  }
  const MapPointId other = kf->point[keypoint];
  if (other == p->id) return;
  const ServerMapPoint* q = map.point(other);
  if (q == nullptr) return;
  // The point seen more keeps its id (and its reference); ties keep the older id.
  const bool keep_p = p->observations.size() != q->observations.size() ? p->observations.size() > q->observations.size()
                                                                       : p->id < q->id;
  const MapPointId keep = keep_p ? p->id : q->id;
  const MapPointId drop = keep_p ? q->id : p->id;
  if (map.mergePoints(drop, keep).ok()) ++fused;
}

}  // namespace

void fuseByProjection(MapContent& map, const std::vector<KeyframeId>& keyframes, const std::vector<MapPointId>& points,
                      const recognition::CameraLookup& cameras, const FusionOptions& options, FusionReport& report) {
  for (const KeyframeId& id : keyframes) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (kf == nullptr) continue;
    const recognition::AgentCamera* camera = cameras(id.agent);
    if (camera == nullptr) continue;
    const SE3d T_c_w = (kf->T_w_s * camera->T_s_c).inverse();
    const double width = camera->camera.width();
    const double height = camera->camera.height();
    for (const MapPointId& pid : points) {
      kf = map.keyframe(id);  // a fusion may have changed the keyframe's links, never its storage
      const ServerMapPoint* p = map.point(map.resolvePoint(pid));
      if (p == nullptr) continue;
      if (std::any_of(p->observations.begin(), p->observations.end(),
                      [&](const ServerMapPoint::Observation& o) { return o.keyframe == id; })) {
        continue;
      }
      const Eigen::Vector3d X_c = T_c_w * p->p_w;
      const std::optional<Eigen::Vector2d> px = camera->camera.project(X_c);
      if (!px || px->x() < 0.0 || px->y() < 0.0 || px->x() >= width || px->y() >= height) continue;
      const double radius = options.search_radius_px * std::pow(options.pyramid_scale_factor, p->octave);
      int best = std::numeric_limits<int>::max();
      int best_keypoint = -1;
      for (std::size_t k = 0; k < kf->keypoints.size(); ++k) {
        const features::Keypoint& key = kf->keypoints[k];
        if ((key.px.cast<double>() - *px).squaredNorm() > radius * radius) continue;
        if (std::abs(static_cast<int>(key.octave) - static_cast<int>(p->octave)) > 1) continue;
        const int distance = features::hammingDistance(kf->descriptors[k], p->descriptor);
        if (distance < best) {
          best = distance;
          best_keypoint = static_cast<int>(k);
        }
      }
      if (best_keypoint < 0 || best > options.max_descriptor_distance) continue;
      linkOrFuse(map, id, static_cast<std::uint16_t>(best_keypoint), p->id, report.projection_linked,
                 report.projection_fused);
    }
  }
}

FusionReport fuseMatch(MapContent& map, const recognition::VerifiedMatch& match,
                       const recognition::CameraLookup& cameras, const FusionOptions& options) {
  FusionReport report;
  for (const auto& [query_point, candidate_point] : match.point_pairs) {
    const MapPointId q = map.resolvePoint(query_point);
    const MapPointId c = map.resolvePoint(candidate_point);
    if (q == c || map.point(q) == nullptr || map.point(c) == nullptr) continue;
    if (map.mergePoints(q, c).ok()) ++report.pairs_fused;
  }
  int fused = 0;
  for (const auto& [keypoint, candidate_point] : match.keypoint_matches) {
    const ServerKeyframe* kf = map.keyframe(match.query);
    if (kf == nullptr || keypoint >= kf->keypoints.size()) break;
    linkOrFuse(map, match.query, keypoint, candidate_point, report.keypoints_linked, fused);
  }
  report.pairs_fused += fused;
  const std::vector<KeyframeId> query_side = neighbourhood(map, match.query, options.neighbours);
  const std::vector<KeyframeId> candidate_side = neighbourhood(map, match.candidate, options.neighbours);
  fuseByProjection(map, query_side, pointsOf(map, candidate_side), cameras, options, report);
  return report;
}

}  // namespace cvislam::server::backend
