#include "server_cloud/recognition/place_recognition.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <sstream>
#include <unordered_map>
#include <unordered_set>

#include <Eigen/Cholesky>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "common/features/best_two.hpp"
#include "common/geometry/alignment.hpp"

namespace cvislam::server::recognition {
namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

Status positive(bool ok, std::string_view field) {
  if (ok) return {};
  return Error(ErrorCode::kInvalidArgument, "recognition." + std::string(field) + " is out of range");
}

// One 2D-3D correspondence: a query keypoint and a candidate map point.
struct Correspondence {
  std::uint16_t keypoint = 0;
  MapPointId point;
  Eigen::Vector3d p_m = Eigen::Vector3d::Zero();  // in the candidate map
  int distance = 0;
};

using CopiedKeyframe = VerificationInput::Keyframe;
using CopiedPoint = VerificationInput::Point;

// Gauss-Newton with a Huber weight on the distorted-pixel reprojection error, over T_c_m (left perturbation,
// [rho; phi]). Returns the refined pose; correspondences behind the camera are left out of each step.
geometry::SE3d refinePose(const camera::CameraModel& camera, const std::vector<Eigen::Vector2d>& px,
                          const std::vector<Eigen::Vector3d>& p_m, geometry::SE3d T_c_m, double huber_px) {
  for (int iteration = 0; iteration < 10; ++iteration) {
    Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
    int used = 0;
    for (std::size_t i = 0; i < px.size(); ++i) {
      const Eigen::Vector3d p_c = T_c_m * p_m[i];
      Eigen::Matrix<double, 2, 3> J_px_p;
      const std::optional<Eigen::Vector2d> projected = camera.project(p_c, &J_px_p);
      if (!projected) continue;
      const Eigen::Vector2d r = *projected - px[i];
      const double norm = r.norm();
      const double w = norm <= huber_px ? 1.0 : huber_px / norm;
      Eigen::Matrix<double, 3, 6> J_p_xi;
      J_p_xi.leftCols<3>().setIdentity();
      J_p_xi.rightCols<3>() << 0.0, p_c.z(), -p_c.y(), -p_c.z(), 0.0, p_c.x(), p_c.y(), -p_c.x(), 0.0;
      const Eigen::Matrix<double, 2, 6> J = J_px_p * J_p_xi;
      H += w * J.transpose() * J;
      b += w * J.transpose() * r;
      ++used;
    }
    if (used < 6) break;
    const Eigen::Matrix<double, 6, 1> delta = H.ldlt().solve(-b);
    if (!delta.allFinite()) break;
    T_c_m = geometry::SE3d::exp(delta) * T_c_m;
    if (delta.norm() < 1e-9) break;
  }
  return T_c_m;
}

std::vector<bool> reprojectionInliers(const camera::CameraModel& camera, const std::vector<Eigen::Vector2d>& px,
                                      const std::vector<Eigen::Vector3d>& p_m, const geometry::SE3d& T_c_m,
                                      double max_px) {
  std::vector<bool> inlier(px.size(), false);
  for (std::size_t i = 0; i < px.size(); ++i) {
    const std::optional<Eigen::Vector2d> projected = camera.project(T_c_m * p_m[i]);
    inlier[i] = projected && (*projected - px[i]).squaredNorm() <= max_px * max_px;
  }
  return inlier;
}

// Angle between the transform's image of +z and +z: its roll/pitch.
double tiltDeg(const geometry::SE3d& T) {
  const Eigen::Vector3d z = T.rotationMatrix() * Eigen::Vector3d::UnitZ();
  return std::acos(std::clamp(z.z(), -1.0, 1.0)) * kRadToDeg;
}

bool usablePoint(const ServerKeyframe& kf, std::size_t i) {
  return i < kf.has_point.size() && kf.has_point[i] != 0;
}

// The `count` keyframes most covisible with `keyframe`, most shared points first (ties by id).
std::vector<KeyframeId> mostCovisible(const MapContent& map, const KeyframeId& keyframe, int count) {
  std::vector<std::pair<int, KeyframeId>> neighbours;
  for (const auto& [n, shared] : map.covisible(keyframe)) neighbours.emplace_back(shared, n);
  std::sort(neighbours.begin(), neighbours.end(),
            [](const auto& a, const auto& b) { return a.first != b.first ? a.first > b.first : a.second < b.second; });
  if (neighbours.size() > static_cast<std::size_t>(count)) neighbours.resize(static_cast<std::size_t>(count));
  std::vector<KeyframeId> out;
  out.reserve(neighbours.size());
  for (const auto& [shared, n] : neighbours) out.push_back(n);
  return out;
}

}  // namespace

Status RecognitionOptions::validate() const {
  if (Status s = positive(min_score >= 0.0 && min_score <= 1.0, "min_score"); !s) return s;
  if (Status s = positive(min_score_ratio >= 0.0 && min_score_ratio <= 1.0, "min_score_ratio"); !s) return s;
  if (Status s = positive(neighbour_min_shared_points >= 1, "neighbour_min_shared_points"); !s) return s;
  if (Status s = positive(min_common_words_ratio >= 0.0 && min_common_words_ratio <= 1.0, "min_common_words_ratio");
      !s) {
    return s;
  }
  if (Status s = positive(group_neighbours >= 0, "group_neighbours"); !s) return s;
  if (Status s = positive(group_score_ratio >= 0.0 && group_score_ratio <= 1.0, "group_score_ratio"); !s) return s;
  if (Status s = positive(max_candidates >= 1, "max_candidates"); !s) return s;
  if (Status s = positive(loop_min_interval_s >= 0.0, "loop_min_interval_s"); !s) return s;
  if (Status s = positive(direct_level >= 0, "direct_level"); !s) return s;
  if (Status s = positive(max_descriptor_distance >= 0 && max_descriptor_distance <= 256, "max_descriptor_distance");
      !s) {
    return s;
  }
  if (Status s = positive(match_ratio > 0.0F && match_ratio <= 1.0F, "match_ratio"); !s) return s;
  if (Status s = positive(min_matches >= 4, "min_matches (at least 4)"); !s) return s;
  if (Status s = positive(ransac_iterations >= 1, "ransac_iterations"); !s) return s;
  if (Status s = positive(ransac_threshold_px > 0.0, "ransac_threshold_px"); !s) return s;
  if (Status s = positive(min_ransac_inliers >= 4, "min_ransac_inliers (at least 4)"); !s) return s;
  if (Status s = positive(max_reprojection_px > 0.0, "max_reprojection_px"); !s) return s;
  if (Status s = positive(guided_neighbours >= 0, "guided_neighbours"); !s) return s;
  if (Status s = positive(guided_radius_px > 0.0, "guided_radius_px"); !s) return s;
  if (Status s = positive(guided_max_distance >= 0 && guided_max_distance <= 256, "guided_max_distance"); !s) return s;
  if (Status s = positive(min_inliers >= min_ransac_inliers, "min_inliers (at least min_ransac_inliers)"); !s) {
    return s;
  }
  if (Status s = positive(max_tilt_deg > 0.0 && max_tilt_deg <= 180.0, "max_tilt_deg"); !s) return s;
  if (Status s = positive(min_pairs_for_scale >= 3, "min_pairs_for_scale (at least 3)"); !s) return s;
  if (Status s = positive(max_scale_error > 0.0, "max_scale_error"); !s) return s;
  return positive(pair_inlier_distance_m > 0.0, "pair_inlier_distance_m");
}

std::string RecognitionOptions::describe() const {
  std::ostringstream out;
  out << "loops >= " << loop_min_interval_s << " s apart; candidates: score >= max(" << min_score << ", "
      << min_score_ratio << " x best covisible neighbour), "
      << "groups of " << group_neighbours << " >= " << group_score_ratio << " x best, at most " << max_candidates
      << "; matching: direct level " << direct_level << ", distance <= " << max_descriptor_distance << ", ratio "
      << match_ratio << ", >= " << min_matches << "; RANSAC " << ransac_iterations << " it, " << ransac_threshold_px
      << " px, >= " << min_ransac_inliers << "; guided search " << guided_radius_px << " px over " << guided_neighbours
      << " neighbours; accept >= " << min_inliers << " inliers within " << max_reprojection_px
      << " px, tilt <= " << max_tilt_deg << " deg, |scale - 1| <= " << max_scale_error;
  return out.str();
}

std::string_view toString(QueryKind kind) {
  return kind == QueryKind::kLoop ? "loop" : "map match";
}

std::string_view toString(Rejection rejection) {
  switch (rejection) {
    case Rejection::kNone:
      return "accepted";
    case Rejection::kMissing:
      return "missing";
    case Rejection::kTooFewMatches:
      return "too few matches";
    case Rejection::kPoseFailed:
      return "no pose";
    case Rejection::kTooFewInliers:
      return "too few inliers";
    case Rejection::kTilted:
      return "tilted";
    case Rejection::kScale:
      return "scale";
  }
  return "?";
}

Result<ScoredCandidates> scoreCandidates(const KeyframeDatabase& database, const MapContent& query_map,
                                         const KeyframeId& query, QueryKind kind, const RecognitionOptions& options) {
  const DatabaseEntry* entry = database.find(query);
  if (entry == nullptr || query_map.keyframe(query) == nullptr) {
    return Error(ErrorCode::kNotFound, "keyframe " + query.toString() + " is not in the database or its map");
  }
  ScoredCandidates scored;
  CandidateSearch& search = scored.search;
  std::unordered_set<KeyframeId> exclude{query};
  for (const auto& [neighbour, shared] : query_map.covisible(query)) {
    exclude.insert(neighbour);  // every keyframe sharing a point is too close to count as a revisit
    if (shared < options.neighbour_min_shared_points) continue;
    if (const DatabaseEntry* n = database.find(neighbour); n != nullptr) {
      search.best_neighbour_score = std::max(search.best_neighbour_score, features::bowScore(entry->bow, n->bow));
    }
  }
  search.min_score = std::max(options.min_score, options.min_score_ratio * search.best_neighbour_score);

  DatabaseQuery q;
  q.scope = kind == QueryKind::kLoop ? QueryScope::kSameMap : QueryScope::kOtherMaps;
  q.map = query_map.id();
  q.exclude = kind == QueryKind::kLoop ? &exclude : nullptr;
  q.min_score = search.min_score;
  q.min_common_words_ratio = options.min_common_words_ratio;
  scored.bow = database.query(entry->bow, q);
  if (kind == QueryKind::kLoop) {
    // The agent's own keyframes from the last loop_min_interval_s are tracking's business, not a loop.
    const std::int64_t t_q = query_map.keyframe(query)->t_ns;
    const auto min_ns = static_cast<std::int64_t>(options.loop_min_interval_s * 1e9);
    std::erase_if(scored.bow, [&](const BowCandidate& c) {
      const ServerKeyframe* kf = query_map.keyframe(c.keyframe);
      return kf != nullptr && c.keyframe.agent == query.agent && std::llabs(kf->t_ns - t_q) < min_ns;
    });
  }
  search.bow_candidates = static_cast<int>(scored.bow.size());
  return scored;
}

std::vector<KeyframeId> groupNeighbours(const MapContent& map, const KeyframeId& keyframe,
                                        const RecognitionOptions& options) {
  return mostCovisible(map, keyframe, options.group_neighbours);
}

CandidateSearch groupCandidates(ScoredCandidates scored, const NeighbourLookup& neighbours,
                                const RecognitionOptions& options) {
  CandidateSearch search = std::move(scored.search);
  const std::vector<BowCandidate>& bow = scored.bow;
  if (bow.empty()) return search;
  // Group by covisibility: each candidate with its most covisible keyframes that are candidates too.
  std::unordered_map<KeyframeId, double> score_of;
  for (const BowCandidate& c : bow) score_of.emplace(c.keyframe, c.score);
  struct Group {
    Candidate best;
    double score = 0.0;
  };
  std::vector<Group> groups;
  for (const BowCandidate& c : bow) {
    Group g;
    g.best = Candidate{c.keyframe, c.map, c.score, 0.0};
    g.score = c.score;
    if (const std::vector<KeyframeId>* around = neighbours(c.keyframe); around != nullptr) {
      for (const KeyframeId& n : *around) {
        const auto it = score_of.find(n);
        if (it == score_of.end()) continue;
        g.score += it->second;
        if (it->second > g.best.score) g.best = Candidate{n, c.map, it->second, 0.0};
      }
    }
    g.best.group_score = g.score;
    groups.push_back(g);
  }
  double best_group = 0.0;
  for (const Group& g : groups) best_group = std::max(best_group, g.score);
  std::sort(groups.begin(), groups.end(), [](const Group& a, const Group& b) {
    return a.score != b.score ? a.score > b.score : a.best.keyframe < b.best.keyframe;
  });
  std::unordered_set<KeyframeId> taken;
  for (const Group& g : groups) {
    if (g.score < options.group_score_ratio * best_group) break;
    if (!taken.insert(g.best.keyframe).second) continue;
    search.candidates.push_back(g.best);
    if (search.candidates.size() >= static_cast<std::size_t>(options.max_candidates)) break;
  }
  return search;
}

Result<CandidateSearch> findCandidates(const KeyframeDatabase& database, const MapContent& query_map,
                                       const KeyframeId& query, QueryKind kind, const MapLookup& maps,
                                       const RecognitionOptions& options) {
  Result<ScoredCandidates> scored = scoreCandidates(database, query_map, query, kind, options);
  if (!scored) return scored.error();
  std::unordered_map<KeyframeId, std::vector<KeyframeId>> around;
  for (const BowCandidate& c : scored->bow) {
    if (const MapContent* map = maps(c.map); map != nullptr)
      around[c.keyframe] = groupNeighbours(*map, c.keyframe, options);
  }
  return groupCandidates(std::move(scored).value(), neighbourLookup(around), options);
}

NeighbourLookup neighbourLookup(const std::unordered_map<KeyframeId, std::vector<KeyframeId>>& around) {
  return [&around](const KeyframeId& id) -> const std::vector<KeyframeId>* {
    const auto it = around.find(id);
    return it == around.end() ? nullptr : &it->second;
  };
}

namespace {

// a. Descriptor matching through the direct index: the query's features against the candidate's features that
// observe a map point, under the same vocabulary node; one query keypoint per candidate point, the closest.
std::vector<Correspondence> matchThroughDirectIndex(const CopiedKeyframe& q, const DatabaseEntry& qe,
                                                    const CopiedKeyframe& c, const DatabaseEntry& ce,
                                                    const std::vector<CopiedPoint>& points,
                                                    const RecognitionOptions& options) {
  std::vector<Correspondence> matches;
  std::unordered_map<MapPointId, std::size_t> by_point;
  const features::FeatureVector& fq = qe.features;
  const features::FeatureVector& fc = ce.features;
  std::size_t i = 0;
  std::size_t j = 0;
  while (i < fq.size() && j < fc.size()) {
    if (fq[i].node < fc[j].node) {
      ++i;
      continue;
    }
    if (fc[j].node < fq[i].node) {
      ++j;
      continue;
    }
    const features::NodeId node = fq[i].node;
    std::size_t i_end = i;
    while (i_end < fq.size() && fq[i_end].node == node) ++i_end;
    std::size_t j_end = j;
    while (j_end < fc.size() && fc[j_end].node == node) ++j_end;
    for (std::size_t a = i; a < i_end; ++a) {
      const std::uint16_t kq = fq[a].feature;
      if (kq >= q.descriptors.size()) continue;
      features::BestTwo<const CopiedPoint*> nearest;
      for (std::size_t b = j; b < j_end; ++b) {
        const std::uint16_t kc = fc[b].feature;
        if (kc >= c.point.size() || c.point[kc] < 0) continue;
        const CopiedPoint* p = &points[static_cast<std::size_t>(c.point[kc])];
        nearest.offer(features::hammingDistance(q.descriptors[kq], c.descriptors[kc]), p);
      }
      const int best = nearest.best;
      const CopiedPoint* best_point = nearest.candidate;
      if (best_point == nullptr || best > options.max_descriptor_distance) continue;
      if (nearest.hasSecond() && static_cast<float>(best) >= options.match_ratio * static_cast<float>(nearest.second)) {
        continue;
      }
      const auto [it, inserted] = by_point.emplace(best_point->id, matches.size());
      if (inserted) {
        matches.push_back(Correspondence{kq, best_point->id, best_point->p_w, best});
      } else if (best < matches[it->second].distance) {
        matches[it->second] = Correspondence{kq, best_point->id, best_point->p_w, best};
      }
    }
    i = i_end;
    j = j_end;
  }
  return matches;
}

// The correspondences a pose is refined on: the query keypoints' pixels, the points in the candidate map, and
// the correspondences themselves.
struct PoseSupport {
  std::vector<Eigen::Vector2d> px;
  std::vector<Eigen::Vector3d> p_m;
  std::vector<Correspondence> used;

  void add(const CopiedKeyframe& q, const Correspondence& m) {
    px.push_back(q.keypoints[m.keypoint].px.cast<double>());
    p_m.push_back(m.p_m);
    used.push_back(m);
  }
};

struct RansacPose {
  geometry::SE3d T_c_m;
  std::vector<int> inliers;  // indices into the matches
};

// b. RANSAC pose of the query camera in the candidate map, on normalised coordinates; an error saying why when it
// fails.
Result<RansacPose> ransacPose(const CopiedKeyframe& q, const AgentCamera& camera,
                              const std::vector<Correspondence>& matches, const RecognitionOptions& options) {
  const double focal = camera.camera.calibration().fx;
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> image;
  object.reserve(matches.size());
  image.reserve(matches.size());
  for (const Correspondence& m : matches) {
    const Eigen::Vector3d ray = camera.camera.unproject(q.keypoints[m.keypoint].px.cast<double>());
    object.emplace_back(m.p_m.x(), m.p_m.y(), m.p_m.z());
    image.emplace_back(ray.x() / ray.z(), ray.y() / ray.z());
  }
  cv::Mat rvec;
  cv::Mat tvec;
  RansacPose out;
  cv::theRNG().state = options.seed;  // OpenCV's RANSAC samples from the thread's generator
  bool solved = false;
  try {
    solved = cv::solvePnPRansac(object, image, cv::Mat::eye(3, 3, CV_64F), cv::noArray(), rvec, tvec, false,
                                options.ransac_iterations, options.ransac_threshold_px / focal, 0.999, out.inliers,
                                cv::SOLVEPNP_AP3P);
  } catch (const cv::Exception& e) {
    return Error{ErrorCode::kNotFound, std::string("RANSAC failed: ") + e.what()};
  }
  if (!solved || static_cast<int>(out.inliers.size()) < options.min_ransac_inliers) {
    return Error{ErrorCode::kNotFound, std::to_string(out.inliers.size()) + " RANSAC inliers of " +
                                           std::to_string(matches.size()) + " matches (needs " +
                                           std::to_string(options.min_ransac_inliers) + ")"};
  }
  const Eigen::Vector3d rotation_vector(rvec.at<double>(0), rvec.at<double>(1), rvec.at<double>(2));
  const Eigen::Vector3d translation(tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2));
  out.T_c_m = geometry::SE3d(geometry::SO3d::exp(rotation_vector), translation);
  return out;
}

// c. Guided search: the points of the candidate's covisible neighbourhood that are not matched yet, projected into
// the query with T_c_m; each free query keypoint takes its closest point within the radius. Added to `support`.
void guidedSearch(const CopiedKeyframe& q, const AgentCamera& camera, const std::vector<CopiedPoint>& points,
                  const geometry::SE3d& T_c_m, const RecognitionOptions& options, PoseSupport& support) {
  std::unordered_set<MapPointId> have;
  std::vector<char> keypoint_taken(q.keypoints.size(), 0);
  for (const Correspondence& m : support.used) {
    have.insert(m.point);
    keypoint_taken[m.keypoint] = 1;
  }
  std::unordered_map<std::uint16_t, Correspondence> best_for_keypoint;
  const double radius2 = options.guided_radius_px * options.guided_radius_px;
  for (const CopiedPoint& p : points) {
    if (have.count(p.id) != 0) continue;
    const std::optional<Eigen::Vector2d> projected = camera.camera.project(T_c_m * p.p_w);
    if (!projected || projected->x() < 0.0 || projected->y() < 0.0 || projected->x() >= camera.camera.width() ||
        projected->y() >= camera.camera.height()) {
      continue;
    }
    int best = options.guided_max_distance + 1;
    int best_keypoint = -1;
    for (std::size_t kq = 0; kq < q.keypoints.size(); ++kq) {
      if (keypoint_taken[kq] != 0) continue;
      if ((q.keypoints[kq].px.cast<double>() - *projected).squaredNorm() > radius2) continue;
      const int d = features::hammingDistance(q.descriptors[kq], p.descriptor);
      if (d < best) {
        best = d;
        best_keypoint = static_cast<int>(kq);
      }
    }
    if (best_keypoint < 0) continue;
    const auto key = static_cast<std::uint16_t>(best_keypoint);
    const auto it = best_for_keypoint.find(key);
    if (it == best_for_keypoint.end() || best < it->second.distance) {
      best_for_keypoint[key] = Correspondence{key, p.id, p.p_w, best};
    }
  }
  std::vector<std::uint16_t> keys;
  for (const auto& [k, m] : best_for_keypoint) keys.push_back(k);
  std::sort(keys.begin(), keys.end());
  for (const std::uint16_t k : keys) support.add(q, best_for_keypoint[k]);
}

// The scale between the maps from the point pairs (query map position, candidate map position) that agree with the
// transform, when there are enough of them.
std::optional<std::pair<double, std::size_t>> pairScale(
    const std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>>& pairs, const geometry::SE3d& T_qmap_cmap,
    const RecognitionOptions& options) {
  std::vector<Eigen::Vector3d> from_candidate;
  std::vector<Eigen::Vector3d> in_query;
  for (const auto& [a, p_c] : pairs) {
    if ((a - T_qmap_cmap * p_c).norm() > options.pair_inlier_distance_m) continue;
    from_candidate.push_back(p_c);
    in_query.push_back(a);
  }
  if (static_cast<int>(from_candidate.size()) < options.min_pairs_for_scale) return std::nullopt;
  const Result<geometry::Sim3d> sim3 = geometry::alignSim3(from_candidate, in_query);
  if (!sim3.ok()) return std::nullopt;
  return std::pair{sim3->scale(), from_candidate.size()};
}

// The copies of the points a keyframe observes, each point once, first seen first (through `index`).
class PointCopier {
 public:
  explicit PointCopier(std::vector<CopiedPoint>& points) : points_(points) { points_.clear(); }
  // The index in the points of the point keypoint `k` of `kf` observes, copied if new; -1 when it observes none.
  std::int32_t copy(const MapContent& map, const ServerKeyframe& kf, std::size_t k) {
    if (!usablePoint(kf, k)) return -1;
    const ServerMapPoint* p = map.point(kf.point[k]);
    if (p == nullptr) return -1;
    const auto [it, added] = index_.emplace(p->id, static_cast<std::int32_t>(points_.size()));
    if (added) points_.push_back(CopiedPoint{p->id, p->p_w, p->descriptor});
    return it->second;
  }

 private:
  std::vector<CopiedPoint>& points_;
  std::unordered_map<MapPointId, std::int32_t> index_;
};

// A keyframe as verification reads it, its points copied through `points` and its links pointing at them.
CopiedKeyframe copyKeyframe(const MapContent& map, const ServerKeyframe& kf, PointCopier& points) {
  CopiedKeyframe copy;
  copy.id = kf.id;
  copy.T_w_s = kf.T_w_s;
  copy.keypoints = kf.keypoints;
  copy.descriptors = kf.descriptors;
  copy.point.assign(kf.keypoints.size(), -1);
  for (std::size_t k = 0; k < copy.point.size(); ++k) copy.point[k] = points.copy(map, kf, k);
  return copy;
}

}  // namespace

Status copyQuery(const MapContent& map, const KeyframeId& query, VerificationInput& input) {
  const ServerKeyframe* q = map.keyframe(query);
  if (q == nullptr) return Error(ErrorCode::kNotFound, "query keyframe " + query.toString() + " is not in its map");
  input.query_map = map.id();
  PointCopier points(input.query_points);
  input.query = copyKeyframe(map, *q, points);
  return Status::Ok();
}

Status copyCandidate(const MapContent& map, const KeyframeId& candidate, const RecognitionOptions& options,
                     VerificationInput& input) {
  const ServerKeyframe* c = map.keyframe(candidate);
  if (c == nullptr) {
    return Error(ErrorCode::kNotFound, "candidate keyframe " + candidate.toString() + " is not in its map");
  }
  input.candidate_map = map.id();
  PointCopier points(input.points);
  input.candidate = copyKeyframe(map, *c, points);
  // The neighbours only add points; their keyframes are not kept.
  for (const KeyframeId& n : mostCovisible(map, candidate, options.guided_neighbours)) {
    if (const ServerKeyframe* kf = map.keyframe(n); kf != nullptr) {
      for (std::size_t k = 0; k < kf->point.size(); ++k) (void)points.copy(map, *kf, k);
    }
  }
  return Status::Ok();
}

Verification verifyCopied(const KeyframeDatabase& database, const VerificationInput& input, double bow_score,
                          const CameraLookup& cameras, const RecognitionOptions& options) {
  Verification out;
  const auto reject = [&out](Rejection r, std::string detail) {
    out.rejection = r;
    out.detail = std::move(detail);
    return out;
  };
  const CopiedKeyframe& q = input.query;
  const CopiedKeyframe& c = input.candidate;
  const DatabaseEntry* qe = database.find(q.id);
  const DatabaseEntry* ce = database.find(c.id);
  const AgentCamera* camera = cameras(q.id.agent);
  if (qe == nullptr || ce == nullptr || camera == nullptr) {
    return reject(Rejection::kMissing,
                  "database entry or camera of " + q.id.toString() + " / " + c.id.toString() + " unknown");
  }
  const std::vector<Correspondence> matches = matchThroughDirectIndex(q, *qe, c, *ce, input.points, options);
  if (static_cast<int>(matches.size()) < options.min_matches) {
    return reject(Rejection::kTooFewMatches, std::to_string(matches.size()) + " descriptor matches (needs " +
                                                 std::to_string(options.min_matches) + ")");
  }
  const Result<RansacPose> ransac = ransacPose(q, *camera, matches, options);
  if (!ransac) return reject(Rejection::kPoseFailed, ransac.error().message());
  const RansacPose& pose = *ransac;
  PoseSupport support;
  for (const int index : pose.inliers) support.add(q, matches[static_cast<std::size_t>(index)]);
  geometry::SE3d T_c_m = refinePose(camera->camera, support.px, support.p_m, pose.T_c_m, options.max_reprojection_px);
  guidedSearch(q, *camera, input.points, T_c_m, options, support);
  T_c_m = refinePose(camera->camera, support.px, support.p_m, T_c_m, options.max_reprojection_px);
  const std::vector<bool> inlier =
      reprojectionInliers(camera->camera, support.px, support.p_m, T_c_m, options.max_reprojection_px);

  VerifiedMatch match;
  match.query = q.id;
  match.candidate = c.id;
  match.query_map = input.query_map;
  match.candidate_map = input.candidate_map;
  match.bow_score = bow_score;
  match.matches = static_cast<int>(matches.size());
  match.ransac_inliers = static_cast<int>(pose.inliers.size());
  match.T_cmap_cq = T_c_m.inverse();
  const geometry::SE3d T_qmap_cq = q.T_w_s * camera->T_s_c;
  match.T_qmap_cmap = T_qmap_cq * T_c_m;
  match.tilt_deg = tiltDeg(match.T_qmap_cmap);
  std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> pair_positions;  // query map, candidate map
  for (std::size_t i = 0; i < support.used.size(); ++i) {
    if (!inlier[i]) continue;
    const Correspondence& m = support.used[i];
    ++match.inliers;
    match.keypoint_matches.emplace_back(m.keypoint, m.point);
    if (const std::int32_t own = q.point[m.keypoint]; own >= 0) {
      const CopiedPoint& p = input.query_points[static_cast<std::size_t>(own)];
      match.point_pairs.emplace_back(p.id, m.point);
      pair_positions.emplace_back(p.p_w, m.p_m);
    }
  }
  std::ostringstream figures;
  figures << match.matches << " matches, " << match.ransac_inliers << " RANSAC inliers, " << match.inliers
          << " inliers after the guided search, tilt " << match.tilt_deg << " deg";
  if (match.inliers < options.min_inliers) {
    return reject(Rejection::kTooFewInliers,
                  figures.str() + " (needs " + std::to_string(options.min_inliers) + " inliers)");
  }
  out.match = match;
  if (match.tilt_deg > options.max_tilt_deg) {
    return reject(Rejection::kTilted, figures.str() + " (roll/pitch above " + std::to_string(options.max_tilt_deg) +
                                          " deg: the maps are gravity-aligned)");
  }
  if (const auto scale = pairScale(pair_positions, match.T_qmap_cmap, options)) {
    match.scale = scale->first;
    out.match = match;
    if (std::abs(scale->first - 1.0) > options.max_scale_error) {
      return reject(Rejection::kScale, figures.str() + ", scale " + std::to_string(scale->first) + " from " +
                                           std::to_string(scale->second) + " point pairs");
    }
  }
  out.detail = figures.str();
  return out;
}

Verification verifyCandidate(const KeyframeDatabase& database, const MapContent& query_map, const KeyframeId& query,
                             const MapContent& candidate_map, const KeyframeId& candidate, double bow_score,
                             const CameraLookup& cameras, const RecognitionOptions& options) {
  VerificationInput input;
  Status copied = copyQuery(query_map, query, input);
  if (copied) copied = copyCandidate(candidate_map, candidate, options, input);
  if (!copied) {
    Verification v;
    v.rejection = Rejection::kMissing;
    v.detail = copied.error().message();
    return v;
  }
  return verifyCopied(database, input, bow_score, cameras, options);
}

Result<RecognitionResult> recognize(const KeyframeDatabase& database, const MapContent& query_map,
                                    const KeyframeId& query, QueryKind kind, const MapLookup& maps,
                                    const CameraLookup& cameras, const RecognitionOptions& options) {
  Result<CandidateSearch> search = findCandidates(database, query_map, query, kind, maps, options);
  if (!search.ok()) return search.error();
  RecognitionResult result;
  result.search = std::move(search).value();
  for (const Candidate& c : result.search.candidates) {
    const MapContent* map = maps(c.map);
    if (map == nullptr) {
      Verification v;
      v.rejection = Rejection::kMissing;
      v.detail = "map " + std::to_string(c.map) + " unknown";
      result.verifications.push_back(std::move(v));
      continue;
    }
    Verification v = verifyCandidate(database, query_map, query, *map, c.keyframe, c.score, cameras, options);
    if (v.accepted() && (!result.best || v.match->inliers > result.best->inliers)) result.best = v.match;
    result.verifications.push_back(std::move(v));
  }
  return result;
}

}  // namespace cvislam::server::recognition
