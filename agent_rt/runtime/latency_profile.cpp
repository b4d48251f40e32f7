#include "agent_rt/runtime/latency_profile.hpp"

#include <cmath>
#include <cstdio>

#include <nlohmann/json.hpp>

#include "common/core/percentile.hpp"

namespace cvislam::agent {

StageSummary summarise(const LatencyRecorder& recorder) {
  const SampleSummary q = summariseSamples(recorder.samplesMs());
  return StageSummary{recorder.name(), q.count, q.p50, q.p90, q.p99, q.max, q.mean};
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
