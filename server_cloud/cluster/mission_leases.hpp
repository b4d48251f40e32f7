// Which replica serves which mission: a lease per mission in PostgreSQL (table cvislam_leases), renewed by its
// holder and taken over by another replica once it lapses.
//
// Time is the database's (now()), so replicas' clocks never have to agree. A holder is one server process
// ("<replica name>/<random number>"): a replica that restarts under the same name is a new holder and waits for
// its old leases to lapse like any other replica (or finds them released, after a clean shutdown). Every takeover
// raises the lease's epoch.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "server_cloud/cluster/pg_connection.hpp"

namespace cvislam::server::cluster {

struct LeaseOptions {
  std::string conninfo;  // libpq connection string
  std::string holder;    // this process; see above
  std::string address;   // host:port where agents and clients reach this replica (what a redirect names)
  double ttl_s = 3.0;    // a lease not renewed for this long lapses
  PgTimeouts timeouts;

  [[nodiscard]] Status validate() const;
};

// A live replica, as its heartbeat row says, and how many missions' live leases it holds.
struct ReplicaLoad {
  std::string holder;
  std::string address;
  int missions = 0;
};

struct Lease {
  std::string mission;
  std::string holder;
  std::string address;
  std::int64_t epoch = 0;
  double remaining_s = 0.0;  // until it lapses; <= 0: lapsed
};

class MissionLeases {
 public:
  static Result<std::unique_ptr<MissionLeases>> open(const LeaseOptions& options);
  ~MissionLeases();
  MissionLeases(const MissionLeases&) = delete;
  MissionLeases& operator=(const MissionLeases&) = delete;

  // Takes the lease of `mission` when it is free (new, lapsed or released) or ours already, and returns it; when
  // another holder's lease is live, returns that one (its holder and address) instead.
  Result<Lease> acquire(const std::string& mission);
  // Extends every lease this holder has; returns the missions it still holds (one taken over is missing).
  Result<std::vector<std::string>> renew();
  // Lets `mission` go at once (a clean shutdown): another replica may take it at its next look.
  Status release(const std::string& mission);
  // The missions whose leases lapsed or were released, by name.
  Result<std::vector<std::string>> lapsed();
  // The lease of `mission`, or nothing when it never had one.
  Result<std::optional<Lease>> find(const std::string& mission);
  // The other holders with a live lease, each once (holder and address; the mission is that of one of them).
  Result<std::vector<Lease>> otherHolders();

  // Says that this holder is alive for one more TTL (table cvislam_replicas), so that the others count it when they
  // share out lapsed missions even while it serves none. Called before the leases are renewed, so that a dead
  // holder's heartbeat lapses before its leases do.
  Status heartbeat();
  // Removes this holder's heartbeat (a clean shutdown).
  Status leave();
  // The replicas with a live heartbeat and no lapsed lease (a holder whose lease lapsed is dead or stalled), by
  // holder name, each with the number of live leases it holds.
  Result<std::vector<ReplicaLoad>> liveReplicas();

  [[nodiscard]] const LeaseOptions& options() const { return options_; }

 private:
  MissionLeases(std::unique_ptr<PgConnection> connection, LeaseOptions options);
  std::unique_ptr<PgConnection> connection_;
  LeaseOptions options_;
};

}  // namespace cvislam::server::cluster
