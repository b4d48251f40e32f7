// The server's core: every mission's map stack, the agents' sessions, statistics, and what the server writes
// at the end. Plain C++: the gRPC adapters in server_cloud/service sit on top, and tests drive it directly.
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "common/core/synchronized.hpp"
#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/access/rate_limiter.hpp"
#include "server_cloud/access/stream_limits.hpp"
#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/cluster/mission_leases.hpp"
#include "server_cloud/cluster/replica_coordinator.hpp"
#include "server_cloud/ingest/agent_session.hpp"
#include "server_cloud/recognition/recognition_worker.hpp"
#include "server_cloud/stack/map_stack.hpp"
#include "server_cloud/store/map_store.hpp"
#include "server_cloud/store/sqlite_store.hpp"

namespace cvislam::v1 {
class ServerStats;
}

namespace cvislam::server {

// Place recognition's defaults, with the vocabulary file of this build's source tree
// (deploy/vocabulary/orb_k10_l5.cvvoc).
recognition::RecognitionWorkerOptions defaultRecognitionOptions();

// A file or folder this build ships: in the source tree where the build ran, else where `cmake --install` put it
// beside the binary, <prefix>/share/cvislam/<installed> (as in the container images). When neither exists, the
// source tree's path, so that what fails to open names it.
std::filesystem::path shippedPath(const std::filesystem::path& in_source_tree, const std::filesystem::path& installed);

// Scale-out (server_cloud/cluster): replicas that share a PostgreSQL store, each serving the missions whose leases it
// holds. Off when `postgres` is empty.
struct ClusterOptions {
  std::string postgres;      // libpq connection string of the shared store, e.g. "host=db port=5432 dbname=cvislam"
  std::string replica;       // this replica's name in the leases and logs; empty: the host name
  std::string advertise;     // host:port where agents and clients reach this replica; empty: `listen`, when usable
  double lease_ttl_s = 3.0;  // a replica that stops renewing loses its missions this long after
  // With TLS: the CA (PEM) that the other replicas' certificates chain to, for the map-service reads one replica
  // passes to a mission's owner. Empty: this replica's own certificate (one certificate for the deployment).
  std::filesystem::path peer_ca;

  [[nodiscard]] bool enabled() const { return !postgres.empty(); }
};

struct ServerOptions;
// Whether host:port names this machine's loopback (127.0.0.0/8, ::1, localhost): nobody else can connect.
bool isLoopbackAddress(const std::string& host_port);

// Where redirected agents and forwarded reads reach this replica: cluster.advertise, or `listen` when it names a
// host and a port; empty when neither does.
std::string clusterAddress(const ServerOptions& o);

struct ServerOptions {
  std::string listen = "127.0.0.1:50051";  // host:port; port 0 picks a free one
  std::filesystem::path output;            // written at shutdown when set
  std::size_t max_message_bytes = 16U << 20U;
  std::size_t memory_quota_mb = 4096;  // what gRPC's buffers may hold in all (grpc::ResourceQuota)
  int keepalive_time_ms = 2000;        // pings on idle streams, to notice a vanished agent
  int keepalive_timeout_ms = 5000;
  double timeline_interval_s = 1.0;  // keyframes and traffic per agent, sampled for timeline.csv
  SessionOptions session;
  // Started by startWorkers(); the vocabulary defaults to the one the project ships.
  recognition::RecognitionWorkerOptions recognition = defaultRecognitionOptions();
  // Map fusion, loop closure, global BA and redundancy removal (started with place recognition, which feeds it).
  backend::BackendOptions backend;
  bool final_gba = true;  // writeOutputs() runs a last GBA on every map first (the end of a mission)
  // The map store (map_store.hpp): a SQLite file that makes every Hello and batch durable before it is
  // acknowledged, and that openStore() replays at start. Empty: maps live in memory only.
  std::filesystem::path store;
  SqliteStoreOptions::Sync store_sync = SqliteStoreOptions::Sync::kFull;
  // Access (server_cloud/access): the missions' tokens (empty: every mission open to every client), and the
  // requests per second per client (map service and monitor calls, agent streams opened).
  std::filesystem::path tokens_file;
  RateLimitOptions rate_limit;
  StreamLimitOptions stream_limits;  // agent streams open at once, per address and in all
  // Map reads that hold a snapshot or an export until the client has read it (GetMap, ExportMap, and their relays
  // in scale-out): open at once per address and in all, and how long one may take.
  StreamLimitOptions map_read_limits{8, 64, "limits.max_map_reads_per_address", "limits.max_map_reads"};
  double map_read_timeout_s = 300.0;
  // TLS on the port (agent link, map service, monitor, health): PEM files; both empty: plaintext.
  std::filesystem::path tls_certificate;
  std::filesystem::path tls_private_key;
  // A second, plaintext port that serves grpc.health.v1 and nothing else (host:port; empty: none), for
  // probes that cannot speak TLS (Kubernetes' gRPC probes). The services stay behind TLS on `listen`.
  std::string health_listen;
  // A `listen` address other machines can reach needs TLS and tokens; true lets the server start without them
  // (a network the operator trusts), and it says so.
  bool insecure = false;
  ClusterOptions cluster;

  [[nodiscard]] Status validate() const;
  [[nodiscard]] std::string describe() const;  // every option with its value, one per line
};

// Reads a YAML config (see deploy/server_config.yaml) over `options`; names unknown keys and values of the wrong
// type. Checking the options as a whole (ServerOptions::validate) is the caller's, after the command line: a
// replica's config may leave cluster.advertise to --advertise, for one.
Status loadServerConfig(const std::filesystem::path& file, ServerOptions& options);

// One sample of the timeline: what the server held of an agent, and its traffic so far.
struct TimelineSample {
  double t_s = 0.0;  // since the server started
  std::string mission;
  AgentId agent = 0;
  bool connected = false;
  std::uint64_t keyframes = 0;         // the agent's keyframes the server received (less those the agent removed)
  std::uint64_t server_keyframes = 0;  // of those, the ones the server holds (less those it found redundant)
  std::uint64_t points = 0;
  std::uint64_t up_bytes = 0;
  std::uint64_t down_bytes = 0;
};

// What openStore() found and replayed.
struct RecoveryReport {
  std::string store;  // the store's description
  std::uint64_t hellos = 0;
  std::uint64_t batches = 0;
  std::uint64_t keyframes = 0;
  std::uint64_t bytes = 0;
  std::size_t missions = 0;
  std::size_t agents = 0;
  double seconds = 0.0;
};

// What loadMission() copied.
struct LoadReport {
  std::string source;         // the store it came from
  std::string from;           // the mission there
  std::string as;             // the mission here
  bool already_held = false;  // `as` was here already (a restart replayed it): nothing was copied
  std::uint64_t hellos = 0;
  std::uint64_t batches = 0;
  std::uint64_t keyframes = 0;
  double seconds = 0.0;
};

class ServerCore {
 public:
  using Clock = std::chrono::steady_clock;
  // Timeline samples kept (about 80 bytes each): 24 h of 10 agents at 1 Hz fit.
  static constexpr std::size_t kMaxTimelineSamples = 1U << 20U;

  explicit ServerCore(const ServerOptions& options);
  ~ServerCore();

  // Loads the vocabulary and starts place recognition for every keyframe stored from now on (when
  // options.recognition.enabled), and the back-end that acts on its matches and removes redundant keyframes (when
  // options.backend.enabled). The error names the vocabulary file and the problem.
  Status startWorkers();
  // The workers, or nullptr when they are not running.
  [[nodiscard]] recognition::RecognitionWorker* recognition() const { return recognition_.get(); }
  [[nodiscard]] backend::BackendWorker* backend() const { return backend_.get(); }

  // Opens options.store (nothing to do when it is empty) and replays it into the missions, so that the server
  // holds everything it acknowledged before it stopped; from then on every session writes to it. Call after
  // startWorkers() (place recognition and the back-end see the replayed keyframes) and before serving. The error
  // names the file and the record that is wrong.
  Result<RecoveryReport> openStore();
  // The same with a store made elsewhere (tests; replicas sharing one PostgreSQL store).
  Result<RecoveryReport> attachStore(std::unique_ptr<MapStore> store);
  [[nodiscard]] MapStore* store() const { return store_.get(); }
  // Scale-out: joins the replicas of options.cluster (openStore() does it when options.cluster is enabled). The
  // store is shared and nothing is replayed now: each mission is loaded from it when this replica takes it (an
  // agent's Hello, or a takeover after another replica's lease lapsed). Starts renewing and taking over.
  // `renewals` is a second connection, used only to renew the leases.
  Result<RecoveryReport> joinCluster(std::unique_ptr<MapStore> store, std::unique_ptr<cluster::MissionLeases> leases,
                                     std::unique_ptr<cluster::MissionLeases> renewals);
  // Gives every mission back at once (a clean shutdown; call after writeOutputs()). Nothing to do when alone.
  Status leaveCluster();
  // Who serves which mission; nullptr when this server runs alone (it serves every mission).
  [[nodiscard]] MissionOwnership* ownership() const;
  [[nodiscard]] cluster::ReplicaCoordinator* replica() const { return replica_.get(); }

  // Map reuse: copies mission `from` of `source` (this server's own store when nullptr) into this server as the
  // new mission `as`. Its records, renamed, go into this server's store (when it has one) and are applied as a
  // replay applies them, so the map service serves the map at once and place recognition and the back-end rebuild
  // what they derive; an agent that flies `as` later is matched against it. The loaded agents keep their ids (and
  // their keyframes' ids), so the agents of `as` take other ids. When `as` is here already (a restarted server
  // replayed it from its store) nothing is copied. Call after openStore() and before serving. Errors name the
  // store and the mission (NOT_FOUND lists the missions the store holds). On a scale-out replica the copy goes
  // into the shared store while this replica holds the mission's lease, and this replica serves it; when another
  // replica serves `as` already, nothing is copied.
  Result<LoadReport> loadMission(const MapStore* source, const std::string& from, const std::string& as);

  // Scale-out: the mission is no longer this replica's (its lease went to another). Its agent streams and watches
  // end, what still comes on them is refused, and memory forgets it, so that a later take loads it afresh.
  void dropMission(const std::string& mission);

  [[nodiscard]] const ServerOptions& options() const { return options_; }
  [[nodiscard]] MissionRegistry& missions() { return missions_; }
  [[nodiscard]] const MissionRegistry& missions() const { return missions_; }

  // Reads options.tokens_file (nothing to do when it is empty): from then on every mission needs its token. The
  // error names the file and line.
  Status loadTokens();
  void setTokens(MissionTokens tokens) { tokens_ = std::move(tokens); }  // tests
  [[nodiscard]] const MissionTokens& tokens() const { return tokens_; }
  // One request of `client` (its address and token; the adapters make the key) against options.rate_limit:
  // RESOURCE_EXHAUSTED naming `what` and the limit when the client is over it.
  Status admitRequest(const std::string& client, const std::string& what) { return limiter_.admit(client, what); }
  [[nodiscard]] const RateLimiter& rateLimiter() const { return limiter_; }
  // A new agent stream from `address` (the peer without its port): its slot, or RESOURCE_EXHAUSTED.
  Result<StreamLimits::Slot> openStreamSlot(const std::string& address) { return streams_.open(address); }
  [[nodiscard]] const StreamLimits& streamLimits() const { return streams_; }
  // The same for a map read (GetMap, ExportMap) from `address`.
  Result<StreamLimits::Slot> openMapReadSlot(const std::string& address) { return map_reads_.open(address); }
  [[nodiscard]] const StreamLimits& mapReadLimits() const { return map_reads_; }
  // Every batch's ingest and store-commit time since start (the metrics endpoint's histograms).
  [[nodiscard]] const IngestMetrics& ingestMetrics() const { return ingest_metrics_; }
  [[nodiscard]] double uptimeSeconds() const;

  // A session for a new agent stream (see AgentSession for `cancel_stream`); `token` is what the stream
  // presented, checked against the tokens when its Hello names the mission.
  std::unique_ptr<AgentSession> openSession(std::function<void()> cancel_stream, std::string token = {});

  // Statistics of one mission, or of every mission when `mission` is empty; `visible`, when set, leaves out the
  // missions it says no to (those a caller's token does not open).
  void fillStats(const std::string& mission, v1::ServerStats& out,
                 const std::function<bool(const std::string&)>& visible = {}) const;

  // Records one timeline sample per agent (the service calls it every timeline_interval_s).
  void sampleTimeline();

  // Lets the workers catch up (recognition queries every waiting keyframe, the back-end acts on every match and,
  // with options.final_gba, runs a last GBA on every map), then writes, under `dir`: stats.json, timeline.csv and,
  // per mission, <mission>/recognition.json (when recognition runs: its counters and every verified loop and map
  // match), <mission>/backend.json (when the back-end runs: merges, loops, GBA runs, removals),
  // <mission>/keyframes_agent<N>.txt (TUM, the agent's keyframes in its server map's frame, all maps) and, for an agent
  // with several maps, <mission>/keyframes_agent<N>_map<M>.txt per map.
  Status writeOutputs(const std::filesystem::path& dir) const;
  // The catching-up part of writeOutputs().
  void drainWorkers(bool final_gba) const;

 private:
  ServerOptions options_;
  Clock::time_point start_;
  MissionRegistry missions_;
  Synchronized<std::vector<TimelineSample>> timeline_;
  std::unique_ptr<recognition::RecognitionWorker> recognition_;
  std::unique_ptr<backend::BackendWorker> backend_;  // after recognition_: it goes first
  std::unique_ptr<MapStore> store_;
  MissionTokens tokens_;
  RateLimiter limiter_;
  IngestMetrics ingest_metrics_;
  StreamLimits streams_;
  StreamLimits map_reads_;
  std::unique_ptr<cluster::ReplicaCoordinator> replica_;  // scale-out only; after store_: it goes first

  // Replays what store_ holds of `mission` (this replica has just taken its lease).
  Status loadFromStore(const std::string& mission);
  // loadMission's steps: a record of the source renamed into mission report.as; and, on a replica, the copy and
  // the load under the mission's lease.
  static Status renameLoaded(StoreRecord& r, const LoadReport& report);
  Status writeIngestSamples(const std::filesystem::path& file) const;
  Result<LoadReport> loadOnReplica(std::vector<StoreRecord>& records, std::size_t held, LoadReport report,
                                   Clock::time_point start);

  [[nodiscard]] AgentSession::StoredListener storedListener() const;
};

}  // namespace cvislam::server
