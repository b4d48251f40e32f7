// A merge's correction, right after the merge and before its GBA (BackendOptions::merge_correction_keyframes).
//
// The match's transform comes from one keyframe and is a few cm off. Two solves take that out:
//   - a BA of the keyframes around the match (the query's and the candidate's N most covisible ones each) over
//     the points just fused, with the candidate map's keyframes that see those points held and the query map's
//     others left out;
//   - a 4-DoF pose graph of the whole merged map that holds the BA's keyframes where it put them and the candidate
//     map's others where they are, and carries the query map's others along its own edges. Edges between the two
//     maps came with the fusion, and their relative poses carry the match's error: they are left out.
// Plain functions on copies: the caller copies under the map's read lock, solves without a lock and applies the
// result under the write lock (applyToMission, with `unchanged` as the held keyframes).
#pragma once

#include <unordered_set>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/backend/pose_graph.hpp"
#include "server_cloud/recognition/place_recognition.hpp"

namespace cvislam::server::backend {

// What both solves need, copied from the merged map.
struct MergeCorrectionInput {
  GbaSnapshot window;  // the BA around the match
  PoseGraph graph;     // the whole map as it is
  std::unordered_set<KeyframeId> query_keyframes;
};

// Copies the input; kFailedPrecondition when the match's keyframes are gone or an agent's sensors are unknown.
Result<MergeCorrectionInput> copyMergeCorrection(const MapContent& map, const recognition::VerifiedMatch& match,
                                                 std::unordered_set<KeyframeId> query_keyframes, int keyframes,
                                                 const AgentSensorsMap& sensors, const std::vector<LoopEdge>& loops,
                                                 const PoseGraphOptions& options);

struct MergeCorrection {
  std::vector<KeyframeCorrection> keyframes;  // the BA's, then the pose graph's
  std::vector<PointCorrection> points;        // the BA's
  std::unordered_set<KeyframeId> unchanged;   // the candidate map's keyframes held where they are
  GlobalBaSummary ba;
  PoseGraphSummary graph;
};

// Both solves, on the input (which they change).
Result<MergeCorrection> solveMergeCorrection(MergeCorrectionInput& input, const GlobalBaOptions& ba_options,
                                             const PoseGraphOptions& graph_options);

// How far `corrections` move keyframe `id`, in metres and degrees; zero when they do not hold it.
struct Move {
  double m = 0.0;
  double deg = 0.0;
};
Move moveOf(const std::vector<KeyframeCorrection>& corrections, const KeyframeId& id);

}  // namespace cvislam::server::backend
