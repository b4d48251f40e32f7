// A merge's correction, right after the merge and before its GBA (BackendOptions::merge_correction_keyframes).
//
// The match's transform comes from one keyframe and is a few cm off. Both maps were consistent on their own
// before (each refined by its own GBAs), so what is wrong after the merge is where one sits in the other, and that
// is a rigid transform. The correction estimates it better and moves the query's map by it, rigidly:
//   - a BA of the query keyframe and its N most covisible keyframes of the query's map, over the points they see
//     (those just fused with the candidate's among them), with the candidate map's keyframes that see those points
//     held and the query map's other keyframes left out: it puts that window where the candidate's map sees it;
//   - the 4-DoF change (yaw about gravity and translation) that fits the window's keyframes' moves best: the mean
//     rotation of their changes, its yaw kept, and the translation that then fits their positions;
//   - that one change for every keyframe of the query's map (and its points, through their reference keyframes).
// A rigid change keeps each map exactly as self-consistent as it was: IMU factors between consecutive keyframes,
// points against their observations, an agent's world frame against its local map. A map bent by a few iterations
// of a window BA and a pose graph instead starts its GBA from a much higher cost, and the agents hold anchors that
// disagree with their own keyframes until it ends (on the simulated euroc-mh mono mission the agents' onboard ATE
// was 1.9-3.1 cm that way against 1.0-1.4 without a correction).
// Plain functions on copies: the caller copies under the map's read lock, solves without a lock and applies the
// result under the write lock (applyToMission, keeping the keyframes' refined state).
#pragma once

#include <unordered_set>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/recognition/place_recognition.hpp"

namespace cvislam::server::backend {

// What the solve needs, copied from the merged map.
struct MergeCorrectionInput {
  GbaSnapshot window;                                        // the BA of the query's window
  std::unordered_set<KeyframeId> window_keyframes;           // the query keyframe and its N most covisible of its map
  std::unordered_set<KeyframeId> query_keyframes;            // every keyframe of the query's map, before it went
  Eigen::Vector3d p_query_before = Eigen::Vector3d::Zero();  // the query keyframe's position
};

// Copies the input; kFailedPrecondition when the match's keyframes are gone or an agent's sensors are unknown.
Result<MergeCorrectionInput> copyMergeCorrection(const MapContent& map, const recognition::VerifiedMatch& match,
                                                 std::unordered_set<KeyframeId> query_keyframes, int keyframes,
                                                 const AgentSensorsMap& sensors);

struct MergeCorrection {
  geometry::SE3d change;  // 4-DoF, in the merged map's frame
  // One per keyframe of the query's map: before = identity, after = `change`, so that applyCorrections moves each
  // by `change` as it is when applied (and the keyframes their agents added meanwhile with it).
  std::vector<KeyframeCorrection> keyframes;
  GlobalBaSummary ba;
  double query_moved_m = 0.0;
  double query_moved_deg = 0.0;
};

// The BA and the fit, on the input (which the BA changes). kFailedPrecondition when the BA moved no keyframe of
// the window or gave a change that is not finite.
Result<MergeCorrection> solveMergeCorrection(MergeCorrectionInput& input, const GlobalBaOptions& ba_options);

// The 4-DoF change that fits keyframes' moves (`before[i]` to `after[i]`, at least one): the yaw of their mean
// rotation change, and the translation that then fits their positions in the least-squares sense.
geometry::SE3d fitFourDofChange(const std::vector<geometry::SE3d>& before, const std::vector<geometry::SE3d>& after);

// How far `corrections` move keyframe `id` in its own frame, in metres and degrees; zero when they do not hold it.
struct Move {
  double m = 0.0;
  double deg = 0.0;
};
Move moveOf(const std::vector<KeyframeCorrection>& corrections, const KeyframeId& id);

}  // namespace cvislam::server::backend
