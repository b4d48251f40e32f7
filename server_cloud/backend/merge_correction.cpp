#include "server_cloud/backend/merge_correction.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <unordered_map>
#include <utility>

#include "server_cloud/backend/map_fusion.hpp"

namespace cvislam::server::backend {

namespace {

using geometry::SE3d;

// The query keyframe and its `n` most covisible keyframes among those of its own map.
std::unordered_set<KeyframeId> queryWindow(const MapContent& map, const KeyframeId& query,
                                           const std::unordered_set<KeyframeId>& query_keyframes, int n) {
  std::vector<std::pair<int, KeyframeId>> ranked;
  for (const auto& [other, shared] : map.covisible(query)) {
    if (query_keyframes.count(other) != 0) ranked.emplace_back(shared, other);
  }
  const auto count = std::min<std::size_t>(ranked.size(), static_cast<std::size_t>(n));
  std::partial_sort(
      ranked.begin(), ranked.begin() + static_cast<std::ptrdiff_t>(count), ranked.end(),
      [](const auto& a, const auto& b) { return a.first > b.first || (a.first == b.first && a.second < b.second); });
  std::unordered_set<KeyframeId> out{query};
  for (std::size_t i = 0; i < count; ++i) out.insert(ranked[i].second);
  return out;
}

}  // namespace

SE3d fitFourDofChange(const std::vector<SE3d>& before, const std::vector<SE3d>& after) {
  // The mean change of the moves (windowChange, as an agent's frame follows its keyframes), its yaw kept; then,
  // given that rotation, the translation that fits the positions: the centroids.
  std::map<std::int64_t, TimedChange> moves;
  Eigen::Vector3d before_sum = Eigen::Vector3d::Zero();
  Eigen::Vector3d after_sum = Eigen::Vector3d::Zero();
  for (std::size_t i = 0; i < before.size(); ++i) {
    moves.emplace(static_cast<std::int64_t>(i), TimedChange{after[i] * before[i].inverse(), before[i].translation()});
    before_sum += before[i].translation();
    after_sum += after[i].translation();
  }
  const SE3d mean = windowChange(moves, static_cast<int>(moves.size()));
  const geometry::SO3d R_yaw = geometry::SO3d::exp(Eigen::Vector3d(0.0, 0.0, yawOf(mean.rotationMatrix())));
  const auto n = static_cast<double>(before.size());
  return SE3d(R_yaw, (after_sum - (R_yaw * before_sum)) / n);
}

Result<MergeCorrectionInput> copyMergeCorrection(const MapContent& map, const recognition::VerifiedMatch& match,
                                                 std::unordered_set<KeyframeId> query_keyframes, int keyframes,
                                                 const AgentSensorsMap& sensors) {
  const ServerKeyframe* query = map.keyframe(match.query);
  if (query == nullptr || map.keyframe(match.candidate) == nullptr) {
    return Error{ErrorCode::kFailedPrecondition, "the match's keyframes left the map before its correction"};
  }
  GbaWindow window;
  window.free = queryWindow(map, match.query, query_keyframes, keyframes);
  for (const KeyframeId& id : query_keyframes) {
    if (window.free.count(id) == 0) window.left_out.insert(id);
  }
  Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, sensors, &window);
  if (!snapshot) return snapshot.error();
  return MergeCorrectionInput{std::move(*snapshot), std::move(window.free), std::move(query_keyframes),
                              query->T_w_s.translation()};
}

Result<MergeCorrection> solveMergeCorrection(MergeCorrectionInput& input, const GlobalBaOptions& ba_options) {
  Result<GlobalBaSummary> ba = runGlobalBa(input.window, ba_options);
  if (!ba) return ba.error();
  std::vector<SE3d> before;
  std::vector<SE3d> after;
  for (const GbaKeyframe& kf : input.window.keyframes) {
    if (kf.held || input.window_keyframes.count(kf.id) == 0) continue;
    before.push_back(kf.T_w_s_before);
    after.push_back(kf.T_w_s);
  }
  if (before.empty()) {
    return Error{ErrorCode::kFailedPrecondition, "the merge correction's BA held every keyframe of its window"};
  }
  MergeCorrection out;
  out.ba = *ba;
  out.change = fitFourDofChange(before, after);
  if (!out.change.matrix().allFinite()) {
    return Error{ErrorCode::kFailedPrecondition, "the merge correction's fit is not finite"};
  }
  out.query_moved_m = (out.change * input.p_query_before - input.p_query_before).norm();
  out.query_moved_deg = out.change.so3().log().norm() * 180.0 / M_PI;
  out.keyframes.reserve(input.query_keyframes.size());
  for (const KeyframeId& id : input.query_keyframes) out.keyframes.push_back({id, SE3d(), out.change, std::nullopt});
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
