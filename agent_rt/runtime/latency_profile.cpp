#include "agent_rt/runtime/latency_profile.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numeric>

#include <nlohmann/json.hpp>

namespace cvislam::agent {

namespace {
double percentile(const std::vector<double>& sorted, double p) {
  if (sorted.empty()) return 0.0;
  const auto rank = static_cast<std::size_t>(std::ceil(p / 100.0 * static_cast<double>(sorted.size())));
  return sorted[std::min(sorted.size() - 1, rank == 0 ? 0 : rank - 1)];
}
}  // namespace

StageSummary summarise(const LatencyRecorder& recorder) {
  StageSummary s;
  s.name = recorder.name();
  std::vector<double> sorted = recorder.samplesMs();
  std::sort(sorted.begin(), sorted.end());
  s.count = sorted.size();
  if (sorted.empty()) return s;
  s.p50_ms = percentile(sorted, 50.0);
  s.p90_ms = percentile(sorted, 90.0);
  s.p99_ms = percentile(sorted, 99.0);
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
