// ServerOptions: their checks, their description, the YAML config file, and the defaults that need the build's
// paths. The core that runs with them is server_core.cpp.
#include <cmath>
#include <filesystem>
#include <sstream>
#include <string>

#include "common/config/yaml_section.hpp"
#include "server_cloud/cluster/pg_connection.hpp"
#include "server_cloud/core/server_core.hpp"

namespace cvislam::server {

namespace {
Error invalid(const std::string& what) {
  return Error{ErrorCode::kInvalidArgument, what};
}

}  // namespace

bool isLoopbackAddress(const std::string& host_port) {
  const std::string host = host_port.substr(0, host_port.rfind(':'));
  return host == "localhost" || host.rfind("127.", 0) == 0 || host == "[::1]" || host == "::1";
}

std::string clusterAddress(const ServerOptions& o) {
  if (!o.cluster.advertise.empty()) return o.cluster.advertise;
  const auto colon = o.listen.rfind(':');
  const std::string host = o.listen.substr(0, colon);
  const std::string port = o.listen.substr(colon + 1);
  if (host.empty() || host == "0.0.0.0" || host == "[::]" || host == "::" || port == "0") return {};
  return o.listen;
}

Status ServerOptions::validate() const {
  if (listen.empty() || listen.find(':') == std::string::npos) {
    return invalid("listen address '" + listen + "': give host:port, e.g. 127.0.0.1:50051 (port 0: any free port)");
  }
  if (max_message_bytes < (64U << 10U) || max_message_bytes > (1U << 30U)) {
    return invalid("max_message_bytes must be in [64 KiB, 1 GiB]");
  }
  if (keepalive_time_ms < 100 || keepalive_timeout_ms < 100) return invalid("keepalive times must be >= 100 ms");
  if (memory_quota_mb < 64 || memory_quota_mb > (1U << 20U))
    return invalid("limits.memory_quota_mb must be in [64, 1048576]");
  if (memory_quota_mb * (1U << 20U) < 4 * max_message_bytes) {
    return invalid("limits.memory_quota_mb must hold at least four messages of max_message_bytes");
  }
  if (!std::isfinite(timeline_interval_s) || !(timeline_interval_s >= 0.05)) {
    return invalid("timeline_interval_s must be >= 0.05");
  }
  if (Status s = session.validate(); !s.ok()) return s;
  if (Status s = rate_limit.validate(); !s.ok()) return s;
  if (Status s = stream_limits.validate(); !s.ok()) return s;
  if (Status s = map_read_limits.validate(); !s.ok()) return s;
  if (!std::isfinite(map_read_timeout_s) || !(map_read_timeout_s > 0.0)) {
    return invalid("limits.map_read_timeout_s must be > 0");
  }
  if (!health_listen.empty() && health_listen.find(':') == std::string::npos) {
    return invalid("health_listen address '" + health_listen + "': give host:port, e.g. 0.0.0.0:50052, or \"\"");
  }
  if (!health_listen.empty() && health_listen == listen) {
    return invalid("health_listen must be another port than listen (" + listen + ")");
  }
  if (tls_certificate.empty() != tls_private_key.empty()) {
    return invalid("TLS needs both a certificate and its private key (--tls-cert and --tls-key)");
  }
  if (!insecure && !isLoopbackAddress(listen) && (tls_certificate.empty() || tokens_file.empty())) {
    const std::string missing = tls_certificate.empty() && tokens_file.empty() ? "TLS and tokens"
                                : tls_certificate.empty()                      ? "TLS"
                                                                               : "tokens";
    return invalid("listen " + listen + " can be reached from other machines, but the server would run without " +
                   missing +
                   ": give --tls-cert and --tls-key, and --tokens; or --insecure (server.insecure) to serve "
                   "a network you trust in plaintext or with every mission open");
  }
  if (backend.enabled) {
    if (Status s = backend.validate(); !s.ok()) return s;
  }
  if (cluster.enabled()) {
    if (!store.empty()) {
      return invalid(
          "give either a store file (server.store: one server) or cluster.postgres (replicas sharing a "
          "PostgreSQL store), not both");
    }
    if (!(cluster.lease_ttl_s >= 1.0) || cluster.lease_ttl_s > 600.0) {
      return invalid("cluster.lease_ttl_s must be in [1, 600]");
    }
    if (clusterAddress(*this).empty()) {
      return invalid("cluster.advertise (--advertise) is needed: listen '" + listen +
                     "' is a wildcard address or port 0, which agents redirected to this replica cannot reach");
    }
    if (!cluster.peer_ca.empty() && tls_certificate.empty()) {
      return invalid(
          "cluster.peer_ca (--peer-ca) is for TLS between replicas, but this one runs plaintext (no "
          "--tls-cert)");
    }
  }
  return recognition.enabled ? recognition.validate() : Status::Ok();
}

std::string ServerOptions::describe() const {
  std::ostringstream out;
  out << "  listen:                       " << listen
      << (insecure && !isLoopbackAddress(listen) && (tls_certificate.empty() || tokens_file.empty())
              ? " (--insecure: reachable from other machines without TLS or tokens)"
              : "")
      << "\n"
      << "  health_listen:                " << (health_listen.empty() ? "(none)" : health_listen) << "\n"
      << "  output:                       " << (output.empty() ? "(none)" : output.string()) << "\n"
      << "  max_message_bytes:            " << max_message_bytes << "\n"
      << "  memory_quota_mb:              " << memory_quota_mb << "\n"
      << "  keepalive_time_ms:            " << keepalive_time_ms << "\n"
      << "  keepalive_timeout_ms:         " << keepalive_timeout_ms << "\n"
      << "  timeline_interval_s:          " << timeline_interval_s << "\n"
      << "  downlink_rate_hz:             " << session.downlink_rate_hz << "\n"
      << "  max_corrections_per_message:  " << session.max_corrections_per_message << "\n"
      << "  covisible_map:                " << (session.covisible.enabled ? "true" : "false") << " (K "
      << session.covisible.keyframes << ", budget " << session.covisible.budget_bytes << " B per message"
      << (session.covisible.foreign_refined_only ? ", other agents' keyframes once refined" : "") << ")\n"
      << "  max_keypoints_per_keyframe:   " << session.ingest.max_keypoints_per_keyframe << "\n"
      << "  max_imu_samples_per_keyframe: " << session.ingest.max_imu_samples_per_keyframe << "\n"
      << "  max_maps_per_agent:           " << session.ingest.max_maps_per_agent << "\n"
      << "  recognition.enabled:          " << (recognition.enabled ? "true" : "false") << "\n"
      << "  recognition.vocabulary:       " << recognition.vocabulary.string() << "\n"
      << "  recognition.delay_keyframes:  " << recognition.delay_keyframes << "\n"
      << "  recognition:                  " << recognition.recognition.describe() << "\n"
      << "  backend.enabled:              " << (backend.enabled ? "true" : "false") << "\n"
      << "  backend:                      " << backend.describe() << "\n"
      << "  final_gba:                    " << (final_gba ? "true" : "false") << "\n"
      << "  store:                        " << (store.empty() ? "(none: maps in memory only)" : store.string())
      << " (sync " << toString(store_sync) << ")\n"
      << "  tokens:                       "
      << (tokens_file.empty() ? "(none: every mission open to every client)" : tokens_file.string()) << "\n"
      << "  tls:                          "
      << (tls_certificate.empty() ? "(off: plaintext)" : tls_certificate.string() + ", key " + tls_private_key.string())
      << "\n"
      << "  max_missions:                 " << session.max_missions << "\n"
      << "  max_agents_per_mission:       " << session.max_agents_per_mission << "\n"
      << "  requests_per_s:               " << rate_limit.rate_per_s << " per client (burst " << rate_limit.burst
      << ")\n"
      << "  max_streams:                  " << stream_limits.total << " (" << stream_limits.per_address
      << " per address; a stream without a Hello within " << session.hello_timeout_s << " s is ended)\n"
      << "  max_map_reads:                " << map_read_limits.total << " (" << map_read_limits.per_address
      << " per address, each at most " << map_read_timeout_s << " s)\n"
      << "  cluster:                      "
      << (cluster.enabled()
              ? "replica " + (cluster.replica.empty() ? std::string("(host name)") : cluster.replica) + " at " +
                    clusterAddress(*this) + ", store " + cluster::redactConninfo(cluster.postgres) + ", lease " +
                    std::to_string(cluster.lease_ttl_s) + " s"
              : std::string("(off: this server serves every mission)"))
      << "\n";
  return out.str();
}

Status loadServerConfig(const std::filesystem::path& file, ServerOptions& o) {
  auto loaded = config::loadSections(file.string(), {"server", "link", "limits", "recognition", "backend", "cluster"});
  if (!loaded) return loaded.error();
  const YAML::Node& root = *loaded;
  const auto in_file = [&](const Status& s) { return s.ok() ? s : Status(s.error().withContext(file.string())); };

  config::YamlSection server(root["server"], "server");
  std::string output = o.output.string();
  std::string store = o.store.string();
  std::string store_sync(toString(o.store_sync));
  server.read("listen", o.listen);
  server.read("health_listen", o.health_listen);
  server.read("insecure", o.insecure);
  server.read("output", output);
  server.read("timeline_interval_s", o.timeline_interval_s);
  server.read("store", store);
  server.read("store_sync", store_sync);
  std::string tokens = o.tokens_file.string();
  std::string tls_cert = o.tls_certificate.string();
  std::string tls_key = o.tls_private_key.string();
  server.read("tokens", tokens);
  server.read("tls_certificate", tls_cert);
  server.read("tls_private_key", tls_key);
  if (Status s = server.finish(); !s.ok()) return in_file(s);
  o.output = output;
  o.store = store;
  o.tokens_file = tokens;
  o.tls_certificate = tls_cert;
  o.tls_private_key = tls_key;
  auto sync = parseStoreSync(store_sync);
  if (!sync) return in_file(Status(sync.error().withContext("server.store_sync")));
  o.store_sync = *sync;

  config::YamlSection cluster(root["cluster"], "cluster");
  cluster.read("postgres", o.cluster.postgres);
  cluster.read("replica", o.cluster.replica);
  cluster.read("advertise", o.cluster.advertise);
  cluster.read("lease_ttl_s", o.cluster.lease_ttl_s);
  std::string peer_ca = o.cluster.peer_ca.string();
  cluster.read("peer_ca", peer_ca);
  o.cluster.peer_ca = peer_ca;
  if (Status s = cluster.finish(); !s.ok()) return in_file(s);

  config::YamlSection link(root["link"], "link");
  link.read("downlink_rate_hz", o.session.downlink_rate_hz);
  link.read("max_corrections_per_message", o.session.max_corrections_per_message);
  link.read("covisible_map", o.session.covisible.enabled);
  link.read("covisible_keyframes", o.session.covisible.keyframes);
  link.read("covisible_seed_keyframes", o.session.covisible.seed_keyframes);
  link.read("covisible_own_recent_excluded", o.session.covisible.own_recent_excluded);
  link.read("covisible_foreign_refined_only", o.session.covisible.foreign_refined_only);
  link.read("downlink_budget_bytes", o.session.covisible.budget_bytes);
  link.read("keepalive_time_ms", o.keepalive_time_ms);
  link.read("keepalive_timeout_ms", o.keepalive_timeout_ms);
  if (Status s = link.finish(); !s.ok()) return in_file(s);

  config::YamlSection limits(root["limits"], "limits");
  limits.read("max_message_bytes", o.max_message_bytes);
  limits.read("memory_quota_mb", o.memory_quota_mb);
  limits.read("max_keypoints_per_keyframe", o.session.ingest.max_keypoints_per_keyframe);
  limits.read("max_imu_samples_per_keyframe", o.session.ingest.max_imu_samples_per_keyframe);
  limits.read("max_maps_per_agent", o.session.ingest.max_maps_per_agent);
  limits.read("max_missions", o.session.max_missions);
  limits.read("max_agents_per_mission", o.session.max_agents_per_mission);
  limits.read("requests_per_s", o.rate_limit.rate_per_s);
  limits.read("request_burst", o.rate_limit.burst);
  limits.read("max_streams", o.stream_limits.total);
  limits.read("max_streams_per_address", o.stream_limits.per_address);
  limits.read("hello_timeout_s", o.session.hello_timeout_s);
  limits.read("max_map_reads", o.map_read_limits.total);
  limits.read("max_map_reads_per_address", o.map_read_limits.per_address);
  limits.read("map_read_timeout_s", o.map_read_timeout_s);
  limits.read("agent_hello_burst", o.session.agent_hello_burst);
  limits.read("agent_hellos_per_minute", o.session.agent_hellos_per_minute);
  if (Status s = limits.finish(); !s.ok()) return in_file(s);

  config::YamlSection recognition(root["recognition"], "recognition");
  std::string vocabulary = o.recognition.vocabulary.string();
  recognition::RecognitionOptions& r = o.recognition.recognition;
  recognition.read("enabled", o.recognition.enabled);
  recognition.read("vocabulary", vocabulary);
  recognition.read("queue_capacity", o.recognition.queue_capacity);
  recognition.read("delay_keyframes", o.recognition.delay_keyframes);
  recognition.read("max_candidates", r.max_candidates);
  recognition.read("min_score_ratio", r.min_score_ratio);
  recognition.read("loop_min_interval_s", r.loop_min_interval_s);
  recognition.read("min_matches", r.min_matches);
  recognition.read("min_inliers", r.min_inliers);
  recognition.read("max_reprojection_px", r.max_reprojection_px);
  recognition.read("max_tilt_deg", r.max_tilt_deg);
  recognition.read("max_scale_error", r.max_scale_error);
  if (Status s = recognition.finish(); !s.ok()) return in_file(s);
  if (!vocabulary.empty()) o.recognition.vocabulary = vocabulary;  // "": the shipped one

  config::YamlSection backend(root["backend"], "backend");
  backend::BackendOptions& b = o.backend;
  backend.read("enabled", b.enabled);
  backend.read("merge_maps", b.merge_maps);
  backend.read("close_loops", b.close_loops);
  backend.read("gba_after_change", b.gba_after_change);
  backend.read("final_gba", o.final_gba);
  backend.read("loop_cooldown_keyframes", b.loop_cooldown_keyframes);
  backend.read("frame_follows_keyframes", b.frame_follows_keyframes);
  backend.read("loop_cancels_gba_m", b.loop_cancels_gba_m);
  backend.read("loop_cancels_gba_deg", b.loop_cancels_gba_deg);
  backend.read("gba_structure_iterations", b.gba.structure_iterations);
  backend.read("gba_full_iterations", b.gba.full_iterations);
  backend.read("gba_threads", b.gba.threads);
  backend.read("gba_max_solver_time_s", b.gba.max_solver_time_s);
  backend.read("gba_time_budget_s", b.gba_time_budget_s);
  backend.read("gba_gauge_position_yaw_only", b.gba.gauge_position_yaw_only);
  backend.read("pose_graph_strong_covisibility", b.pose_graph.strong_covisibility);
  backend.read("merge_correction_keyframes", b.merge_correction_keyframes);
  backend.read("gba_function_tolerance", b.gba.function_tolerance);
  backend.read("gba_iterative_schur", b.gba.iterative_schur);
  std::string gba_solver = toString(b.gba.solver);
  backend.read("gba_solver", gba_solver);
  backend.read("fusion_search_radius_px", b.fusion.search_radius_px);
  backend.read("fusion_max_descriptor_distance", b.fusion.max_descriptor_distance);
  backend.read("fuse_new_keyframes", b.fuse_new_keyframes);
  backend.read("fusion_nearby_keyframes", b.fusion.nearby_keyframes);
  backend.read("fusion_nearby_radius_m", b.fusion.nearby_radius_m);
  backend.read("fusion_nearby_max_angle_deg", b.fusion.nearby_max_angle_deg);
  backend.read("redundancy_removal", b.redundancy.enabled);
  backend.read("gba_every_keyframes", b.gba_every_keyframes);
  backend.read("gba_window_above_keyframes", b.gba_window_above_keyframes);
  backend.read("loop_window_move_m", b.loop_window_move_m);
  backend.read("loop_window_move_deg", b.loop_window_move_deg);
  backend.read("redundancy_every_keyframes", b.redundancy_every_keyframes);
  backend.read("redundancy_final_pass", b.final_redundancy_pass);
  backend.read("redundant_fraction", b.redundancy.redundant_fraction);
  backend.read("redundancy_min_other_observers", b.redundancy.min_other_observers);
  backend.read("redundancy_max_imu_gap_s", b.redundancy.max_imu_gap_s);
  backend.read("redundancy_keep_newest", b.redundancy.keep_newest);
  backend.read("redundancy_seed", b.redundancy.seed);
  if (Status s = backend.finish(); !s.ok()) return in_file(s);
  auto solver = backend::parseGbaSolver(gba_solver);
  if (!solver) return in_file(Status(solver.error().withContext("backend.gba_solver")));
  b.gba.solver = *solver;
  return Status::Ok();  // the caller validates once the command line is applied: options combine from both
}

std::filesystem::path shippedPath(const std::filesystem::path& in_source_tree, const std::filesystem::path& installed) {
  std::error_code ec;
  if (std::filesystem::exists(in_source_tree, ec)) return in_source_tree;
  const std::filesystem::path binary = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    const auto beside = binary.parent_path().parent_path() / "share" / "cvislam" / installed;
    if (std::filesystem::exists(beside, ec)) return beside;
  }
  return in_source_tree;
}

recognition::RecognitionWorkerOptions defaultRecognitionOptions() {
  recognition::RecognitionWorkerOptions o;
  const std::filesystem::path vocabulary = CVISLAM_DEFAULT_VOCABULARY;
  o.vocabulary = shippedPath(vocabulary, std::filesystem::path("vocabulary") / vocabulary.filename());
  return o;
}

}  // namespace cvislam::server
