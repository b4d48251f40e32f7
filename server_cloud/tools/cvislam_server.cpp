// cvislam_server: the collaborative SLAM server. Agents stream their maps to it over the agent link; it keeps
// one map stack per mission, and API clients read its maps over cvislam.v1.MapService (cvislam_mapctl) and its
// statistics over cvislam.v1.Monitor.
//
//   cvislam_server --listen HOST:PORT [--config FILE] [--output DIR] [--port-file FILE] [--store FILE]
//
// HOST:PORT may use port 0: the server then takes a free port and prints it ("listening on 127.0.0.1:PORT",
// and into --port-file). It runs until SIGINT or SIGTERM, then ends the agents' streams, writes DIR
// (stats.json, timeline.csv, <mission>/keyframes_agent<N>.txt) and prints what it held.
// Exit status: 0 after a clean stop, 1 it could not start or write its outputs, 2 bad command line or config.
#include <pthread.h>

#include <algorithm>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/trace/trace.hpp"
#include "cvislam/v1/monitor.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/service/grpc_server.hpp"
#include "server_cloud/service/metrics_endpoint.hpp"
#include "server_cloud/viewer/viewer_endpoint.hpp"
#include "server_cloud/viewer/viewer_hub.hpp"
#include "server_cloud/viewer/viewer_publisher.hpp"

namespace {

using cvislam::server::ServerOptions;

std::string megabytes(std::uint64_t bytes) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.2f", static_cast<double>(bytes) / 1e6);
  return text;
}

std::uint64_t bytesOf(const google::protobuf::Map<std::string, cvislam::v1::TrafficCounter>& counters) {
  auto it = counters.find("message");
  return it == counters.end() ? 0 : it->second.bytes();
}

void printStatus(const cvislam::server::ServerCore& core) {
  cvislam::v1::ServerStats stats;
  core.fillStats("", stats);
  int connected = 0;
  std::uint64_t keyframes = 0;
  std::uint64_t points = 0;
  for (const auto& a : stats.agents()) {
    connected += a.connected() ? 1 : 0;
    keyframes += a.keyframes();
    points += a.points();
  }
  std::fprintf(stderr, "[server] t=%.0f s  agents %d connected / %d known  maps %d  keyframes %llu  points %llu\n",
               stats.uptime_s(), connected, stats.agents_size(), stats.maps_size(),
               static_cast<unsigned long long>(keyframes), static_cast<unsigned long long>(points));
}

void printSummary(const cvislam::server::ServerCore& core) {
  cvislam::v1::ServerStats stats;
  core.fillStats("", stats);
  std::printf("%-16s %5s %5s %9s %9s %5s %10s %10s %8s %8s\n", "mission", "agent", "conn", "keyframes", "points",
              "maps", "up[MB]", "down[MB]", "batches", "dup");
  for (const auto& a : stats.agents()) {
    const auto batches = a.up().count("batch") != 0 ? a.up().at("batch").messages() : 0;
    std::printf("%-16s %5u %5u %9llu %9llu %5u %10s %10s %8llu %8llu\n", a.mission().c_str(), a.agent_id(),
                a.connections(), static_cast<unsigned long long>(a.keyframes()),
                static_cast<unsigned long long>(a.points()), a.maps(), megabytes(bytesOf(a.up())).c_str(),
                megabytes(bytesOf(a.down())).c_str(), static_cast<unsigned long long>(batches),
                static_cast<unsigned long long>(a.duplicate_batches()));
    if (!a.last_error().empty()) std::printf("  last error of agent %u: %s\n", a.agent_id(), a.last_error().c_str());
  }
  if (const auto* worker = core.recognition(); worker != nullptr) {
    for (const std::string& mission : worker->missions()) {
      const auto c = worker->counters(mission);
      std::printf(
          "recognition %s: %llu keyframes, %llu queries, %llu candidates verified, %llu loops and %llu map "
          "matches accepted, %.1f s busy, %llu events dropped\n",
          mission.c_str(), static_cast<unsigned long long>(c.keyframes), static_cast<unsigned long long>(c.queries),
          static_cast<unsigned long long>(c.candidates), static_cast<unsigned long long>(c.loops),
          static_cast<unsigned long long>(c.map_matches), c.busy_s, static_cast<unsigned long long>(c.dropped_events));
    }
  }
}

struct CommandLine {
  std::string listen;
  std::string config;
  std::string output;
  std::string port_file;
  double status_interval_s = 10.0;
  bool quiet = false;
  std::string vocabulary;
  bool no_recognition = false;
  bool no_backend = false;
  bool no_redundancy = false;
  bool no_gba = false;
  std::string store;
  std::string store_sync;
  std::string tokens;
  std::string tls_cert;
  std::string tls_key;
  bool insecure = false;
  std::string health_listen;
  std::optional<std::size_t> max_missions;
  std::optional<std::size_t> max_agents;
  std::optional<double> requests_per_s;
  std::string postgres;
  std::string replica;
  std::string advertise;
  std::optional<double> lease_ttl_s;
  std::string peer_ca;
  std::vector<std::string> load_missions;
  std::string load_from;
  std::string trace;
  std::string metrics_listen;
  std::size_t trace_events_per_thread = std::size_t{1} << 16;
  std::string viewer_listen;
  std::string viewer_port_file;
  // Installed: the page by `cmake --install`, three.js by the server image's npm step.
  std::string viewer_dir = cvislam::server::shippedPath(CVISLAM_DEFAULT_VIEWER_DIR, "viewer").string();
  std::string viewer_three =
      cvislam::server::shippedPath(CVISLAM_DEFAULT_VIEWER_THREE, "node_modules/three/build").string();
  double viewer_period_s = 0.2;
  std::size_t viewer_points = 20000;
  std::size_t viewer_queue = 256;
  std::size_t viewer_send_buffer = std::size_t{1} << 20U;
  std::string record;
};

// Every option, bound to `cl`.
void addOptions(CLI::App& app, CommandLine& cl) {
  app.add_option("--listen", cl.listen, "host:port to serve on; port 0 takes a free port [127.0.0.1:50051]");
  app.add_option("--config", cl.config, "YAML config (see deploy/server_config.yaml); command-line options win");
  app.add_option("--output", cl.output,
                 "Folder written at shutdown: stats.json, timeline.csv, <mission>/keyframes_agent<N>.txt");
  app.add_option("--port-file", cl.port_file, "Write the bound port here once serving (for scripts using port 0)");
  app.add_option("--status-interval", cl.status_interval_s, "Seconds between status lines on stderr; 0: none [10]");
  app.add_flag("--quiet", cl.quiet, "Print neither the options nor status lines");
  app.add_option("--vocabulary", cl.vocabulary,
                 "Place recognition's vocabulary file [the shipped deploy/vocabulary/orb_k10_l5.cvvoc]");
  app.add_flag("--no-recognition", cl.no_recognition,
               "Run without place recognition (and so without merges and loops)");
  app.add_flag("--no-backend", cl.no_backend, "Run without the back-end: no map fusion, loop closure, GBA or removal");
  app.add_flag("--no-redundancy", cl.no_redundancy, "Keep every keyframe (no redundancy removal)");
  app.add_flag("--no-gba", cl.no_gba,
               "No global BA (neither after merges and loops, nor periodic, nor on every map at shutdown): the "
               "server's keyframes "
               "keep the agents' estimates, moved only by merges and pose graphs");
  app.add_option("--store", cl.store,
                 "Map store file (SQLite): every batch is durable before it is acknowledged, and a restarted server "
                 "replays it and holds everything it acknowledged. Made when missing [none: maps in memory only]");
  app.add_option("--store-sync", cl.store_sync,
                 "full: a commit survives power loss; normal: it survives a crash of the process (SIGKILL) but maybe "
                 "not of the machine; off: left to the OS [full]");
  app.add_option("--tokens", cl.tokens,
                 "Tokens file: one 'MISSION TOKEN' line per mission ('*': an operator token for every mission). "
                 "Agents and clients then present their mission's token; a mission not listed cannot be opened "
                 "[none: every mission open to every client]");
  app.add_option("--tls-cert", cl.tls_cert, "PEM certificate (chain) for TLS on the port [none: plaintext]");
  app.add_option("--tls-key", cl.tls_key, "PEM private key of --tls-cert");
  app.add_flag("--insecure", cl.insecure,
               "Start on an address other machines can reach (e.g. 0.0.0.0) without TLS or without tokens; without "
               "it such a server refuses to start. For a network you trust");
  app.add_option("--health-listen", cl.health_listen,
                 "Also serve grpc.health.v1 alone, in plaintext, on this host:port (for Kubernetes probes, which "
                 "cannot speak TLS) [none]");
  app.add_option("--max-missions", cl.max_missions, "Missions this server holds at most [64]");
  app.add_option("--max-agents-per-mission", cl.max_agents, "Agents of one mission at most [32]");
  app.add_option("--requests-per-s", cl.requests_per_s,
                 "Requests per second per client (map service and monitor calls, agent streams opened), with a "
                 "burst of twice as many; 0: no limit [50]");
  app.add_option("--postgres", cl.postgres,
                 "Scale-out: run as one of several replicas sharing this PostgreSQL store (a libpq connection "
                 "string, e.g. 'host=db port=5432 user=cvislam dbname=cvislam'). Each mission is served by the "
                 "replica holding its lease; agents that reach another replica are redirected, and a replica that "
                 "dies has its missions taken over once its leases lapse. Replaces --store [none]");
  app.add_option("--replica", cl.replica, "Scale-out: this replica's name in leases and logs [the host name]");
  app.add_option("--advertise", cl.advertise,
                 "Scale-out: host:port where agents and clients reach this replica (redirects name it) [--listen, "
                 "unless it is a wildcard address or port 0]");
  app.add_option("--lease-ttl", cl.lease_ttl_s,
                 "Scale-out: seconds a replica that stops renewing keeps its missions; the takeover time after a "
                 "crash is about this plus a third of it [3]");
  app.add_option("--peer-ca", cl.peer_ca,
                 "Scale-out with TLS: the CA (PEM) of the other replicas' certificates; a map-service read of a "
                 "mission another replica serves is passed to it over TLS [the --tls-cert file]")
      ->check(CLI::ExistingFile);
  app.add_option("--load-mission", cl.load_missions,
                 "Map reuse: FROM=AS loads mission FROM (a finished one) as the new mission AS before serving, "
                 "stored in --store; agents of AS are matched against its map. Repeatable. Loaded agents keep their "
                 "ids: give AS's agents other ids")
      ->check([](const std::string& v) {
        const auto eq = v.find('=');
        return eq == std::string::npos || eq == 0 || eq + 1 == v.size() ? std::string("give FROM=AS") : std::string();
      });
  app.add_option("--metrics-listen", cl.metrics_listen,
                 "host:port serving Prometheus metrics at /metrics over plain HTTP (agents, traffic, ingest and store "
                 "latency, recognition, merges, loops, GBA, limits, leases) [none]; port 0 takes a free port");
  app.add_option("--trace", cl.trace,
                 "Write a Chrome Trace Event JSON of ingest, store, recognition, fusion, merges, loops, GBA and the "
                 "downlink here at shutdown (opens in https://ui.perfetto.dev; cvislam_trace joins it with the "
                 "agents')");
  app.add_option("--trace-events-per-thread", cl.trace_events_per_thread,
                 "Events each thread keeps for --trace, the newest (about 104 bytes each) [65536]")
      ->check(CLI::Range(16, 1 << 24));
  app.add_option("--load-from", cl.load_from,
                 "The store --load-mission reads (not in use by a running server) [this server's --store]");
  app.add_option("--viewer-listen", cl.viewer_listen,
                 "host:port serving the live viewer: the browser page over HTTP and the Foxglove WebSocket protocol "
                 "(Foxglove, Lichtblick) on the same port; TLS with --tls-cert; port 0 takes a free port [none]");
  app.add_option("--viewer-port-file", cl.viewer_port_file, "Write the viewer's bound port here once serving");
  app.add_option("--viewer-dir", cl.viewer_dir, "The browser viewer's files, served at / [" + cl.viewer_dir + "]");
  app.add_option("--viewer-three", cl.viewer_three,
                 "three.js' build/ folder, served at /three/ (deploy/install_deploy_tools.sh installs it) [" +
                     cl.viewer_three + "]");
  app.add_option("--viewer-period", cl.viewer_period_s,
                 "Seconds between the viewer's looks at the missions (what changed goes out) [0.2]")
      ->check(CLI::Range(0.01, 60.0));
  app.add_option("--viewer-points", cl.viewer_points, "Map points per map a viewer gets at most [20000]")
      ->check(CLI::Range(0, 5000000));
  app.add_option("--viewer-queue", cl.viewer_queue,
                 "Messages waiting per viewer at most; the oldest is dropped beyond that [256]")
      ->check(CLI::Range(1, 1000000));
  app.add_option("--viewer-send-buffer", cl.viewer_send_buffer,
                 "Bytes handed to a viewer's socket and not yet sent, at most; beyond them messages wait in the queue "
                 "[1048576]")
      ->check(CLI::Range(4096, 1 << 30));
  app.add_option("--record", cl.record,
                 "Write each mission to DIR/<mission>.mcap (the viewer's channels; opens in Foxglove or Lichtblick)");
}

// The command line over the config file: each option given replaces the config's value. Returns the exit
// status on an error (2: a bad value), nothing when the options hold.
std::optional<int> applyCommandLine(const CommandLine& cl, ServerOptions& options) {
  if (!cl.config.empty()) {
    if (auto s = cvislam::server::loadServerConfig(cl.config, options); !s.ok()) {
      std::cerr << "cvislam_server: " << s.error().toString() << "\n";
      return 2;
    }
  }
  if (!cl.listen.empty()) options.listen = cl.listen;
  if (!cl.output.empty()) options.output = cl.output;
  if (!cl.vocabulary.empty()) options.recognition.vocabulary = cl.vocabulary;
  if (!cl.store.empty()) options.store = cl.store;
  if (!cl.store_sync.empty()) {
    auto sync = cvislam::server::parseStoreSync(cl.store_sync);
    if (!sync) {
      std::cerr << "cvislam_server: --store-sync: " << sync.error().message() << "\n";
      return 2;
    }
    options.store_sync = *sync;
  }
  if (!cl.tokens.empty()) options.tokens_file = cl.tokens;
  if (!cl.tls_cert.empty()) options.tls_certificate = cl.tls_cert;
  if (!cl.tls_key.empty()) options.tls_private_key = cl.tls_key;
  if (!cl.health_listen.empty()) options.health_listen = cl.health_listen;
  if (cl.insecure) options.insecure = true;
  if (!cl.postgres.empty()) options.cluster.postgres = cl.postgres;
  if (!cl.replica.empty()) options.cluster.replica = cl.replica;
  if (!cl.advertise.empty()) options.cluster.advertise = cl.advertise;
  if (cl.lease_ttl_s) options.cluster.lease_ttl_s = *cl.lease_ttl_s;
  if (!cl.peer_ca.empty()) options.cluster.peer_ca = cl.peer_ca;
  if (cl.max_missions) options.session.max_missions = *cl.max_missions;
  if (cl.max_agents) options.session.max_agents_per_mission = *cl.max_agents;
  if (cl.requests_per_s) {
    options.rate_limit.rate_per_s = *cl.requests_per_s;
    options.rate_limit.burst = std::max(1.0, 2.0 * *cl.requests_per_s);
  }
  if (cl.no_recognition) options.recognition.enabled = false;
  if (cl.no_backend) options.backend.enabled = false;
  if (cl.no_redundancy) options.backend.redundancy.enabled = false;
  if (cl.no_gba) {
    options.backend.gba_after_change = false;
    options.backend.gba_every_keyframes = 0;
    options.final_gba = false;
  }
  if (auto s = options.validate(); !s.ok()) {
    std::cerr << "cvislam_server: " << s.error().message() << "\n";
    return 2;
  }
  if (cl.status_interval_s < 0) {
    std::cerr << "cvislam_server: --status-interval must be >= 0\n";
    return 2;
  }
  return std::nullopt;
}

// Opens the single-node store and replays it, or joins the replicas' shared store. False (after saying why)
// when it cannot.
bool openStore(cvislam::server::ServerCore& core, const ServerOptions& options) {
  if (options.cluster.enabled()) {
    auto joined = core.openStore();
    if (!joined) {
      std::cerr << "cvislam_server: " << joined.error().message() << "\n";
      return false;
    }
    std::fprintf(stderr, "[server] scale-out: shared store %s; missions are loaded as this replica takes them\n",
                 joined->store.c_str());
  } else if (!options.store.empty()) {
    std::fprintf(stderr, "[server] opening the map store %s\n", options.store.string().c_str());
    auto recovered = core.openStore();
    if (!recovered) {
      std::cerr << "cvislam_server: " << recovered.error().message() << "\n";
      return false;
    }
    const auto& r = *recovered;
    std::fprintf(stderr,
                 "[server] map store: %s; replayed %llu batches and %llu hellos (%.2f MB) of %zu agents in %zu "
                 "missions, %llu keyframes, in %.2f s\n",
                 r.store.c_str(), static_cast<unsigned long long>(r.batches), static_cast<unsigned long long>(r.hellos),
                 static_cast<double>(r.bytes) / 1e6, r.agents, r.missions, static_cast<unsigned long long>(r.keyframes),
                 r.seconds);
  }
  return true;
}

// Map reuse: each FROM=AS of --load-mission, read from --load-from or from this server's own store. False
// (after saying why) when one cannot be loaded.
bool loadMissions(cvislam::server::ServerCore& core, const CommandLine& cl) {
  std::unique_ptr<cvislam::server::MapStore> source;
  if (!cl.load_from.empty()) {
    cvislam::server::SqliteStoreOptions source_options;
    source_options.path = cl.load_from;
    source_options.create_if_missing = false;
    auto opened = cvislam::server::openSqliteStore(source_options);
    if (!opened) {
      std::cerr << "cvislam_server: --load-from: " << opened.error().message() << "\n";
      return false;
    }
    source = std::move(opened).value();
  }
  for (const std::string& spec : cl.load_missions) {
    const std::string from = spec.substr(0, spec.find('='));
    const std::string as = spec.substr(spec.find('=') + 1);
    auto loaded = core.loadMission(source.get(), from, as);
    if (!loaded) {
      std::cerr << "cvislam_server: --load-mission " << spec << ": " << loaded.error().message() << "\n";
      return false;
    }
    if (loaded->already_held) {
      std::fprintf(stderr, "[server] mission '%s' is held already (loaded before): not loaded again\n", as.c_str());
    } else {
      std::fprintf(stderr,
                   "[server] loaded mission '%s' of %s as '%s': %llu batches and %llu hellos, %llu keyframes, in "
                   "%.2f s\n",
                   from.c_str(), loaded->source.c_str(), as.c_str(), static_cast<unsigned long long>(loaded->batches),
                   static_cast<unsigned long long>(loaded->hellos), static_cast<unsigned long long>(loaded->keyframes),
                   loaded->seconds);
    }
  }
  return true;
}

// Written through a rename, so that a script polling for the file never reads half of it.
void writePortFile(const std::string& port_file, int port) {
  const std::string tmp = port_file + ".tmp";
  std::ofstream(tmp) << port << "\n";
  std::filesystem::rename(tmp, port_file);
}

// The live viewer (--viewer-listen) and the recordings (--record): the publisher runs when either is asked for.
// False (after saying why) when one cannot start.
bool startViewer(const CommandLine& cl, const ServerOptions& options, const cvislam::server::ServerCore& core,
                 cvislam::server::viewer::ViewerHub& hub,
                 std::unique_ptr<cvislam::server::viewer::ViewerEndpoint>& endpoint,
                 std::unique_ptr<cvislam::server::viewer::ViewerPublisher>& publisher) {
  namespace viewer = cvislam::server::viewer;
  if (cl.viewer_listen.empty() && cl.record.empty()) return true;
  if (!cl.viewer_listen.empty()) {
    viewer::EndpointOptions endpoint_options;
    endpoint_options.listen = cl.viewer_listen;
    endpoint_options.static_dir = cl.viewer_dir;
    endpoint_options.three_dir = cl.viewer_three;
    endpoint_options.tls_cert = options.tls_certificate;
    endpoint_options.tls_key = options.tls_private_key;
    endpoint_options.socket_buffer_bytes = cl.viewer_send_buffer;
    auto started = viewer::ViewerEndpoint::start(hub, core.tokens(), endpoint_options);
    if (!started) {
      std::cerr << "cvislam_server: --viewer-listen: " << started.error().message() << "\n";
      return false;
    }
    endpoint = std::move(*started);
    if (!std::filesystem::exists(std::filesystem::path(cl.viewer_three) / "three.module.js")) {
      std::fprintf(stderr,
                   "[server] viewer: three.js is not in %s: the page cannot draw until "
                   "deploy/install_deploy_tools.sh has run (or give --viewer-three)\n",
                   cl.viewer_three.c_str());
    }
    std::printf("viewer on port %d (%s://HOST:%d/; Foxglove WebSocket on the same port)\n", endpoint->port(),
                endpoint->tls() ? "https" : "http", endpoint->port());
    std::fflush(stdout);
    if (!cl.viewer_port_file.empty()) writePortFile(cl.viewer_port_file, endpoint->port());
  }
  viewer::PublisherOptions publisher_options;
  publisher_options.period_s = cl.viewer_period_s;
  publisher_options.feed.max_points_per_map = cl.viewer_points;
  publisher_options.record_dir = cl.record;
  auto started = viewer::ViewerPublisher::start(core.missions(), endpoint ? &hub : nullptr, publisher_options);
  if (!started) {
    std::cerr << "cvislam_server: " << started.error().message() << "\n";
    return false;
  }
  publisher = std::move(*started);
  return true;
}

// Waits for SIGINT or SIGTERM (blocked in every thread, so only this wait sees them), printing a status line
// every `status_interval_s` (0: none). Returns the signal.
int waitForStopSignal(const sigset_t& signals, const cvislam::server::ServerCore& core, double status_interval_s) {
  double since_status = 0.0;
  for (;;) {
    timespec timeout{0, 500'000'000};
    if (const int s = sigtimedwait(&signals, nullptr, &timeout); s > 0) return s;
    since_status += 0.5;
    if (status_interval_s > 0 && since_status >= status_interval_s) {
      printStatus(core);
      since_status = 0.0;
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"cvislam_server: the collaborative SLAM server (agent link, map stacks, monitoring)"};
  CommandLine cl;
  addOptions(app, cl);
  CLI11_PARSE(app, argc, argv);

  ServerOptions options;
  if (auto status = applyCommandLine(cl, options)) return *status;
  if (!cl.port_file.empty()) std::filesystem::remove(cl.port_file);

  // Signals go to this thread only (sigtimedwait); every thread made from here on inherits the mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  std::signal(SIGPIPE, SIG_IGN);

  // Before the workers start: they bind to it on their threads; gRPC's threads get a track on their first event.
  std::optional<cvislam::trace::Session> trace_session;
  if (!cl.trace.empty()) {
    cvislam::trace::SessionOptions trace_options;
    trace_options.process_name = "server";
    trace_options.events_per_thread = cl.trace_events_per_thread;
    trace_options.trace_unbound_threads = true;
    trace_session.emplace(trace_options);
  }
  if (!cl.quiet) std::fprintf(stderr, "[server] options:\n%s", options.describe().c_str());
  cvislam::server::ServerCore core(options);
  if (auto s = core.loadTokens(); !s.ok()) {
    std::cerr << "cvislam_server: " << s.error().message() << "\n";
    return 2;
  }
  if (core.tokens().enabled()) {
    std::fprintf(stderr, "[server] tokens: %zu missions listed in %s\n", core.tokens().missions(),
                 options.tokens_file.string().c_str());
  }
  if (auto s = core.startWorkers(); !s.ok()) {
    std::cerr << "cvislam_server: " << s.error().message() << "\n";
    return 1;
  }
  if (!openStore(core, options)) return 1;
  if (!cl.load_missions.empty() && !loadMissions(core, cl)) return 1;
  auto server = cvislam::server::GrpcServer::start(core);
  if (!server) {
    std::cerr << "cvislam_server: " << server.error().message() << "\n";
    return 1;
  }
  std::printf("listening on %s\n", (*server)->address().c_str());
  if ((*server)->healthPort() != 0) std::printf("health checks on port %d (plaintext)\n", (*server)->healthPort());
  std::fflush(stdout);
  std::unique_ptr<cvislam::server::MetricsEndpoint> metrics;
  if (!cl.metrics_listen.empty()) {
    auto started = cvislam::server::MetricsEndpoint::start(core, cl.metrics_listen);
    if (!started) {
      std::cerr << "cvislam_server: " << started.error().message() << "\n";
      return 1;
    }
    metrics = std::move(*started);
    std::printf("metrics on port %d (http://HOST:%d/metrics)\n", metrics->port(), metrics->port());
    std::fflush(stdout);
  }
  // The viewer's hub lives as long as its endpoint and publisher, which both point at it.
  cvislam::server::viewer::ViewerHub viewer_hub({cl.viewer_queue});
  std::unique_ptr<cvislam::server::viewer::ViewerEndpoint> viewer;
  std::unique_ptr<cvislam::server::viewer::ViewerPublisher> publisher;
  if (!startViewer(cl, options, core, viewer_hub, viewer, publisher)) return 1;
  if (!cl.port_file.empty()) writePortFile(cl.port_file, (*server)->port());

  const int received = waitForStopSignal(signals, core, cl.quiet ? 0.0 : cl.status_interval_s);
  std::fprintf(stderr, "[server] %s: stopping\n", received == SIGINT ? "SIGINT" : "SIGTERM");
  (*server)->shutdown();
  // Nothing is appended from here on: the other replicas may take the missions over while this one finishes.
  if (auto s = core.leaveCluster(); !s.ok()) {
    std::fprintf(stderr, "[server] could not release the mission leases (they lapse by themselves): %s\n",
                 s.error().message().c_str());
  }
  printSummary(core);
  if (!options.output.empty()) {
    if (auto s = core.writeOutputs(options.output); !s.ok()) {
      std::cerr << "cvislam_server: " << s.error().toString() << "\n";
      return 1;
    }
    std::printf("outputs: %s\n", options.output.string().c_str());
  }
  if (viewer) {
    std::printf("viewer: %llu messages dropped for viewers that did not keep up\n",
                static_cast<unsigned long long>(viewer_hub.droppedTotal()));
  }
  viewer.reset();
  if (publisher) {
    // After the outputs: the recordings end with the map as the final GBA left it.
    if (auto s = publisher->finish(); !s.ok()) {
      std::cerr << "cvislam_server: " << s.error().message() << "\n";
      return 1;
    }
    for (const auto& [mission, file] : publisher->recordings()) {
      std::printf("recording of mission %s: %s\n", mission.c_str(), file.string().c_str());
    }
  }
  if (trace_session) {  // the workers are idle and gRPC's threads have stopped
    if (auto s = trace_session->writeChromeJson(cl.trace); !s.ok()) {
      std::cerr << "cvislam_server: " << s.error().toString() << "\n";
      return 1;
    }
    std::printf("trace: %s\n", cl.trace.c_str());
  }
  return 0;
}
