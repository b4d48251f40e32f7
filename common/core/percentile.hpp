// The nearest-rank percentile of sorted samples: the smallest sample that at least `fraction` of all samples
// are less than or equal to. The agent's stage timings and the server's ingest timings both report with it.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <numeric>
#include <span>
#include <vector>

namespace cvislam {

// `sorted` ascending; `fraction` in [0, 1] (0 gives the smallest, 1 the largest); 0 without samples.
inline double nearestRankPercentile(std::span<const double> sorted, double fraction) {
  if (sorted.empty()) return 0.0;
  const auto rank = static_cast<std::size_t>(std::ceil(fraction * static_cast<double>(sorted.size())));
  return sorted[std::min(sorted.size() - 1, rank == 0 ? 0 : rank - 1)];
}

// Count, nearest-rank p50/p90/p99, max and mean of samples in any order (all 0 without samples).
struct SampleSummary {
  std::size_t count = 0;
  double p50 = 0.0;
  double p90 = 0.0;
  double p99 = 0.0;
  double max = 0.0;
  double mean = 0.0;
};

inline SampleSummary summariseSamples(std::vector<double> samples) {
  SampleSummary s;
  s.count = samples.size();
  if (samples.empty()) return s;
  std::sort(samples.begin(), samples.end());
  s.p50 = nearestRankPercentile(samples, 0.50);
  s.p90 = nearestRankPercentile(samples, 0.90);
  s.p99 = nearestRankPercentile(samples, 0.99);
  s.max = samples.back();
  s.mean = std::accumulate(samples.begin(), samples.end(), 0.0) / static_cast<double>(samples.size());
  return s;
}

}  // namespace cvislam
