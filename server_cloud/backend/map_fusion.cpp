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
  if (nearby_keyframes < 0) return Error{ErrorCode::kInvalidArgument, "fusion.nearby_keyframes must be >= 0"};
  if (!(nearby_radius_m >= 0.0)) return Error{ErrorCode::kInvalidArgument, "fusion.nearby_radius_m must be >= 0"};
  if (!(nearby_max_angle_deg >= 0.0 && nearby_max_angle_deg <= 180.0)) {
    return Error{ErrorCode::kInvalidArgument, "fusion.nearby_max_angle_deg must be in [0, 180]"};
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

namespace {

// A keyframe's keypoints bucketed by pixel, so that a projection looks at its neighbourhood only.
class KeypointGrid {
 public:
  KeypointGrid(const std::vector<features::Keypoint>& keypoints, double width, double height)
      : columns_(std::max(1, static_cast<int>(std::ceil(width / kCell)))),
        rows_(std::max(1, static_cast<int>(std::ceil(height / kCell)))),
        cells_(static_cast<std::size_t>(columns_ * rows_)) {
    for (std::size_t k = 0; k < keypoints.size(); ++k) {
      const Eigen::Vector2f& px = keypoints[k].px;
      cells_[cellOf(column(px.x()), row(px.y()))].push_back(static_cast<std::uint16_t>(k));
    }
  }
  // Calls `visit(keypoint)` for every keypoint in the cells that a circle of `radius` around `px` touches.
  template <typename Visit>
  void forEachNear(const Eigen::Vector2d& px, double radius, Visit&& visit) const {
    const int c0 = column(px.x() - radius);
    const int c1 = column(px.x() + radius);
    const int r0 = row(px.y() - radius);
    const int r1 = row(px.y() + radius);
    for (int r = r0; r <= r1; ++r) {
      for (int c = c0; c <= c1; ++c) {
        for (std::uint16_t k : cells_[cellOf(c, r)]) visit(k);
      }
    }
  }

 private:
  static constexpr double kCell = 16.0;
  [[nodiscard]] int column(double x) const {
    return std::clamp(static_cast<int>(std::floor(x / kCell)), 0, columns_ - 1);
  }
  [[nodiscard]] int row(double y) const { return std::clamp(static_cast<int>(std::floor(y / kCell)), 0, rows_ - 1); }
  [[nodiscard]] std::size_t cellOf(int c, int r) const { return static_cast<std::size_t>(r * columns_ + c); }

  int columns_;
  int rows_;
  std::vector<std::vector<std::uint16_t>> cells_;
};

}  // namespace

ProjectionSearchInput gatherProjectionSearch(const MapContent& map, const std::vector<KeyframeId>& keyframes,
                                             const std::vector<MapPointId>& points,
                                             const recognition::CameraLookup& cameras) {
  ProjectionSearchInput input;
  for (const KeyframeId& id : keyframes) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (kf == nullptr) continue;
    const recognition::AgentCamera* camera = cameras(id.agent);
    if (camera == nullptr) continue;
    ProjectionSearchInput::Target& t = input.targets.emplace_back();
    t.id = id;
    t.T_c_w = (kf->T_w_s * camera->T_s_c).inverse();
    t.camera = camera;
    t.keypoints = kf->keypoints;
    t.descriptors = kf->descriptors;
    for (std::size_t k = 0; k < kf->has_point.size(); ++k) {
      if (kf->has_point[k] != 0) t.observed.insert(kf->point[k]);
    }
  }
  std::unordered_set<MapPointId> seen;
  for (const MapPointId& pid : points) {
    const ServerMapPoint* p = map.point(map.resolvePoint(pid));
    if (p == nullptr || !seen.insert(p->id).second) continue;
    input.points.push_back(ProjectionSearchInput::Point{p->id, p->p_w, p->descriptor, p->octave});
  }
  return input;
}

std::vector<ProjectionMatch> searchByProjection(const ProjectionSearchInput& input, const FusionOptions& options) {
  std::vector<ProjectionMatch> out;
  for (const ProjectionSearchInput::Target& t : input.targets) {
    const double width = t.camera->camera.width();
    const double height = t.camera->camera.height();
    const KeypointGrid grid(t.keypoints, width, height);
    for (const ProjectionSearchInput::Point& p : input.points) {
      if (t.observed.count(p.id) != 0) continue;
      const Eigen::Vector3d X_c = t.T_c_w * p.p_w;
      const std::optional<Eigen::Vector2d> px = t.camera->camera.project(X_c);
      if (!px || px->x() < 0.0 || px->y() < 0.0 || px->x() >= width || px->y() >= height) continue;
      // The octave comes from an agent: bounded by an 8-level pyramid, so that no point searches a whole image.
      const double radius =
          options.search_radius_px * std::pow(options.pyramid_scale_factor, std::min<int>(p.octave, 7));
      int best = std::numeric_limits<int>::max();
      int best_keypoint = -1;
      grid.forEachNear(*px, radius, [&](std::uint16_t k) {
        const features::Keypoint& key = t.keypoints[k];
        if ((key.px.cast<double>() - *px).squaredNorm() > radius * radius) return;
        if (std::abs(static_cast<int>(key.octave) - static_cast<int>(p.octave)) > 1) return;
        const int distance = features::hammingDistance(t.descriptors[k], p.descriptor);
        if (distance < best || (distance == best && static_cast<int>(k) < best_keypoint)) {
          best = distance;
          best_keypoint = static_cast<int>(k);
        }
      });
      if (best_keypoint < 0 || best > options.max_descriptor_distance) continue;
      out.push_back(ProjectionMatch{t.id, static_cast<std::uint16_t>(best_keypoint), p.id});
    }
  }
  return out;
}

std::vector<ProjectionMatch> searchByProjection(const MapContent& map, const std::vector<KeyframeId>& keyframes,
                                                const std::vector<MapPointId>& points,
                                                const recognition::CameraLookup& cameras,
                                                const FusionOptions& options) {
  return searchByProjection(gatherProjectionSearch(map, keyframes, points, cameras), options);
}

void applyProjectionMatches(MapContent& map, const std::vector<ProjectionMatch>& matches, FusionReport& report) {
  for (const ProjectionMatch& m : matches) {
    const ServerKeyframe* kf = map.keyframe(m.keyframe);
    if (kf == nullptr || m.keypoint >= kf->keypoints.size()) continue;
    linkOrFuse(map, m.keyframe, m.keypoint, m.point, report.projection_linked, report.projection_fused);
  }
}

void fuseByProjection(MapContent& map, const std::vector<KeyframeId>& keyframes, const std::vector<MapPointId>& points,
                      const recognition::CameraLookup& cameras, const FusionOptions& options, FusionReport& report) {
  applyProjectionMatches(map, searchByProjection(map, keyframes, points, cameras, options), report);
}

std::vector<KeyframeId> nearbyKeyframes(const MapContent& map, const KeyframeId& keyframe,
                                        const recognition::CameraLookup& cameras, const FusionOptions& options) {
  std::vector<KeyframeId> out;
  const ServerKeyframe* kf = map.keyframe(keyframe);
  const recognition::AgentCamera* camera = cameras(keyframe.agent);
  if (kf == nullptr || camera == nullptr || options.nearby_keyframes <= 0) return out;
  const SE3d T_w_c = kf->T_w_s * camera->T_s_c;
  const double cos_max = std::cos(options.nearby_max_angle_deg * M_PI / 180.0);
  std::vector<std::pair<double, KeyframeId>> near;
  for (const auto& [id, other] : map.keyframes()) {
    if (id == keyframe) continue;
    const recognition::AgentCamera* other_camera = cameras(id.agent);
    if (other_camera == nullptr) continue;
    const SE3d T_w_o = other.T_w_s * other_camera->T_s_c;
    const double distance = (T_w_o.translation() - T_w_c.translation()).norm();
    if (distance > options.nearby_radius_m) continue;
    const double cos_angle = T_w_o.so3().matrix().col(2).dot(T_w_c.so3().matrix().col(2));
    if (cos_angle < cos_max) continue;
    near.emplace_back(distance, id);
  }
  std::sort(near.begin(), near.end(),
            [](const auto& a, const auto& b) { return a.first != b.first ? a.first < b.first : a.second < b.second; });
  for (std::size_t i = 0; i < near.size() && static_cast<int>(i) < options.nearby_keyframes; ++i) {
    out.push_back(near[i].second);
  }
  return out;
}

NewKeyframeSearch gatherNewKeyframeSearch(const MapContent& map, const KeyframeId& keyframe,
                                          const recognition::CameraLookup& cameras, const FusionOptions& options) {
  std::vector<KeyframeId> partners = neighbourhood(map, keyframe, options.neighbours);
  if (!partners.empty()) partners.erase(partners.begin());  // itself
  for (const KeyframeId& id : nearbyKeyframes(map, keyframe, cameras, options)) {
    if (std::find(partners.begin(), partners.end(), id) == partners.end()) partners.push_back(id);
  }
  NewKeyframeSearch search;
  if (partners.empty()) return search;
  search.into_keyframe = gatherProjectionSearch(map, {keyframe}, pointsOf(map, partners), cameras);
  search.into_partners = gatherProjectionSearch(map, partners, pointsOf(map, {keyframe}), cameras);
  return search;
}

std::vector<ProjectionMatch> searchNewKeyframe(const NewKeyframeSearch& search, const FusionOptions& options) {
  std::vector<ProjectionMatch> out = searchByProjection(search.into_keyframe, options);
  std::vector<ProjectionMatch> back = searchByProjection(search.into_partners, options);
  out.insert(out.end(), back.begin(), back.end());
  return out;
}

std::vector<ProjectionMatch> searchNewKeyframe(const MapContent& map, const KeyframeId& keyframe,
                                               const recognition::CameraLookup& cameras, const FusionOptions& options) {
  return searchNewKeyframe(gatherNewKeyframeSearch(map, keyframe, cameras, options), options);
}

FusionReport fuseMatch(MapContent& map, const recognition::VerifiedMatch& match,
                       const recognition::CameraLookup& cameras, const FusionOptions& options) {
  FusionReport report;
  const ProjectionSearchInput input = fuseMatchPairs(map, match, cameras, options, report);
  applyProjectionMatches(map, searchByProjection(input, options), report);
  return report;
}

ProjectionSearchInput fuseMatchPairs(MapContent& map, const recognition::VerifiedMatch& match,
                                     const recognition::CameraLookup& cameras, const FusionOptions& options,
                                     FusionReport& report) {
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
  return gatherProjectionSearch(map, query_side, pointsOf(map, candidate_side), cameras);
}

}  // namespace cvislam::server::backend
