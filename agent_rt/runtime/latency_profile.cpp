#include "agent_rt/runtime/latency_profile.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numeric>

#include <nlohmann/json.hpp>

#include "common/core/percentile.hpp"

namespace cvislam::agent {

StageSummary summarise(const LatencyRecorder& recorder) {
  StageSummary s;
  s.name = recorder.name();
  std::vector<double> sorted = recorder.samplesMs();
  std::sort(sorted.begin(), sorted.end());
  s.count = sorted.size();
  if (sorted.empty()) return s;
  s.p50_ms = nearestRankPercentile(sorted, 0.50);
  s.p90_ms = nearestRankPercentile(sorted, 0.90);
  s.p99_ms = nearestRankPercentile(sorted, 0.99);
  s.max_ms = sorted.back();
  s.mean_ms = std::accumulate(sorted.begin(), sorted.end(), 0.0) / static_cast<double>(sorted.size());
  return s;
}

std::string formatLatencyTable(const std::vector<StageSummary>& stages) {
  std::string out = "stage                          count      p50      p90      p99      max   [ms]\n";
  char line[160];
  for (const StageSummary& s : stages) {
    std::snprintf(line, sizeof(line), "%-28s %7zu %8.2f %8.2f %8.2f %8.2f\n", s.name.c_str(), s.count, s.p50_ms,
                  s.p90_ms, s.p99_ms, s.max_ms);
    out += line;
  }
  return out;
}

std::string latencyJson(const std::vector<StageSummary>& stages) {
  nlohmann::json j = nlohmann::json::object();
  for (const StageSummary& s : stages) {
    j[s.name] = {{"count", s.count},   {"p50_ms", s.p50_ms}, {"p90_ms", s.p90_ms},
                 {"p99_ms", s.p99_ms}, {"max_ms", s.max_ms}, {"mean_ms", s.mean_ms}};
  }
  return j.dump(2) + "\n";
}

}  // namespace cvislam::agent
