#include "server_cloud/cluster/mission_leases.hpp"

#include "server_cloud/cluster/pg_connection.hpp"
#include "server_cloud/cluster/postgres_store.hpp"

namespace cvislam::server::cluster {

namespace {
constexpr const char* kLeaseColumns = "mission, holder, address, epoch, extract(epoch FROM expires_at - now())::float8";

Lease leaseOf(const PgResult& rows, int i) {
  Lease lease;
  lease.mission = std::string(rows.bytes(i, 0));
  lease.holder = std::string(rows.bytes(i, 1));
  lease.address = std::string(rows.bytes(i, 2));
  lease.epoch = rows.i64(i, 3);
  lease.remaining_s = rows.f64(i, 4);
  return lease;
}
}  // namespace

Status LeaseOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "cluster: " + what}; };
  if (conninfo.empty()) return bad("no PostgreSQL connection string given");
  if (holder.empty()) return bad("the lease holder's name is empty");
  if (address.empty() || address.find(':') == std::string::npos) {
    return bad("the replica's address '" + address + "' is not host:port (agents are redirected to it)");
  }
  if (!(ttl_s >= 1.0) || ttl_s > 600.0) return bad("lease_ttl_s must be in [1, 600], got " + std::to_string(ttl_s));
  return Status::Ok();
}

Result<std::unique_ptr<MissionLeases>> MissionLeases::open(const LeaseOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto connection = PgConnection::open(options.conninfo, "mission leases", options.timeouts);
  if (!connection) return connection.error();
  if (Status s = ensureClusterSchema(**connection, "cvislam_server"); !s.ok()) return s.error();
  return std::unique_ptr<MissionLeases>(new MissionLeases(std::move(connection).value(), options));
}

MissionLeases::MissionLeases(std::unique_ptr<PgConnection> connection, LeaseOptions options)
    : connection_(std::move(connection)), options_(std::move(options)) {}
MissionLeases::~MissionLeases() = default;

Result<Lease> MissionLeases::acquire(const std::string& mission) {
  auto taken = connection_->exec(
      std::string("INSERT INTO cvislam_leases AS l (mission, holder, address, epoch, expires_at) "
                  "VALUES ($1, $2, $3, 1, now() + make_interval(secs => $4)) "
                  "ON CONFLICT (mission) DO UPDATE SET holder = EXCLUDED.holder, address = EXCLUDED.address, "
                  "  epoch = l.epoch + CASE WHEN l.holder = EXCLUDED.holder THEN 0 ELSE 1 END, "
                  "  expires_at = EXCLUDED.expires_at "
                  "  WHERE l.holder = EXCLUDED.holder OR l.expires_at <= now() "
                  "RETURNING ") +
          kLeaseColumns,
      PgParams().text(mission).text(options_.holder).text(options_.address).f64(options_.ttl_s));
  if (!taken) return taken.error().withContext("taking the lease of mission '" + mission + "'");
  if (taken->rows() == 1) return leaseOf(*taken, 0);
  // Another holder's live lease.
  auto held = find(mission);
  if (!held) return held.error();
  if (!*held) {
    return Error{ErrorCode::kUnavailable, "the lease of mission '" + mission + "' changed while it was taken: retry"};
  }
  return **held;
}

Result<std::vector<std::string>> MissionLeases::renew() {
  auto renewed = connection_->exec(
      "UPDATE cvislam_leases SET expires_at = now() + make_interval(secs => $2) WHERE holder = $1 "
      "RETURNING mission",
      PgParams().text(options_.holder).f64(options_.ttl_s));
  if (!renewed) return renewed.error().withContext("renewing the leases of " + options_.holder);
  std::vector<std::string> out;
  for (int i = 0; i < renewed->rows(); ++i) out.emplace_back(renewed->bytes(i, 0));
  return out;
}

Status MissionLeases::release(const std::string& mission) {
  auto released = connection_->exec(
      "UPDATE cvislam_leases SET expires_at = 'epoch'::timestamptz WHERE mission = $1 AND holder = $2",
      PgParams().text(mission).text(options_.holder));
  if (!released) return released.error().withContext("releasing the lease of mission '" + mission + "'");
  return Status::Ok();
}

Result<std::vector<std::string>> MissionLeases::lapsed() {
  auto rows = connection_->exec("SELECT mission FROM cvislam_leases WHERE expires_at <= now() ORDER BY mission");
  if (!rows) return rows.error().withContext("listing lapsed leases");
  std::vector<std::string> out;
  for (int i = 0; i < rows->rows(); ++i) out.emplace_back(rows->bytes(i, 0));
  return out;
}

Result<std::optional<Lease>> MissionLeases::find(const std::string& mission) {
  auto rows = connection_->exec(std::string("SELECT ") + kLeaseColumns + " FROM cvislam_leases WHERE mission = $1",
                                PgParams().text(mission));
  if (!rows) return rows.error().withContext("reading the lease of mission '" + mission + "'");
  if (rows->rows() == 0) return std::optional<Lease>();
  return std::optional<Lease>(leaseOf(*rows, 0));
}

Result<std::vector<Lease>> MissionLeases::otherHolders() {
  auto rows = connection_->exec(std::string("SELECT DISTINCT ON (holder) ") + kLeaseColumns +
                                    " FROM cvislam_leases WHERE expires_at > now() AND holder <> $1 ORDER BY holder",
                                PgParams().text(options_.holder));
  if (!rows) return rows.error().withContext("listing the other replicas");
  std::vector<Lease> out;
  for (int i = 0; i < rows->rows(); ++i) out.push_back(leaseOf(*rows, i));
  return out;
}

Status MissionLeases::heartbeat() {
  auto beat = connection_->exec(
      "INSERT INTO cvislam_replicas AS r (holder, address, expires_at) "
      "VALUES ($1, $2, now() + make_interval(secs => $3)) "
      "ON CONFLICT (holder) DO UPDATE SET address = EXCLUDED.address, expires_at = EXCLUDED.expires_at",
      PgParams().text(options_.holder).text(options_.address).f64(options_.ttl_s));
  if (!beat) return beat.error().withContext("writing the heartbeat of " + options_.holder);
  return Status::Ok();
}

Status MissionLeases::leave() {
  auto gone = connection_->exec("DELETE FROM cvislam_replicas WHERE holder = $1", PgParams().text(options_.holder));
  if (!gone) return gone.error().withContext("removing the heartbeat of " + options_.holder);
  return Status::Ok();
}

Result<std::vector<ReplicaLoad>> MissionLeases::liveReplicas() {
  // A released lease (expires_at at the epoch) does not make its holder dead: a replica may give one mission back.
  auto rows = connection_->exec(
      "SELECT r.holder, r.address, "
      "  (SELECT count(*) FROM cvislam_leases l WHERE l.holder = r.holder AND l.expires_at > now()) "
      "FROM cvislam_replicas r WHERE r.expires_at > now() AND NOT EXISTS ("
      "  SELECT 1 FROM cvislam_leases l WHERE l.holder = r.holder AND l.expires_at <= now() "
      "    AND l.expires_at > 'epoch'::timestamptz) "
      "ORDER BY r.holder");
  if (!rows) return rows.error().withContext("listing the live replicas");
  std::vector<ReplicaLoad> out;
  for (int i = 0; i < rows->rows(); ++i) {
    out.push_back(
        ReplicaLoad{std::string(rows->bytes(i, 0)), std::string(rows->bytes(i, 1)), static_cast<int>(rows->i64(i, 2))});
  }
  return out;
}

}  // namespace cvislam::server::cluster
