// Map fusion (CVI-SLAM IV-F) and the point fusion that loop closure shares with it.
//
// A verified match between two maps says where the query keyframe's camera is in the candidate's map. Both
// maps are metric and gravity-aligned, so the query map moves into the candidate map by a 4-DoF transform:
// the yaw of the match's rotation about gravity (z) and the translation that puts the query keyframe where the
// match saw it. The match's roll and pitch (a few tenths of a degree of noise) are dropped.
//
// Duplicated points (one physical point made by both maps) are then fused: first the pairs the match found,
// then a projection search: the points of the candidate's covisible neighbourhood are projected into the
// query's neighbourhood keyframes, and a keypoint close to the projection with a close descriptor observes the
// point; when the keypoint already observes another point, the two become one (the point seen more keeps).
//
// Every new keyframe is fused the same way (ORB-SLAM's SearchAndFuse, run on the server): with its covisible
// keyframes and with the map's nearby keyframes that look the same way. The nearby ones find what another
// agent, or an earlier pass of the same agent, made of the same place: without a downlink an agent cannot
// know those points, so it makes them again, and only the server can join them.
#pragma once

#include <unordered_set>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/recognition/place_recognition.hpp"
#include "server_cloud/stack/map_content.hpp"

namespace cvislam::server::backend {

struct FusionOptions {
  int neighbours = 10;            // a keyframe's neighbourhood: itself and its most covisible keyframes
  double search_radius_px = 5.0;  // at octave 0; grows with the pyramid scale of the point's octave
  int max_descriptor_distance = 50;
  double pyramid_scale_factor = 1.2;
  // A new keyframe's fusion partners: its `neighbours` most covisible keyframes and up to `nearby_keyframes`
  // nearest keyframes of the map within `nearby_radius_m` whose optical axes are within `nearby_max_angle_deg`
  // of its own.
  int nearby_keyframes = 10;
  double nearby_radius_m = 3.0;
  double nearby_max_angle_deg = 45.0;

  [[nodiscard]] Status validate() const;
};

struct FusionReport {
  int pairs_fused = 0;        // the match's point pairs
  int keypoints_linked = 0;   // the match's keypoint inliers that now observe the candidate's point
  int projection_fused = 0;   // duplicates found by projection
  int projection_linked = 0;  // keypoints without a point that now observe one
};

// One keypoint found for a point by projection: `keypoint` of `keyframe` should observe `point`.
struct ProjectionMatch {
  KeyframeId keyframe;
  std::uint16_t keypoint = 0;
  MapPointId point;
};

// The 4-DoF transform (yaw about z, translation) closest to T_to_from that maps `p_from_anchor` exactly to
// T_to_from * p_from_anchor.
geometry::SE3d fourDofTransform(const geometry::SE3d& T_to_from, const Eigen::Vector3d& p_from_anchor);

// Yaw about z of a rotation (ZYX Euler angles), in radians.
double yawOf(const Eigen::Matrix3d& R);

// The keyframe and its `count` most covisible keyframes (fewer when it has fewer neighbours).
std::vector<KeyframeId> neighbourhood(const MapContent& map, const KeyframeId& keyframe, int count);

// The points the keyframes observe (each once).
std::vector<MapPointId> pointsOf(const MapContent& map, const std::vector<KeyframeId>& keyframes);

// The keyframes of the map nearest to `keyframe`, within the radius and viewing angle of `options`, nearest first.
std::vector<KeyframeId> nearbyKeyframes(const MapContent& map, const KeyframeId& keyframe,
                                        const recognition::CameraLookup& cameras, const FusionOptions& options);

// What a projection search needs from the map, copied under the map's read lock so that the search itself runs
// without any lock. The cameras point into the lookup's table, which must outlive the input.
struct ProjectionSearchInput {
  struct Target {
    KeyframeId id;
    geometry::SE3d T_c_w;
    const recognition::AgentCamera* camera = nullptr;
    std::vector<features::Keypoint> keypoints;
    std::vector<features::Descriptor> descriptors;
    std::unordered_set<MapPointId> observed;  // points it observes already
  };
  struct Point {
    MapPointId id;
    Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
    features::Descriptor descriptor{};
    std::uint8_t octave = 0;
  };
  std::vector<Target> targets;
  std::vector<Point> points;
};

ProjectionSearchInput gatherProjectionSearch(const MapContent& map, const std::vector<KeyframeId>& keyframes,
                                             const std::vector<MapPointId>& points,
                                             const recognition::CameraLookup& cameras);

// Projects the points into the targets and finds, for each, the keypoint close to the projection with the closest
// descriptor (within the options' bounds). Touches no map.
std::vector<ProjectionMatch> searchByProjection(const ProjectionSearchInput& input, const FusionOptions& options);

// gatherProjectionSearch, then searchByProjection.
std::vector<ProjectionMatch> searchByProjection(const MapContent& map, const std::vector<KeyframeId>& keyframes,
                                                const std::vector<MapPointId>& points,
                                                const recognition::CameraLookup& cameras, const FusionOptions& options);

// Links or fuses each match (see the header comment), checking each against the map as it is now. Adds to `report`.
void applyProjectionMatches(MapContent& map, const std::vector<ProjectionMatch>& matches, FusionReport& report);

// Projects `points` into `keyframes` and links or fuses: searchByProjection, then applyProjectionMatches.
void fuseByProjection(MapContent& map, const std::vector<KeyframeId>& keyframes, const std::vector<MapPointId>& points,
                      const recognition::CameraLookup& cameras, const FusionOptions& options, FusionReport& report);

// Everything a verified match lets the (single, already joined) map fuse: its point pairs, its keypoint inliers,
// then the projection search between the two neighbourhoods.
FusionReport fuseMatch(MapContent& map, const recognition::VerifiedMatch& match,
                       const recognition::CameraLookup& cameras, const FusionOptions& options);
// The same in steps, so that the search holds no lock: this fuses the pairs and inliers and copies what the
// projection search needs (the map write-locked); searchByProjection(input) then runs without a lock, and
// applyProjectionMatches under the write lock again.
ProjectionSearchInput fuseMatchPairs(MapContent& map, const recognition::VerifiedMatch& match,
                                     const recognition::CameraLookup& cameras, const FusionOptions& options,
                                     FusionReport& report);

// A new keyframe's fusion with its partners, both ways: its partners' points projected into it, and its points
// projected into its partners.
struct NewKeyframeSearch {
  ProjectionSearchInput into_keyframe;
  ProjectionSearchInput into_partners;
};
NewKeyframeSearch gatherNewKeyframeSearch(const MapContent& map, const KeyframeId& keyframe,
                                          const recognition::CameraLookup& cameras, const FusionOptions& options);
std::vector<ProjectionMatch> searchNewKeyframe(const NewKeyframeSearch& search, const FusionOptions& options);
// Both, on the map (which must stay unchanged meanwhile).
std::vector<ProjectionMatch> searchNewKeyframe(const MapContent& map, const KeyframeId& keyframe,
                                               const recognition::CameraLookup& cameras, const FusionOptions& options);

}  // namespace cvislam::server::backend
