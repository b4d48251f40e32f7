#include "server_cloud/backend/merge_correction.hpp"

#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <utility>

namespace cvislam::server::backend {

namespace {

using geometry::SE3d;

// The keyframes around a match: the query's and the candidate's `n` most covisible ones each, with themselves.
std::unordered_set<KeyframeId> aroundMatch(const MapContent& map, const recognition::VerifiedMatch& match, int n) {
  std::unordered_set<KeyframeId> out{match.query, match.candidate};
  for (const KeyframeId& centre : {match.query, match.candidate}) {
    std::vector<std::pair<int, KeyframeId>> ranked;
    for (const auto& [other, shared] : map.covisible(centre)) ranked.emplace_back(shared, other);
    const auto count = std::min<std::size_t>(ranked.size(), static_cast<std::size_t>(n));
    std::partial_sort(
        ranked.begin(), ranked.begin() + static_cast<std::ptrdiff_t>(count), ranked.end(),
        [](const auto& a, const auto& b) { return a.first > b.first || (a.first == b.first && a.second < b.second); });
    for (std::size_t i = 0; i < count; ++i) out.insert(ranked[i].second);
  }
  return out;
}

// Readies the pose graph once the BA has placed `placed` (see the header). Returns the keyframes held where they
// are.
std::unordered_set<KeyframeId> holdForMerge(PoseGraph& graph, const std::vector<KeyframeCorrection>& placed,
                                            const std::unordered_set<KeyframeId>& query_keyframes) {
  std::erase_if(graph.edges, [&](const PoseGraph::Edge& e) {
    return query_keyframes.count(graph.nodes[static_cast<std::size_t>(e.a)].id) !=
           query_keyframes.count(graph.nodes[static_cast<std::size_t>(e.b)].id);
  });
  std::unordered_map<KeyframeId, SE3d> after;
  for (const KeyframeCorrection& c : placed) after.emplace(c.id, c.T_w_s_after);
  std::unordered_set<KeyframeId> unchanged;
  for (PoseGraph::Node& node : graph.nodes) {
    if (const auto it = after.find(node.id); it != after.end()) {
      node.held_at = it->second;
    } else if (query_keyframes.count(node.id) == 0) {
      node.held_at = node.T_w_s;
      unchanged.insert(node.id);
    }
  }
  return unchanged;
}

}  // namespace

Result<MergeCorrectionInput> copyMergeCorrection(const MapContent& map, const recognition::VerifiedMatch& match,
                                                 std::unordered_set<KeyframeId> query_keyframes, int keyframes,
                                                 const AgentSensorsMap& sensors, const std::vector<LoopEdge>& loops,
                                                 const PoseGraphOptions& options) {
  if (map.keyframe(match.query) == nullptr || map.keyframe(match.candidate) == nullptr) {
    return Error{ErrorCode::kFailedPrecondition, "the match's keyframes left the map before its correction"};
  }
  GbaWindow window;
  window.free = aroundMatch(map, match, keyframes);
  for (const KeyframeId& id : query_keyframes) {
    if (window.free.count(id) == 0) window.left_out.insert(id);
  }
  Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, sensors, &window);
  if (!snapshot) return snapshot.error();
  return MergeCorrectionInput{std::move(*snapshot), buildPoseGraph(map, loops, options), std::move(query_keyframes)};
}

Result<MergeCorrection> solveMergeCorrection(MergeCorrectionInput& input, const GlobalBaOptions& ba_options,
                                             const PoseGraphOptions& graph_options) {
  Result<GlobalBaSummary> ba = runGlobalBa(input.window, ba_options);
  if (!ba) return ba.error();
  MergeCorrection out;
  out.ba = *ba;
  out.keyframes = keyframeCorrections(input.window);
  out.points = pointCorrections(input.window);
  out.unchanged = holdForMerge(input.graph, out.keyframes, input.query_keyframes);
  Result<std::vector<KeyframeCorrection>> carried = solvePoseGraph(input.graph, graph_options);
  if (!carried) return carried.error();
  out.graph = input.graph.summary;
  out.keyframes.insert(out.keyframes.end(), carried->begin(), carried->end());
  return out;
}

Move moveOf(const std::vector<KeyframeCorrection>& corrections, const KeyframeId& id) {
  for (const KeyframeCorrection& c : corrections) {
    if (c.id != id) continue;
    const SE3d delta = c.T_w_s_before.inverse() * c.T_w_s_after;
    return {delta.translation().norm(), delta.so3().log().norm() * 180.0 / M_PI};
  }
  return {};
}

}  // namespace cvislam::server::backend
