// p50 and p99 aggregates for Google Benchmark repetitions: every cvislam benchmark reports these instead of
// a single run.
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include <benchmark/benchmark.h>

namespace cvislam::bench {

inline double percentile(const std::vector<double>& values, double p) {
  std::vector<double> v = values;
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[static_cast<std::size_t>(std::lround(p * static_cast<double>(v.size() - 1)))];
}

// Repetitions reported as p50 and p99 (with Google Benchmark's mean, median and stddev).
inline void withPercentiles(benchmark::internal::Benchmark* b, int repetitions) {
  b->Repetitions(repetitions)
      ->ReportAggregatesOnly(true)
      ->ComputeStatistics("p50", [](const std::vector<double>& v) { return percentile(v, 0.5); })
      ->ComputeStatistics("p99", [](const std::vector<double>& v) { return percentile(v, 0.99); });
}

}  // namespace cvislam::bench
