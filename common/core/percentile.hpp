// The nearest-rank percentile of sorted samples: the smallest sample that at least `fraction` of all samples
// are less than or equal to. The agent's stage timings and the server's ingest timings both report with it.
#pragma once

#include <algorithm>
#include <cmath>
#include <span>

namespace cvislam {

// `sorted` ascending; `fraction` in [0, 1] (0 gives the smallest, 1 the largest); 0 without samples.
inline double nearestRankPercentile(std::span<const double> sorted, double fraction) {
  if (sorted.empty()) return 0.0;
  const auto rank = static_cast<std::size_t>(std::ceil(fraction * static_cast<double>(sorted.size())));
  return sorted[std::min(sorted.size() - 1, rank == 0 ? 0 : rank - 1)];
}

}  // namespace cvislam
