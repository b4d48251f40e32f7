#include "agent_rt/runtime/latency_profile.hpp"

#include <cmath>
#include <cstdio>

#include <nlohmann/json.hpp>

#include "common/core/percentile.hpp"

namespace cvislam::agent {

StageSummary summarise(const LatencyRecorder& recorder) {
  return StageSummary{recorder.name(), summariseSamples(recorder.samplesMs())};
}

std::string formatLatencyTable(const std::vector<StageSummary>& stages) {
  std::string out = "stage                          count      p50      p90      p99      max   [ms]\n";
  char line[160];
  for (const StageSummary& s : stages) {
    std::snprintf(line, sizeof(line), "%-28s %7zu %8.2f %8.2f %8.2f %8.2f\n", s.name.c_str(), s.ms.count, s.ms.p50,
                  s.ms.p90, s.ms.p99, s.ms.max);
    out += line;
  }
  return out;
}

std::string latencyJson(const std::vector<StageSummary>& stages) {
  nlohmann::json j = nlohmann::json::object();
  for (const StageSummary& s : stages) {
    j[s.name] = {{"count", s.ms.count}, {"p50_ms", s.ms.p50}, {"p90_ms", s.ms.p90},
                 {"p99_ms", s.ms.p99},  {"max_ms", s.ms.max}, {"mean_ms", s.ms.mean}};
  }
  return j.dump(2) + "\n";
}

}  // namespace cvislam::agent
