// Durations counted into fixed buckets since start, for the metrics endpoint. LatencySamples keeps the newest
// 4096 for percentiles; a Prometheus histogram instead needs every sample counted, cumulatively, so that rates
// and quantiles over any window can be computed by whoever scrapes it. Observed from any thread without a lock.
#pragma once

#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>

namespace cvislam::server {

class LatencyHistogram {
 public:
  // Upper bounds [s], ascending: from a millisecond (an ingest) to a minute (a GBA of a large map). One more
  // bucket, +Inf, takes what lies above the last.
  static constexpr std::array<double, 16> kUpperBoundsS = {0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1,  0.25,
                                                           0.5,   1.0,    2.5,   5.0,  10.0,  20.0, 40.0, 80.0};
  static constexpr std::size_t kBuckets = kUpperBoundsS.size() + 1;

  struct Snapshot {
    std::array<std::uint64_t, kBuckets> counts{};  // per bucket, not cumulative; the last is +Inf
    std::uint64_t count = 0;
    double sum_s = 0.0;
  };

  void observe(double seconds) {
    if (!std::isfinite(seconds) || seconds < 0.0) seconds = 0.0;
    std::size_t b = 0;
    while (b < kUpperBoundsS.size() && seconds > kUpperBoundsS[b]) ++b;
    counts_[b].fetch_add(1, std::memory_order_relaxed);
    sum_ns_.fetch_add(static_cast<std::uint64_t>(std::llround(seconds * 1e9)), std::memory_order_relaxed);
  }

  [[nodiscard]] Snapshot snapshot() const {
    Snapshot s;
    for (std::size_t b = 0; b < kBuckets; ++b) {
      s.counts[b] = counts_[b].load(std::memory_order_relaxed);
      s.count += s.counts[b];
    }
    s.sum_s = static_cast<double>(sum_ns_.load(std::memory_order_relaxed)) * 1e-9;
    return s;
  }

 private:
  std::array<std::atomic<std::uint64_t>, kBuckets> counts_{};
  std::atomic<std::uint64_t> sum_ns_{0};
};

// What the agent sessions time for the metrics endpoint, server-wide.
struct IngestMetrics {
  LatencyHistogram ingest;        // a batch from its arrival to stored and applied (map-lock waits included)
  LatencyHistogram store_commit;  // its append to the map store
};

}  // namespace cvislam::server
