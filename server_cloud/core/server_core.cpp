#include "server_cloud/core/server_core.hpp"

#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>

#include <google/protobuf/util/json_util.h>
#include <nlohmann/json.hpp>

#include "common/dataset/trajectory_io.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "cvislam/v1/monitor.pb.h"
#include "server_cloud/cluster/postgres_store.hpp"

namespace cvislam::server {

namespace {
std::string hostName() {
  char name[256] = {};
  if (::gethostname(name, sizeof name - 1) != 0 || name[0] == '\0') return "replica";
  return name;
}
}  // namespace

ServerCore::ServerCore(const ServerOptions& options)
    : options_(options),
      start_(Clock::now()),
      limiter_(options.rate_limit),
      streams_(options.stream_limits),
      map_reads_(options.map_read_limits) {}

ServerCore::~ServerCore() {
  // The replica's thread loads missions, which feeds the workers: it stops first (without releasing: a crash
  // would not either). Recognition's thread calls the back-end (matches) and the back-end's thread calls
  // recognition (merges and removals to re-index): recognition's thread stops next, then the back-end goes, then
  // recognition itself.
  replica_.reset();
  if (recognition_) recognition_->stop();
  backend_.reset();
  recognition_.reset();
}

Status ServerCore::startWorkers() {
  if (options_.recognition.enabled && !recognition_) {
    Result<std::unique_ptr<recognition::RecognitionWorker>> worker =
        recognition::RecognitionWorker::create(options_.recognition, missions_);
    if (!worker) return worker.error();
    recognition_ = std::move(worker).value();
  }
  if (options_.backend.enabled && !backend_) {
    if (Status s = options_.backend.validate(); !s.ok()) return s;
    backend_ = std::make_unique<backend::BackendWorker>(options_.backend, missions_, recognition_.get());
    if (recognition_) {
      backend::BackendWorker* b = backend_.get();
      recognition_->setMatchListener(
          [b](const std::string& mission, const recognition::MatchRecord& match) { b->onMatch(mission, match); });
    }
  }
  return Status::Ok();
}

void ServerCore::drainWorkers(bool final_gba) const {
  if (recognition_) recognition_->drain();  // the last keyframes of every agent get their turn
  if (backend_) backend_->drain(final_gba);
  // A merge or removal the back-end made tells recognition: let it follow.
  if (recognition_) recognition_->drain();
}

std::unique_ptr<AgentSession> ServerCore::openSession(std::function<void()> cancel_stream, std::string token) {
  return std::make_unique<AgentSession>(missions_, options_.session, std::move(cancel_stream), storedListener(),
                                        store_.get(), SessionCredentials{&tokens_, std::move(token)}, ownership(),
                                        &ingest_metrics_);
}

double ServerCore::uptimeSeconds() const {
  return std::chrono::duration<double>(Clock::now() - start_).count();
}

MissionOwnership* ServerCore::ownership() const {
  return replica_.get();
}

Status ServerCore::loadTokens() {
  if (options_.tokens_file.empty()) return Status::Ok();
  auto loaded = MissionTokens::load(options_.tokens_file);
  if (!loaded) return loaded.error();
  tokens_ = std::move(loaded).value();
  return Status::Ok();
}

Result<RecoveryReport> ServerCore::openStore() {
  if (options_.cluster.enabled()) {
    const std::string holder =
        cluster::makeHolderName(options_.cluster.replica.empty() ? hostName() : options_.cluster.replica);
    cluster::PostgresStoreOptions store_options;
    store_options.conninfo = options_.cluster.postgres;
    store_options.holder = holder;
    store_options.software = options_.session.server_name;
    auto store = cluster::openPostgresStore(store_options);
    if (!store) return store.error();
    cluster::LeaseOptions lease_options;
    lease_options.conninfo = options_.cluster.postgres;
    lease_options.holder = holder;
    lease_options.address = clusterAddress(options_);
    lease_options.ttl_s = options_.cluster.lease_ttl_s;
    auto leases = cluster::MissionLeases::open(lease_options);
    if (!leases) return leases.error();
    auto renewals = cluster::MissionLeases::open(lease_options);
    if (!renewals) return renewals.error();
    return joinCluster(std::move(store).value(), std::move(leases).value(), std::move(renewals).value());
  }
  if (options_.store.empty()) return RecoveryReport{};
  SqliteStoreOptions store_options;
  store_options.path = options_.store;
  store_options.sync = options_.store_sync;
  store_options.software = options_.session.server_name;
  auto store = openSqliteStore(store_options);
  if (!store) return store.error();
  return attachStore(std::move(store).value());
}

Result<RecoveryReport> ServerCore::attachStore(std::unique_ptr<MapStore> store) {
  if (store_) return Error{ErrorCode::kFailedPrecondition, "the server has a map store already"};
  const auto start = Clock::now();
  RecoveryReport report;
  report.store = store->describe();
  const AgentSession::StoredListener on_stored = storedListener();
  std::set<std::pair<std::string, AgentId>> agents;
  std::set<std::string> missions;
  Status replayed = store->replay("", [&](const StoreRecord& r) -> Status {
    if (Status s = replayStored(missions_, options_.session, r, on_stored); !s.ok()) return s;
    (r.kind == StoreRecord::Kind::kHello ? report.hellos : report.batches) += 1;
    report.bytes += r.body.size();
    agents.emplace(r.mission, r.agent);
    missions.insert(r.mission);
    return Status::Ok();
  });
  if (!replayed.ok()) {
    return replayed.error().withContext("replaying " + report.store +
                                        " (nothing was served from it; fix or move the store aside)");
  }
  for (const auto& mission : missions_.missions()) {
    for (const auto& agent : mission->agents()) report.keyframes += agent->read()->keyframes.size();
  }
  report.missions = missions.size();
  report.agents = agents.size();
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  store_ = std::move(store);
  return report;
}

Result<RecoveryReport> ServerCore::joinCluster(std::unique_ptr<MapStore> store,
                                               std::unique_ptr<cluster::MissionLeases> leases,
                                               std::unique_ptr<cluster::MissionLeases> renewals) {
  if (store_) return Error{ErrorCode::kFailedPrecondition, "the server has a map store already"};
  RecoveryReport report;
  report.store = store->describe() + ", replica " + leases->options().holder + " at " + leases->options().address;
  store_ = std::move(store);
  replica_ = std::make_unique<cluster::ReplicaCoordinator>(
      std::move(leases), std::move(renewals), [this](const std::string& mission) { return loadFromStore(mission); },
      [this](const std::string& mission) { dropMission(mission); },
      [this] { return missions_.size() < options_.session.max_missions; });
  replica_->start();
  return report;
}

Status ServerCore::leaveCluster() {
  if (!replica_) return Status::Ok();
  return replica_->release();
}

void ServerCore::dropMission(const std::string& name) {
  std::shared_ptr<Mission> mission = missions_.remove(name);
  if (!mission) return;
  mission->retire();  // its sessions and watches end, and refuse what still comes
  for (const SharedAgentRecord& agent : mission->agents()) {
    std::function<void()> cancel = agent->read()->cancel_stream;
    if (cancel) cancel();
  }
}

Status ServerCore::loadFromStore(const std::string& mission) {
  if (!store_) return Status::Ok();
  if (missions_.find(mission)) {
    return Error{ErrorCode::kFailedPrecondition, "mission '" + mission + "' is in memory already"};
  }
  const AgentSession::StoredListener on_stored = storedListener();
  return store_->replay(
      mission, [&](const StoreRecord& r) -> Status { return replayStored(missions_, options_.session, r, on_stored); });
}

Result<LoadReport> ServerCore::loadMission(const MapStore* source, const std::string& from, const std::string& as) {
  const auto start = Clock::now();
  if (source == nullptr) source = store_.get();
  if (source == nullptr) {
    return Error{ErrorCode::kFailedPrecondition,
                 "no store to load mission '" + from + "' from (give --store or --load-from)"};
  }
  LoadReport report;
  report.source = source->describe();
  report.from = from;
  report.as = as;
  // Before anything is written: a name the replay would refuse would make the store unreplayable.
  if (Status s = checkMissionName(as); !s.ok()) return s.error().withContext("loading a mission as '" + as + "'");
  if (from == as) return Error{ErrorCode::kInvalidArgument, "mission '" + from + "' cannot be loaded as itself"};
  if (missions_.find(as) && !store_) {
    report.already_held = true;
    return report;
  }
  // Collected first: the source may be this server's own store, which the copy appends to.
  std::vector<StoreRecord> records;
  if (Status s = source->replay(from,
                                [&](const StoreRecord& r) -> Status {
                                  records.push_back(r);
                                  return Status::Ok();
                                });
      !s.ok()) {
    return s.error().withContext("reading mission '" + from + "' of " + report.source);
  }
  if (records.empty()) {
    std::string held;
    if (auto names = source->missions(); names) {
      for (const std::string& n : *names) held += (held.empty() ? "" : ", ") + n;
    }
    return Error{ErrorCode::kNotFound,
                 report.source + " holds no mission '" + from + "' (it holds: " + (held.empty() ? "none" : held) + ")"};
  }
  // What an earlier load stored of `as` already: all of it (a restart replayed it), or a part (that load was cut
  // short by a crash; it goes on from there, as the copy keeps the source's order).
  std::size_t held = 0;
  if (store_) {
    if (Status s = store_->replay(as,
                                  [&](const StoreRecord&) -> Status {
                                    ++held;
                                    return Status::Ok();
                                  });
        !s.ok()) {
      return s.error().withContext("reading mission '" + as + "' of " + store_->describe());
    }
  }
  if (replica_) return loadOnReplica(records, held, std::move(report), start);
  if (held >= records.size()) {
    report.already_held = true;
    return report;
  }
  const AgentSession::StoredListener on_stored = storedListener();
  for (std::size_t i = held; i < records.size(); ++i) {
    StoreRecord& r = records[i];
    if (Status s = renameLoaded(r, report); !s.ok()) return s.error();
    if (store_) {
      if (Status s = store_->append(r); !s.ok()) {
        return s.error().withContext("storing mission '" + as + "' (loaded from '" + from + "')");
      }
    }
    if (Status s = replayStored(missions_, options_.session, r, on_stored); !s.ok()) {
      return s.error().withContext("loading mission '" + from + "' of " + report.source + " as '" + as + "'");
    }
    (r.kind == StoreRecord::Kind::kHello ? report.hellos : report.batches) += 1;
  }
  if (auto mission = missions_.find(as)) {
    for (const auto& agent : mission->agents()) report.keyframes += agent->read()->keyframes.size();
  }
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  return report;
}

Status ServerCore::renameLoaded(StoreRecord& r, const LoadReport& report) {
  r.mission = report.as;
  if (r.kind != StoreRecord::Kind::kHello) return Status::Ok();
  // The Hello names its mission; the copy names the new one (replay checks that they agree).
  v1::Hello hello;
  if (!hello.ParseFromString(r.body)) {
    return Error{ErrorCode::kDataError,
                 report.source + " record " + std::to_string(r.number) + ": the Hello does not parse"};
  }
  hello.set_mission(report.as);
  r.body = hello.SerializeAsString();
  return Status::Ok();
}

// On a replica the copy goes into the shared store under the mission's lease, so that no other replica takes the
// mission while it is half written; then the replica loads it from the store as it loads any mission it takes,
// and serves it.
Result<LoadReport> ServerCore::loadOnReplica(std::vector<StoreRecord>& records, std::size_t held, LoadReport report,
                                             Clock::time_point start) {
  const std::string as = report.as;
  const auto copy = [&]() -> Status {
    for (std::size_t i = held; i < records.size(); ++i) {
      StoreRecord& r = records[i];
      if (Status s = renameLoaded(r, report); !s.ok()) return s;
      if (Status s = store_->append(r); !s.ok()) {
        return s.error().withContext("storing mission '" + as + "' (loaded from '" + report.from + "')");
      }
      (r.kind == StoreRecord::Kind::kHello ? report.hellos : report.batches) += 1;
    }
    return Status::Ok();
  };
  Result<MissionOwner> owner = replica_->claimPrepared(as, copy);
  if (!owner) return owner.error().withContext("loading mission '" + report.from + "' as '" + as + "'");
  if (!owner->here) {
    if (held >= records.size()) {  // copied before; another replica serves it
      report.already_held = true;
      return report;
    }
    return Error{ErrorCode::kFailedPrecondition, "mission '" + as + "' is served by replica " + owner->holder + " at " +
                                                     owner->address +
                                                     " and the store holds only part of the copy: load it when that "
                                                     "replica has let it go, or load it under another name"};
  }
  report.already_held = held >= records.size();
  replica_->waitForLoads();
  auto mission = missions_.find(as);
  if (!mission) {
    return Error{ErrorCode::kUnavailable, "mission '" + as + "' was copied into " + store_->describe() +
                                              " but did not load on this replica (see its log); it is loaded when "
                                              "an agent of it connects"};
  }
  for (const auto& agent : mission->agents()) report.keyframes += agent->read()->keyframes.size();
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  return report;
}

AgentSession::StoredListener ServerCore::storedListener() const {
  AgentSession::StoredListener on_stored;
  recognition::RecognitionWorker* worker = recognition_.get();
  backend::BackendWorker* back_end = backend_.get();
  if (worker != nullptr || back_end != nullptr) {
    on_stored = [worker, back_end](const std::string& mission, const IngestReport& report) {
      using Event = recognition::KeyframeEvent;
      if (worker != nullptr) {
        for (const KeyframeId& id : report.removed_keyframe_ids) {
          worker->enqueue(Event{Event::Kind::kRemoved, mission, 0, id});
        }
        for (const auto& [map, id] : report.keyframes_ready) {
          worker->enqueue(Event{Event::Kind::kAdded, mission, map, id});
        }
      }
      if (back_end != nullptr && !report.keyframes_ready.empty()) {
        back_end->onKeyframesAdded(mission, report.keyframes_ready);
      }
    };
  }
  return on_stored;
}

void ServerCore::fillStats(const std::string& mission_filter, v1::ServerStats& out,
                           const std::function<bool(const std::string&)>& visible) const {
  out.Clear();
  out.set_uptime_s(uptimeSeconds());
  for (const auto& mission : missions_.missions()) {
    if (!mission_filter.empty() && mission->name() != mission_filter) continue;
    if (visible && !visible(mission->name())) continue;
    for (const auto& shared : mission->agents()) {
      auto record = shared->read();
      v1::AgentStats& a = *out.add_agents();
      a.set_mission(mission->name());
      a.set_agent_id(record->id);
      a.set_connected(record->connected);
      a.set_finished(record->finished);
      a.set_connections(record->connections);
      a.set_keyframes(record->keyframes.size());
      a.set_server_keyframes(record->serverKeyframes());
      a.set_points(record->points.size());
      a.set_maps(static_cast<std::uint32_t>(record->agent_maps.size()));
      a.set_stored_sequence(record->stored_sequence);
      a.set_duplicate_batches(record->duplicate_batches);
      a.set_duplicate_objects(record->duplicate_objects);
      a.set_refused_messages(record->refused_messages);
      a.set_last_error(record->last_error);
      const auto latency = [](const LatencySamples& samples, v1::Latency& into) {
        into.set_samples(samples.size());
        into.set_p50(samples.percentile(0.5));
        into.set_p99(samples.percentile(0.99));
        into.set_max(samples.percentile(1.0));
      };
      latency(record->ingest_ms, *a.mutable_ingest_ms());
      latency(record->ingest_during_gba_ms, *a.mutable_ingest_during_gba_ms());
      for (const auto& [kind, count] : record->up) {
        v1::TrafficCounter& c = (*a.mutable_up())[kind];
        c.set_messages(count.messages);
        c.set_bytes(count.bytes);
      }
      for (const auto& [kind, count] : record->down) {
        v1::TrafficCounter& c = (*a.mutable_down())[kind];
        c.set_messages(count.messages);
        c.set_bytes(count.bytes);
      }
    }
    for (const auto& map : mission->stack().maps()) {
      auto content = map->read();
      v1::MapStats& m = *out.add_maps();
      m.set_mission(mission->name());
      m.set_map_id(map->id());
      for (AgentId agent : content->agents()) m.add_agents(agent);
      m.set_keyframes(content->keyframes().size());
      m.set_points(content->points().size());
      m.set_covisibility_edges(content->covisibilityEdges());
    }
  }
}

void ServerCore::sampleTimeline() {
  const double t_s = std::chrono::duration<double>(Clock::now() - start_).count();
  std::vector<TimelineSample> samples;
  for (const auto& mission : missions_.missions()) {
    for (const auto& shared : mission->agents()) {
      // An agent whose record is busy (a batch being committed) misses this sample rather than delay every other
      // agent's, and the downlinks that share this thread.
      auto locked = shared->tryRead();
      if (!locked) continue;
      const auto& record = *locked;
      TimelineSample s;
      s.t_s = t_s;
      s.mission = mission->name();
      s.agent = record->id;
      s.connected = record->connected;
      s.keyframes = record->keyframes.size();
      s.server_keyframes = record->serverKeyframes();
      s.points = record->points.size();
      if (auto it = record->up.find("message"); it != record->up.end()) s.up_bytes = it->second.bytes;
      if (auto it = record->down.find("message"); it != record->down.end()) s.down_bytes = it->second.bytes;
      samples.push_back(std::move(s));
    }
  }
  auto timeline = timeline_.write();
  // Bounded for a server that runs for days: when full, the older half goes (timeline.csv then starts later).
  if (timeline->size() + samples.size() > kMaxTimelineSamples) {
    timeline->erase(timeline->begin(), timeline->begin() + static_cast<std::ptrdiff_t>(timeline->size() / 2));
  }
  timeline->insert(timeline->end(), samples.begin(), samples.end());
}

namespace {

// `stack`, when given, names each match's map frames: the agent map each map was opened for (a scorer needs it
// once merges have made a map hold several agents).
Status writeRecognition(const std::filesystem::path& path, const recognition::RecognitionCounters& c,
                        const std::vector<recognition::MatchRecord>& matches, const MapStack* stack) {
  nlohmann::json j;
  j["keyframes"] = c.keyframes;
  j["queries"] = c.queries;
  j["candidates"] = c.candidates;
  j["loops"] = c.loops;
  j["map_matches"] = c.map_matches;
  j["rejections"] = c.rejections;
  j["dropped_events"] = c.dropped_events;
  j["skipped"] = c.skipped;
  j["busy_s"] = c.busy_s;
  const auto quantiles = [](const LatencySamples& samples) {
    return nlohmann::json{{"p50", samples.percentile(0.5)},
                          {"p99", samples.percentile(0.99)},
                          {"max", samples.percentile(1.0)},
                          {"n", samples.size()}};
  };
  j["query_ms"] = quantiles(c.query_ms);
  j["lock_held_ms"] = quantiles(c.lock_held_ms);
  j["query_cpu_ms"] = quantiles(c.query_cpu_ms);
  j["locked_cpu_ms"] = quantiles(c.locked_cpu_ms);
  nlohmann::json list = nlohmann::json::array();
  for (const recognition::MatchRecord& r : matches) {
    const recognition::VerifiedMatch& m = r.match;
    const Eigen::Quaterniond& q = m.T_qmap_cmap.quaternion();
    const Eigen::Vector3d& t = m.T_qmap_cmap.translation();
    nlohmann::json e;
    e["kind"] = r.kind == recognition::QueryKind::kLoop ? "loop" : "map_match";
    e["query"] = {m.query.agent, m.query.counter};
    e["candidate"] = {m.candidate.agent, m.candidate.counter};
    e["query_map"] = m.query_map;
    e["candidate_map"] = m.candidate_map;
    if (stack != nullptr) {
      for (const auto& [key, id] :
           {std::pair{"query_map_origin", m.query_map}, {"candidate_map_origin", m.candidate_map}}) {
        if (const std::optional<MapOrigin> o = stack->origin(id)) e[key] = {o->agent, o->agent_map};
      }
    }
    e["T_qmap_cmap"] = {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()};  // x y z qx qy qz qw
    const Eigen::Vector3d& p_cq = m.T_cmap_cq.translation();
    e["p_cmap_query"] = {p_cq.x(), p_cq.y(), p_cq.z()};  // the query camera in the candidate map
    e["inliers"] = m.inliers;
    e["bow_score"] = m.bow_score;
    e["tilt_deg"] = m.tilt_deg;
    e["point_pairs"] = m.point_pairs.size();
    if (m.scale) e["scale"] = *m.scale;
    list.push_back(std::move(e));
  }
  j["matches"] = std::move(list);
  std::ofstream out(path);
  out << j.dump(1) << "\n";
  if (!out) return Error{ErrorCode::kIoError, "cannot write " + path.string()};
  return Status::Ok();
}

nlohmann::json toJson(const geometry::SE3d& T) {
  const Eigen::Quaterniond& q = T.quaternion();
  const Eigen::Vector3d& t = T.translation();
  return {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()};
}

// [[seconds since the solve began, cost], ...] after each accepted step.
nlohmann::json acceptedSteps(const backend::GlobalBaSummary& summary) {
  nlohmann::json out = nlohmann::json::array();
  for (const backend::GlobalBaSummary::Step& step : summary.accepted) out.push_back({step.t_s, step.cost});
  return out;
}

nlohmann::json toJson(const backend::FusionReport& f) {
  return {{"pairs_fused", f.pairs_fused},
          {"keypoints_linked", f.keypoints_linked},
          {"projection_fused", f.projection_fused},
          {"projection_linked", f.projection_linked}};
}

// How well covered the mission's keyframes are at the end, by the redundancy rule: a histogram of the fraction of
// each keyframe's points that enough other keyframes observe, in tenths (for tuning redundancy removal).
nlohmann::json keyframeCoverage(const Mission& mission, const backend::RedundancyOptions& options) {
  std::vector<int> tenths(10, 0);
  int redundant = 0;
  for (const auto& map : mission.stack().maps()) {
    const auto content = map->read();
    for (const auto& [id, kf] : content->keyframes()) {
      const double f = backend::coveredFraction(*content, id, options);
      ++tenths[static_cast<std::size_t>(std::clamp(static_cast<int>(f * 10.0), 0, 9))];
      if (f >= options.redundant_fraction) ++redundant;
    }
  }
  return nlohmann::json{{"covered_fraction_tenths", tenths}, {"redundant_by_the_rule", redundant}};
}

Status writeBackend(const std::filesystem::path& path, const backend::BackendStats& b,
                    const nlohmann::json& final_coverage) {
  nlohmann::json j;
  nlohmann::json merges = nlohmann::json::array();
  for (const backend::MergeRecord& m : b.merges) {
    merges.push_back({{"from_map", m.from},
                      {"into_map", m.into},
                      {"query", {m.query.agent, m.query.counter}},
                      {"candidate", {m.candidate.agent, m.candidate.counter}},
                      {"T_into_from", toJson(m.T_into_from)},
                      {"fusion", toJson(m.fusion)},
                      {"apply_ms", m.apply_ms},
                      {"match_to_merged_s", m.match_to_merged_s},
                      {"correction",
                       {{"ba_keyframes", m.correction_ba.keyframes},
                        {"ba_points", m.correction_ba.points},
                        {"ba_iterations", m.correction_ba.structure_iterations + m.correction_ba.full_iterations},
                        {"moved_keyframes", m.correction_keyframes},
                        {"query_moved_m", m.correction_m},
                        {"query_moved_deg", m.correction_deg},
                        {"solve_ms", m.correction_solve_ms}}},
                      {"match_to_corrected_s", m.match_to_corrected_s},
                      {"match_to_optimised_s", m.match_to_optimised_s}});
  }
  nlohmann::json loops = nlohmann::json::array();
  for (const backend::LoopRecord& l : b.loops) {
    loops.push_back({{"map", l.map},
                     {"query", {l.query.agent, l.query.counter}},
                     {"candidate", {l.candidate.agent, l.candidate.counter}},
                     {"correction_m", l.correction_m},
                     {"correction_deg", l.correction_deg},
                     {"query_t_ns", l.query_t_ns},
                     {"candidate_t_ns", l.candidate_t_ns},
                     {"T_cs_qs_measured", toJson(l.T_cs_qs_measured)},
                     {"T_cs_qs_map", toJson(l.T_cs_qs_map)},
                     {"window_agent_maps", l.window_agent_maps},
                     {"map_agent_maps", l.map_agent_maps},
                     {"cancelled_gba", l.cancelled_gba},
                     {"graph_keyframes", l.graph.keyframes},
                     {"graph_edges", l.graph.tree_edges + l.graph.covisibility_edges + l.graph.loop_edges},
                     {"loop_edges", l.graph.loop_edges},
                     {"solve_ms", l.solve_ms},
                     {"fusion", toJson(l.fusion)},
                     {"match_to_corrected_s", l.match_to_corrected_s},
                     {"match_to_optimised_s", l.match_to_optimised_s}});
  }
  nlohmann::json gba = nlohmann::json::array();
  for (const backend::GbaRecord& g : b.gba) {
    gba.push_back({{"map", g.map},
                   {"final", g.final},
                   {"cancelled", g.summary.cancelled},
                   {"budget_reached", g.summary.budget_reached},
                   {"keyframes", g.summary.keyframes},
                   {"points", g.summary.points},
                   {"reprojection_factors", g.summary.reprojection_factors},
                   {"imu_factors", g.summary.imu_factors},
                   {"iterations", g.summary.structure_iterations + g.summary.full_iterations},
                   {"initial_cost", g.summary.initial_cost},
                   {"final_cost", g.summary.final_cost},
                   {"solve_s", g.summary.structure_s + g.summary.full_s},
                   {"profile_s",
                    {{"build", g.summary.profile.build_s},
                     {"preprocess", g.summary.profile.preprocess_s},
                     {"residuals", g.summary.profile.residuals_s},
                     {"jacobians", g.summary.profile.jacobians_s},
                     {"linear_solver", g.summary.profile.linear_solver_s},
                     {"other", g.summary.profile.other_s}}},
                   {"snapshot_ms", g.snapshot_ms},
                   {"apply_ms", g.apply_ms},
                   {"keyframes_propagated", g.keyframes_propagated},
                   {"accepted_steps", acceptedSteps(g.summary)},
                   {"windowed", g.windowed},
                   {"held_keyframes", g.held_keyframes}});
  }
  j["merges"] = std::move(merges);
  j["loops"] = std::move(loops);
  j["gba"] = std::move(gba);
  j["gba_cancelled"] = b.gba_cancelled;
  j["stale_matches"] = b.stale_matches;
  j["loops_in_cooldown"] = b.loops_in_cooldown;
  j["new_keyframes_fused"] = b.new_keyframes_fused;
  j["new_keyframe_links"] = b.new_keyframe_links;
  j["new_keyframe_point_merges"] = b.new_keyframe_point_merges;
  j["new_keyframe_fuse_ms_max"] = b.new_keyframe_fuse_ms_max;
  j["new_keyframe_fuse_locked_ms_max"] = b.new_keyframe_fuse_locked_ms_max;
  j["new_keyframe_fuse_ms_mean"] =
      b.new_keyframes_fused == 0 ? 0.0 : b.new_keyframe_fuse_ms_total / static_cast<double>(b.new_keyframes_fused);
  j["redundancy_checked"] = b.redundancy_checked;
  j["redundant_keyframes_removed"] = b.redundant_removed;
  j["redundant_removed_by_final_pass"] = b.final_pass_removed;
  j["redundant_kept_for_imu_gap"] = b.redundant_kept_for_imu_gap;
  j["points_removed"] = b.points_removed;
  j["dropped_events"] = b.dropped_events;
  j["final_keyframe_coverage"] = final_coverage;
  std::ofstream out(path);
  out << j.dump(1) << "\n";
  if (!out) return Error{ErrorCode::kIoError, "cannot write " + path.string()};
  return Status::Ok();
}

}  // namespace

Status ServerCore::writeOutputs(const std::filesystem::path& dir) const {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return Error{ErrorCode::kIoError, "cannot create " + dir.string() + ": " + ec.message()};
  drainWorkers(options_.final_gba);

  for (const auto& mission : missions_.missions()) {
    const std::filesystem::path mission_dir = dir / mission->name();
    std::filesystem::create_directories(mission_dir, ec);
    if (ec) return Error{ErrorCode::kIoError, "cannot create " + mission_dir.string() + ": " + ec.message()};
    // Keyframes per agent (all maps) and per agent map.
    std::map<AgentId, dataset::Trajectory> per_agent;
    std::map<std::pair<AgentId, MapId>, dataset::Trajectory> per_map;
    for (const auto& map : mission->stack().maps()) {
      auto content = map->read();
      for (const auto& [id, kf] : content->keyframes()) {
        per_agent[id.agent].push_back({kf.t_ns, kf.T_w_s});
        per_map[{id.agent, map->id()}].push_back({kf.t_ns, kf.T_w_s});
      }
    }
    const auto by_time = [](const dataset::StampedPose& a, const dataset::StampedPose& b) { return a.t_ns < b.t_ns; };
    std::map<AgentId, int> maps_of_agent;
    for (auto& [key, trajectory] : per_map) ++maps_of_agent[key.first];
    for (auto& [agent, trajectory] : per_agent) {
      std::sort(trajectory.begin(), trajectory.end(), by_time);
      const auto path = mission_dir / ("keyframes_agent" + std::to_string(agent) + ".txt");
      if (Status s = dataset::writeTrajectory(path, trajectory, dataset::TrajectoryFormat::kTum); !s.ok()) return s;
    }
    for (auto& [key, trajectory] : per_map) {
      if (maps_of_agent[key.first] < 2) continue;
      std::sort(trajectory.begin(), trajectory.end(), by_time);
      const auto path =
          mission_dir / ("keyframes_agent" + std::to_string(key.first) + "_map" + std::to_string(key.second) + ".txt");
      if (Status s = dataset::writeTrajectory(path, trajectory, dataset::TrajectoryFormat::kTum); !s.ok()) return s;
    }
  }

  v1::ServerStats stats;
  fillStats("", stats);
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.add_whitespace = true;
  print.always_print_primitive_fields = true;
  print.preserve_proto_field_names = true;
  if (!google::protobuf::util::MessageToJsonString(stats, &json, print).ok()) {
    return Error{ErrorCode::kInternal, "cannot print the statistics as JSON"};
  }
  std::ofstream(dir / "stats.json") << json;

  if (backend_) {
    for (const std::string& name : backend_->missions()) {
      const auto mission_dir = dir / name;
      std::filesystem::create_directories(mission_dir, ec);
      const std::shared_ptr<Mission> mission = missions_.find(name);
      const nlohmann::json coverage =
          mission ? keyframeCoverage(*mission, options_.backend.redundancy) : nlohmann::json::object();
      if (Status s = writeBackend(mission_dir / "backend.json", backend_->stats(name), coverage); !s.ok()) return s;
    }
  }
  if (recognition_) {
    for (const std::string& name : recognition_->missions()) {
      const auto mission_dir = dir / name;
      std::filesystem::create_directories(mission_dir, ec);
      const std::shared_ptr<Mission> mission = missions_.find(name);
      if (Status s = writeRecognition(mission_dir / "recognition.json", recognition_->counters(name),
                                      recognition_->matches(name), mission ? &mission->stack() : nullptr);
          !s.ok()) {
        return s;
      }
    }
  }

  std::ofstream timeline(dir / "timeline.csv");
  timeline << "t_s,mission,agent,connected,keyframes,server_keyframes,points,up_bytes,down_bytes\n";
  for (const TimelineSample& s : *timeline_.read()) {
    timeline << s.t_s << ',' << s.mission << ',' << s.agent << ',' << (s.connected ? 1 : 0) << ',' << s.keyframes << ','
             << s.server_keyframes << ',' << s.points << ',' << s.up_bytes << ',' << s.down_bytes << '\n';
  }
  if (!timeline) return Error{ErrorCode::kIoError, "cannot write " + (dir / "timeline.csv").string()};
  return writeIngestSamples(dir / "ingest_ms.csv");
}

// Every batch's ingest time, so that a fleet's pooled percentiles can be computed across replicas (stats.json has
// each agent's own).
Status ServerCore::writeIngestSamples(const std::filesystem::path& file) const {
  std::ofstream out(file);
  out << "mission,agent,ingest_ms,record_wait_ms,map_wait_ms,cpu_ms\n";
  for (const auto& mission : missions_.missions()) {
    for (const auto& shared : mission->agents()) {
      auto record = shared->read();
      const std::vector<double>& ingest = record->ingest_ms.samples();
      const std::vector<double>& record_wait = record->ingest_record_wait_ms.samples();
      const std::vector<double>& map_wait = record->ingest_map_wait_ms.samples();
      const std::vector<double>& cpu = record->ingest_cpu_ms.samples();
      for (std::size_t i = 0; i < ingest.size(); ++i) {
        out << mission->name() << ',' << record->id << ',' << ingest[i] << ',' << record_wait[i] << ',' << map_wait[i]
            << ',' << cpu[i] << '\n';
      }
    }
  }
  if (!out) return Error{ErrorCode::kIoError, "cannot write " + file.string()};
  return Status::Ok();
}

}  // namespace cvislam::server
