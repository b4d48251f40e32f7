// Place recognition for one query keyframe (CVI-SLAM IV-A loop detection and IV-F map matching): where has an
// agent been before in its own map (a loop), and where does another map see the same place (a map match).
//
// 1. Candidates (findCandidates): the keyframe database's BoW candidates in scope (the query's map without the
//    query's covisible neighbours, or every other map), scoring at least
//    max(min_score, min_score_ratio * the query's best score against its covisible neighbours); grouped by the
//    candidate's covisibility (a group scores the sum of its members' scores); the best keyframe of every group
//    scoring at least group_score_ratio of the best group.
// 2. Verification (verifyCandidate), for each candidate:
//    a. descriptor matching between the query's keypoints and the candidate's keypoints that observe a map
//       point, only between features under the same vocabulary node (the direct index), with Lowe's ratio test;
//    b. the query camera's pose in the candidate's map from these 2D-3D correspondences by RANSAC (OpenCV
//       calib3d, AP3P), then refined by minimising reprojection error over the inliers;
//    c. a guided search: the map points of the candidate's covisible neighbourhood are projected into the query
//       and matched to keypoints near their projection; the pose is refined again on all matches and the
//       inliers (reprojection error within max_reprojection_px) are counted;
//    d. the relative transform T_qmap_cmap (candidate map into the query's map), from the query keyframe's pose
//       in its own map. Both maps are metric and gravity-aligned, so a true match has roll and pitch near zero:
//       a tilt above max_tilt_deg rejects it. The query's own map points matched to candidate map points give
//       point pairs; where there are enough, their Sim3 alignment checks the scale.
// The output, a VerifiedMatch, is what map fusion and loop closure consume.
//
// Reads the maps it is given and writes nothing; the caller holds what makes that safe (a read lock or a copy).
// Verification runs on a VerificationInput, a flat copy of the two keyframes and the neighbourhood's points it
// reads, so that the server's worker copies under a map's read lock and verifies with no lock held.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include "common/camera/camera_model.hpp"
#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/recognition/keyframe_database.hpp"
#include "server_cloud/stack/map_content.hpp"

namespace cvislam::server::recognition {

struct RecognitionOptions {
  // Candidates.
  double min_score = 0.01;               // absolute BoW floor
  double min_score_ratio = 0.25;         // of the query's best covisible neighbour's score
  int neighbour_min_shared_points = 15;  // a covisible neighbour (paper: >= 15 shared map points)
  double min_common_words_ratio = 0.8;
  int group_neighbours = 10;        // a candidate's group: itself and its most covisible keyframes
  double group_score_ratio = 0.75;  // of the best group's score
  int max_candidates = 5;           // verified per query, best group first
  // A loop needs this much time between the two keyframes of the agent (a revisit seconds later is tracking's).
  double loop_min_interval_s = 10.0;
  // Matching.
  int direct_level = 2;  // vocabulary node level of the direct index (0 = root)
  int max_descriptor_distance = 50;
  float match_ratio = 0.75F;
  int min_matches = 20;
  // Pose.
  int ransac_iterations = 300;
  double ransac_threshold_px = 4.0;
  int min_ransac_inliers = 15;
  double max_reprojection_px = 4.0;  // inlier threshold after refinement
  // Guided search.
  int guided_neighbours = 10;  // the candidate's most covisible keyframes whose points are projected
  double guided_radius_px = 8.0;
  int guided_max_distance = 50;
  // Acceptance.
  int min_inliers = 40;
  double max_tilt_deg = 5.0;            // roll/pitch of T_qmap_cmap
  int min_pairs_for_scale = 12;         // point pairs needed to check the scale
  double max_scale_error = 0.15;        // |s - 1| of the pairs' Sim3 alignment
  double pair_inlier_distance_m = 0.3;  // a pair agrees with T_qmap_cmap within this (for the scale check)
  std::uint64_t seed = 1;               // RANSAC sampling

  [[nodiscard]] Status validate() const;
  [[nodiscard]] std::string describe() const;
};

// The camera an agent's keypoints were measured with, and where it sits on the body.
struct AgentCamera {
  camera::CameraModel camera;
  geometry::SE3d T_s_c;
};
using CameraLookup = std::function<const AgentCamera*(AgentId)>;
using MapLookup = std::function<const MapContent*(MapId)>;

enum class QueryKind { kLoop, kMapMatch };
std::string_view toString(QueryKind kind);

struct Candidate {
  KeyframeId keyframe;
  MapId map = 0;
  double score = 0.0;        // BoW score with the query
  double group_score = 0.0;  // its covisibility group's
};

struct CandidateSearch {
  double min_score = 0.0;  // the floor that applied
  double best_neighbour_score = 0.0;
  int bow_candidates = 0;  // what the database returned
  std::vector<Candidate> candidates;
};

// The candidates of `query` (held in `database` and in `query_map`). `maps` finds candidate maps. In three steps
// that the server's worker takes under one map's lock at a time: scoreCandidates (the query's map), the
// candidates' groupNeighbours (each candidate's map), groupCandidates (no map).
Result<CandidateSearch> findCandidates(const KeyframeDatabase& database, const MapContent& query_map,
                                       const KeyframeId& query, QueryKind kind, const MapLookup& maps,
                                       const RecognitionOptions& options);

// The database's candidates above the floor, before grouping.
struct ScoredCandidates {
  CandidateSearch search;  // min_score, best_neighbour_score, bow_candidates; no candidates yet
  std::vector<BowCandidate> bow;
};
Result<ScoredCandidates> scoreCandidates(const KeyframeDatabase& database, const MapContent& query_map,
                                         const KeyframeId& query, QueryKind kind, const RecognitionOptions& options);
// A candidate's group_neighbours most covisible keyframes in its map.
std::vector<KeyframeId> groupNeighbours(const MapContent& map, const KeyframeId& keyframe,
                                        const RecognitionOptions& options);
// A candidate's groupNeighbours, or nullptr when they are unknown (its map went).
using NeighbourLookup = std::function<const std::vector<KeyframeId>*(const KeyframeId&)>;
NeighbourLookup neighbourLookup(const std::unordered_map<KeyframeId, std::vector<KeyframeId>>& around);
CandidateSearch groupCandidates(ScoredCandidates scored, const NeighbourLookup& neighbours,
                                const RecognitionOptions& options);

struct VerifiedMatch {
  KeyframeId query;
  KeyframeId candidate;
  MapId query_map = 0;
  MapId candidate_map = 0;
  geometry::SE3d T_qmap_cmap;  // the candidate map's frame into the query map's frame
  geometry::SE3d T_cmap_cq;    // the query camera's pose in the candidate map
  double bow_score = 0.0;
  int matches = 0;         // descriptor matches through the direct index
  int ransac_inliers = 0;  // of those
  int inliers = 0;         // after the guided search
  double tilt_deg = 0.0;
  std::optional<double> scale;  // of the point pairs' Sim3 alignment, where there were enough
  // (query map point, candidate map point) for the same physical point.
  std::vector<std::pair<MapPointId, MapPointId>> point_pairs;
  // (query keypoint, candidate map point) inliers.
  std::vector<std::pair<std::uint16_t, MapPointId>> keypoint_matches;
};

enum class Rejection {
  kNone,
  kMissing,        // a keyframe, its database entry or its camera is unknown
  kTooFewMatches,  // descriptor matches below min_matches
  kPoseFailed,     // RANSAC found no pose, or too few inliers
  kTooFewInliers,  // below min_inliers after the guided search
  kTilted,         // roll/pitch above max_tilt_deg
  kScale,          // the point pairs disagree on scale
};
std::string_view toString(Rejection rejection);

struct Verification {
  Rejection rejection = Rejection::kNone;
  std::string detail;                  // why, in words, with the figures
  std::optional<VerifiedMatch> match;  // set when accepted (and, for kTilted and kScale, what was found)
  [[nodiscard]] bool accepted() const { return rejection == Rejection::kNone; }
};

// What verifying one candidate reads of the two maps, copied (copyQuery, copyCandidate).
struct VerificationInput {
  struct Point {
    MapPointId id;
    Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
    features::Descriptor descriptor{};
  };
  struct Keyframe {
    KeyframeId id;
    geometry::SE3d T_w_s;
    std::vector<features::Keypoint> keypoints;
    std::vector<features::Descriptor> descriptors;
    std::vector<std::int32_t> point;  // per keypoint: the index of the point it observes in its points, or -1
  };
  MapId query_map = 0;
  Keyframe query;
  std::vector<Point> query_points;
  MapId candidate_map = 0;
  Keyframe candidate;
  // The candidate's points, then those of its guided_neighbours most covisible keyframes (the guided search's
  // neighbourhood), each point once, first seen first: the order the guided search breaks ties in.
  std::vector<Point> points;
};

// Copy the query keyframe and its points from its map (kNotFound when it is not there), or the candidate, its
// neighbourhood and their points from the candidate's map.
Status copyQuery(const MapContent& map, const KeyframeId& query, VerificationInput& input);
Status copyCandidate(const MapContent& map, const KeyframeId& candidate, const RecognitionOptions& options,
                     VerificationInput& input);

// The verification of a copied candidate: needs no map and no lock.
Verification verifyCopied(const KeyframeDatabase& database, const VerificationInput& input, double bow_score,
                          const CameraLookup& cameras, const RecognitionOptions& options);

// copyQuery and copyCandidate from the maps, then verifyCopied.
Verification verifyCandidate(const KeyframeDatabase& database, const MapContent& query_map, const KeyframeId& query,
                             const MapContent& candidate_map, const KeyframeId& candidate, double bow_score,
                             const CameraLookup& cameras, const RecognitionOptions& options);

struct RecognitionResult {
  CandidateSearch search;
  std::vector<Verification> verifications;  // one per candidate, in order
  std::optional<VerifiedMatch> best;        // the accepted match with the most inliers
};

// findCandidates, then verifyCandidate on each.
Result<RecognitionResult> recognize(const KeyframeDatabase& database, const MapContent& query_map,
                                    const KeyframeId& query, QueryKind kind, const MapLookup& maps,
                                    const CameraLookup& cameras, const RecognitionOptions& options);

}  // namespace cvislam::server::recognition
