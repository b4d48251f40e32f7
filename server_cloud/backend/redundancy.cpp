#include "server_cloud/backend/redundancy.hpp"

#include <algorithm>
#include <map>
#include <unordered_map>

namespace cvislam::server::backend {

Status RedundancyOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "redundancy." + what}; };
  if (!(redundant_fraction > 0.0 && redundant_fraction <= 1.0)) return bad("redundant_fraction must be in (0, 1]");
  if (min_other_observers < 1) return bad("min_other_observers must be >= 1");
  if (!(max_imu_gap_s > 0.0)) return bad("max_imu_gap_s must be positive");
  if (keep_newest < 1) return bad("keep_newest must be >= 1 (the agent's next keyframe links to its newest)");
  if (checks_per_round < 1) return bad("checks_per_round must be >= 1");
  if (min_point_observations < 1) return bad("min_point_observations must be >= 1");
  return Status::Ok();
}

double coveredFraction(const MapContent& map, const KeyframeId& id, const RedundancyOptions& options) {
  const ServerKeyframe* kf = map.keyframe(id);
  if (kf == nullptr) return 0.0;
  int points = 0;
  int covered = 0;
  for (std::size_t k = 0; k < kf->has_point.size(); ++k) {
    if (kf->has_point[k] == 0) continue;
    const ServerMapPoint* p = map.point(kf->point[k]);
    if (p == nullptr) continue;
    ++points;
    if (static_cast<int>(p->observations.size()) - 1 >= options.min_other_observers) ++covered;
  }
  return points == 0 ? 0.0 : static_cast<double>(covered) / static_cast<double>(points);
}

bool isRedundant(const MapContent& map, const KeyframeId& id, const RedundancyOptions& options) {
  // A keyframe without points has fraction 0, below any valid redundant_fraction.
  return coveredFraction(map, id, options) >= options.redundant_fraction;
}

RedundancyReport removeRedundantKeyframes(MapContent& map, const AgentSensorsMap& sensors,
                                          const RedundancyOptions& options, std::mt19937_64& rng) {
  RedundancyReport report;
  if (!options.enabled || map.keyframes().empty()) return report;
  // Per agent map, keyframes by time; the newest keep_newest are not eligible.
  std::map<std::pair<AgentId, std::uint32_t>, std::vector<std::pair<std::int64_t, KeyframeId>>> series;
  std::unordered_map<KeyframeId, KeyframeId> successor;  // IMU links: predecessor -> successor
  for (const auto& [id, kf] : map.keyframes()) {
    series[{id.agent, kf.agent_map}].emplace_back(kf.t_ns, id);
    if (kf.imu_from) successor.emplace(*kf.imu_from, id);
  }
  std::vector<KeyframeId> eligible;
  for (auto& [key, list] : series) {
    std::sort(list.begin(), list.end());
    const auto end = list.size() > static_cast<std::size_t>(options.keep_newest)
                         ? list.size() - static_cast<std::size_t>(options.keep_newest)
                         : 0;
    for (std::size_t i = 0; i < end; ++i) eligible.push_back(list[i].second);
  }
  std::sort(eligible.begin(), eligible.end());  // the random pick must not depend on hash order
  for (int round = 0; round < options.checks_per_round && !eligible.empty(); ++round) {
    std::uniform_int_distribution<std::size_t> pick(0, eligible.size() - 1);
    const std::size_t at = pick(rng);
    const KeyframeId id = eligible[at];
    eligible[at] = eligible.back();
    eligible.pop_back();
    ++report.checked;
    if (!isRedundant(map, id, options)) continue;
    ++report.redundant;

    ServerKeyframe* kf = map.keyframe(id);
    const auto next = successor.find(id);
    ServerKeyframe* after = next != successor.end() ? map.keyframe(next->second) : nullptr;
    if (after != nullptr) {
      // Its successor's IMU link must now reach back to its predecessor, within the gap.
      const ServerKeyframe* before = kf->imu_from ? map.keyframe(*kf->imu_from) : nullptr;
      if (before == nullptr || static_cast<double>(after->t_ns - before->t_ns) * 1e-9 > options.max_imu_gap_s) {
        ++report.kept_for_imu_gap;
        continue;
      }
      const auto sensor = sensors.find(id.agent);
      if (sensor == sensors.end()) continue;
      std::vector<dataset::ImuSample> joined = kf->imu;
      const std::int64_t last = joined.empty() ? before->t_ns : joined.back().t_ns;
      for (const dataset::ImuSample& s : after->imu) {
        if (s.t_ns > last) joined.push_back(s);
      }
      imu::Preintegration preintegration(before->bias, sensor->second.imu_noise);
      if (!preintegration.integrateInterval(joined, before->t_ns, after->t_ns).ok()) {
        ++report.kept_for_imu_gap;
        continue;
      }
      after->imu = std::move(joined);
      after->imu_from = before->id;
      after->preintegration = preintegration;
      successor[before->id] = after->id;
    } else if (kf->imu_from) {
      continue;  // the newest of its IMU chain: the agent's next keyframe may still link to it
    }
    std::vector<MapPointId> touched;
    for (std::size_t k = 0; k < kf->has_point.size(); ++k) {
      if (kf->has_point[k] != 0) touched.push_back(kf->point[k]);
    }
    std::vector<MapPointId> went;
    if (!map.removeKeyframe(id, &went).ok()) continue;
    successor.erase(id);
    report.removed_keyframes.push_back(id);
    report.removed_points.insert(report.removed_points.end(), went.begin(), went.end());
    for (const MapPointId& p : touched) {
      const ServerMapPoint* point = map.point(p);
      if (point == nullptr || static_cast<int>(point->observations.size()) >= options.min_point_observations) continue;
      if (map.removePoint(p).ok()) report.removed_points.push_back(p);
    }
  }
  return report;
}

}  // namespace cvislam::server::backend
