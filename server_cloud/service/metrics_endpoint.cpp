#include "server_cloud/service/metrics_endpoint.hpp"

#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <utility>

#include <prometheus/collectable.h>
#include <prometheus/exposer.h>
#include <prometheus/metric_family.h>
#include <prometheus/text_serializer.h>

#include "cvislam/v1/monitor.pb.h"
#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/cluster/replica_coordinator.hpp"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/recognition/recognition_worker.hpp"

namespace cvislam::server {

namespace {

using prometheus::ClientMetric;
using prometheus::MetricFamily;
using prometheus::MetricType;
using Labels = std::vector<ClientMetric::Label>;

// Mission names as label values: the first max_labelled ones by name, the rest as "_other".
class MissionLabels {
 public:
  MissionLabels(const std::set<std::string>& missions, std::size_t max_labelled) {
    for (const std::string& m : missions) {
      if (labelled_.size() == max_labelled) break;
      labelled_.insert(m);
    }
  }
  [[nodiscard]] std::string of(const std::string& mission) const {
    return labelled_.count(mission) != 0 ? mission : "_other";
  }

 private:
  std::set<std::string> labelled_;
};

// A family whose samples are summed per label set (missions beyond the cap fall together).
class Family {
 public:
  Family(std::string name, std::string help, MetricType type) {
    family_.name = std::move(name);
    family_.help = std::move(help);
    family_.type = type;
  }
  void add(const Labels& labels, double value) { sums_[labels] += value; }
  MetricFamily take() {
    for (const auto& [labels, value] : sums_) {
      ClientMetric m;
      m.label = labels;
      if (family_.type == MetricType::Counter) {
        m.counter.value = value;
      } else {
        m.gauge.value = value;
      }
      family_.metric.push_back(std::move(m));
    }
    return std::move(family_);
  }

 private:
  MetricFamily family_;
  std::map<Labels, double> sums_;
};

MetricFamily histogram(const std::string& name, const std::string& help, const LatencyHistogram::Snapshot& s) {
  MetricFamily f;
  f.name = name;
  f.help = help;
  f.type = MetricType::Histogram;
  ClientMetric m;
  m.histogram.sample_count = s.count;
  m.histogram.sample_sum = s.sum_s;
  std::uint64_t cumulative = 0;
  for (std::size_t b = 0; b < LatencyHistogram::kBuckets; ++b) {
    cumulative += s.counts[b];
    const double bound = b < LatencyHistogram::kUpperBoundsS.size() ? LatencyHistogram::kUpperBoundsS[b]
                                                                    : std::numeric_limits<double>::infinity();
    m.histogram.bucket.push_back({cumulative, bound});
  }
  f.metric.push_back(std::move(m));
  return f;
}

MetricFamily single(const std::string& name, const std::string& help, MetricType type, double value) {
  Family f(name, help, type);
  f.add({}, value);
  return f.take();
}

// The link's traffic, agents, keyframes and points, per mission (from the core's statistics).
void addMissionFamilies(const v1::ServerStats& stats, const MissionLabels& labels, std::vector<MetricFamily>& out) {
  Family agents("cvislam_agents", "Agents known per mission", MetricType::Gauge);
  Family connected("cvislam_agents_connected", "Agents with an open stream per mission", MetricType::Gauge);
  Family messages("cvislam_link_messages_total",
                  "Messages (or, for the parts of a batch, objects) on the agent link by direction and kind",
                  MetricType::Counter);
  Family bytes("cvislam_link_bytes_total", "Serialized bytes on the agent link by direction and kind",
               MetricType::Counter);
  Family refused("cvislam_link_refused_messages_total", "Agent messages refused (each ended its stream)",
                 MetricType::Counter);
  Family duplicates("cvislam_link_duplicate_batches_total", "Batches dropped as stored already (resends)",
                    MetricType::Counter);
  Family keyframes("cvislam_keyframes", "Keyframes in the server's maps per mission (after redundancy removal)",
                   MetricType::Gauge);
  Family points("cvislam_points", "Map points in the server's maps per mission", MetricType::Gauge);
  Family maps("cvislam_maps", "Server maps per mission", MetricType::Gauge);
  for (const v1::AgentStats& a : stats.agents()) {
    const Labels mission{{"mission", labels.of(a.mission())}};
    agents.add(mission, 1.0);
    connected.add(mission, a.connected() ? 1.0 : 0.0);
    refused.add(mission, static_cast<double>(a.refused_messages()));
    duplicates.add(mission, static_cast<double>(a.duplicate_batches()));
    keyframes.add(mission, static_cast<double>(a.server_keyframes()));
    for (const auto& [direction, by_kind] : {std::pair{"up", &a.up()}, std::pair{"down", &a.down()}}) {
      for (const auto& [kind, count] : *by_kind) {
        const Labels l{{"direction", direction}, {"kind", kind}, {"mission", labels.of(a.mission())}};
        messages.add(l, static_cast<double>(count.messages()));
        bytes.add(l, static_cast<double>(count.bytes()));
      }
    }
  }
  for (const v1::MapStats& m : stats.maps()) {
    const Labels mission{{"mission", labels.of(m.mission())}};
    points.add(mission, static_cast<double>(m.points()));
    maps.add(mission, 1.0);
  }
  for (Family* f : {&agents, &connected, &messages, &bytes, &refused, &duplicates, &keyframes, &points, &maps}) {
    out.push_back(f->take());
  }
}

void addRecognitionFamilies(const recognition::RecognitionWorker& worker, const MissionLabels& labels,
                            std::vector<MetricFamily>& out) {
  out.push_back(single("cvislam_recognition_queue_depth", "Keyframe events waiting for place recognition",
                       MetricType::Gauge, static_cast<double>(worker.queueDepth())));
  Family queries("cvislam_recognition_queries_total", "Place-recognition queries run", MetricType::Counter);
  Family busy("cvislam_recognition_query_seconds_total",
              "Time spent on place-recognition queries (divided by the queries: the mean query time)",
              MetricType::Counter);
  Family dropped("cvislam_recognition_dropped_events_total", "Keyframe events dropped: the queue was full",
                 MetricType::Counter);
  for (const std::string& mission : worker.missions()) {
    const recognition::RecognitionCounters c = worker.counters(mission);
    const Labels l{{"mission", labels.of(mission)}};
    queries.add(l, static_cast<double>(c.queries));
    busy.add(l, c.busy_s);
    dropped.add(l, static_cast<double>(c.dropped_events));
  }
  for (Family* f : {&queries, &busy, &dropped}) out.push_back(f->take());
}

void addBackendFamilies(const backend::BackendWorker& worker, const MissionLabels& labels,
                        std::vector<MetricFamily>& out) {
  Family merges("cvislam_merges_total", "Maps merged", MetricType::Counter);
  Family loops("cvislam_loops_total", "Loops closed", MetricType::Counter);
  Family runs("cvislam_gba_runs_total", "Global BA runs, cut short ones included", MetricType::Counter);
  Family cancelled("cvislam_gba_cancelled_total", "Global BA runs cut short by a newer change", MetricType::Counter);
  Family removed("cvislam_keyframes_removed_total", "Keyframes removed as redundant", MetricType::Counter);
  // Every GBA's run from snapshot to applied result, counted from the back-end's records (kept whole).
  LatencyHistogram gba;
  for (const std::string& mission : worker.missions()) {
    const backend::BackendStats s = worker.stats(mission);
    const Labels l{{"mission", labels.of(mission)}};
    merges.add(l, static_cast<double>(s.merges.size()));
    loops.add(l, static_cast<double>(s.loops.size()));
    runs.add(l, static_cast<double>(s.gba.size()));
    cancelled.add(l, static_cast<double>(s.gba_cancelled));
    removed.add(l, static_cast<double>(s.redundant_removed));
    for (const backend::GbaRecord& r : s.gba) {
      gba.observe((r.snapshot_ms + r.apply_ms) * 1e-3 + r.summary.structure_s + r.summary.full_s);
    }
  }
  for (Family* f : {&merges, &loops, &runs, &cancelled, &removed}) out.push_back(f->take());
  out.push_back(histogram("cvislam_gba_seconds", "Global BA runs from snapshot to applied result", gba.snapshot()));
}

void addReplicaFamilies(const cluster::ReplicaCoordinator& replica, std::vector<MetricFamily>& out) {
  const cluster::ReplicaCounters c = replica.counters();
  out.push_back(single("cvislam_replica_missions_served", "Missions whose lease this replica holds", MetricType::Gauge,
                       static_cast<double>(replica.served().size())));
  out.push_back(single("cvislam_replica_missions_claimed_total", "Missions taken at an agent's Hello",
                       MetricType::Counter, static_cast<double>(c.claimed)));
  out.push_back(single("cvislam_replica_takeovers_total", "Missions taken over after their lease lapsed",
                       MetricType::Counter, static_cast<double>(c.taken_over)));
  out.push_back(single("cvislam_replica_leases_lost_total", "Leases this replica lost", MetricType::Counter,
                       static_cast<double>(c.lost)));
  out.push_back(single("cvislam_replica_redirects_total", "Hellos answered with another replica's address",
                       MetricType::Counter, static_cast<double>(c.redirected)));
  out.push_back(single("cvislam_replica_renew_failures_total", "Lease renewals that failed", MetricType::Counter,
                       static_cast<double>(c.renew_failures)));
}

class ServerCollectable final : public prometheus::Collectable {
 public:
  ServerCollectable(const ServerCore& core, MetricsOptions options) : core_(core), options_(options) {}
  std::vector<MetricFamily> Collect() const override { return collectMetrics(core_, options_); }

 private:
  const ServerCore& core_;
  MetricsOptions options_;
};

}  // namespace

std::vector<MetricFamily> collectMetrics(const ServerCore& core, const MetricsOptions& options) {
  v1::ServerStats stats;
  core.fillStats("", stats);
  std::set<std::string> missions;
  for (const v1::AgentStats& a : stats.agents()) missions.insert(a.mission());
  for (const v1::MapStats& m : stats.maps()) missions.insert(m.mission());
  const MissionLabels labels(missions, options.max_labelled_missions);

  std::vector<MetricFamily> out;
  out.push_back(
      single("cvislam_uptime_seconds", "Seconds since the server started", MetricType::Gauge, core.uptimeSeconds()));
  out.push_back(single("cvislam_missions", "Missions this server holds", MetricType::Gauge,
                       static_cast<double>(core.missions().size())));
  addMissionFamilies(stats, labels, out);
  out.push_back(histogram("cvislam_ingest_seconds",
                          "A batch from its arrival to stored and applied, map-lock waits included",
                          core.ingestMetrics().ingest.snapshot()));
  out.push_back(histogram("cvislam_store_commit_seconds", "A batch's append to the map store",
                          core.ingestMetrics().store_commit.snapshot()));
  out.push_back(single("cvislam_rate_limit_refusals_total", "Requests refused by the per-client rate limit",
                       MetricType::Counter, static_cast<double>(core.rateLimiter().refused())));
  out.push_back(single("cvislam_stream_limit_refusals_total", "Agent streams refused by the per-address limit",
                       MetricType::Counter, static_cast<double>(core.streamLimits().refused())));
  if (const recognition::RecognitionWorker* worker = core.recognition()) addRecognitionFamilies(*worker, labels, out);
  if (const backend::BackendWorker* worker = core.backend()) addBackendFamilies(*worker, labels, out);
  if (const cluster::ReplicaCoordinator* replica = core.replica()) addReplicaFamilies(*replica, out);
  return out;
}

std::string metricsText(const ServerCore& core, const MetricsOptions& options) {
  std::ostringstream text;
  prometheus::TextSerializer().Serialize(text, collectMetrics(core, options));
  return text.str();
}

struct MetricsEndpoint::Impl {
  std::shared_ptr<ServerCollectable> collectable;
  std::unique_ptr<prometheus::Exposer> exposer;
};

MetricsEndpoint::MetricsEndpoint(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
MetricsEndpoint::~MetricsEndpoint() = default;

Result<std::unique_ptr<MetricsEndpoint>> MetricsEndpoint::start(const ServerCore& core, const std::string& listen,
                                                                const MetricsOptions& options) {
  auto impl = std::make_unique<Impl>();
  impl->collectable = std::make_shared<ServerCollectable>(core, options);
  try {
    // One thread: a scrape every few seconds needs no more, and it must not take cores from ingest.
    impl->exposer = std::make_unique<prometheus::Exposer>(listen, 1);
  } catch (const std::exception& e) {
    return Error{ErrorCode::kUnavailable,
                 "cannot serve metrics on " + listen + " (--metrics-listen): " + std::string(e.what())};
  }
  impl->exposer->RegisterCollectable(impl->collectable);
  return std::unique_ptr<MetricsEndpoint>(new MetricsEndpoint(std::move(impl)));
}

int MetricsEndpoint::port() const {
  const std::vector<int> ports = impl_->exposer->GetListeningPorts();
  return ports.empty() ? 0 : ports.front();
}

}  // namespace cvislam::server
