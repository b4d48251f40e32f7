// The server's metrics for Prometheus: counters, gauges and histograms of what the core already counts (agents,
// traffic by direction and kind, ingest and store latency, recognition, merges, loops, GBA, limits, replica
// leases), read from the core at each scrape and served in Prometheus' text format at /metrics.
//
// Labels stay bounded: only `mission`, `direction` and `kind` are used, and the kinds are the link's fixed set.
// The first max_labelled_missions missions (by name) are labelled with their names; the rest are summed under
// mission="_other", so that a server holding many missions cannot make the series grow without limit.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "common/core/result.hpp"

namespace prometheus {
struct MetricFamily;
}

namespace cvislam::server {

class ServerCore;

struct MetricsOptions {
  std::size_t max_labelled_missions = 64;
};

// Every metric now, as Prometheus families (plain data; tests read them without HTTP).
std::vector<prometheus::MetricFamily> collectMetrics(const ServerCore& core, const MetricsOptions& options);
// The same in Prometheus' text exposition format.
std::string metricsText(const ServerCore& core, const MetricsOptions& options);

// /metrics over HTTP (plaintext; prometheus-cpp's embedded server) on `listen`, until destroyed.
class MetricsEndpoint {
 public:
  // The error names the address when it cannot be bound.
  static Result<std::unique_ptr<MetricsEndpoint>> start(const ServerCore& core, const std::string& listen,
                                                        const MetricsOptions& options = {});
  ~MetricsEndpoint();
  MetricsEndpoint(const MetricsEndpoint&) = delete;
  MetricsEndpoint& operator=(const MetricsEndpoint&) = delete;

  [[nodiscard]] int port() const;

 private:
  struct Impl;
  explicit MetricsEndpoint(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::server
