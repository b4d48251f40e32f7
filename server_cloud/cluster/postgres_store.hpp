// The map store that server replicas share: the log of map_store.hpp in PostgreSQL.
//
// Tables (made by the first replica that connects, under an advisory lock, so that replicas may start together):
//   cvislam_meta     format and schema version;
//   cvislam_records  one row per StoreRecord, numbered by a sequence, with its checksum (map_store.hpp);
//   cvislam_leases   which replica serves which mission, until when (mission_leases.hpp).
//
// Fencing: with `holder` set, a record is appended only while that replica holds its mission's lease, checked in
// the same statement as the insert, under a share lock of the lease row (see execAppend). A replica whose lease lapsed
// (it stalled, or lost the database for longer than the lease) and was taken over can therefore never write into the
// mission behind the new owner's back: its append fails with kFailedPrecondition and its agents reconnect to the owner.
#pragma once

#include <memory>
#include <string>

#include "common/core/result.hpp"
#include "server_cloud/cluster/pg_connection.hpp"
#include "server_cloud/store/map_store.hpp"

namespace cvislam::server::cluster {

class PgConnection;

struct PostgresStoreOptions {
  std::string conninfo;  // libpq connection string
  std::string holder;    // the lease holder whose leases fence the appends; empty: no fencing (one server)
  std::string software = "cvislam_server";
  PgTimeouts timeouts;

  [[nodiscard]] Status validate() const;
};

// The schema version this build writes and reads.
inline constexpr int kClusterSchemaVersion = 1;

// The fenced append of one record on `connection` (what PostgresStore::append runs; tests run it inside a
// transaction they hold open). The insert takes a share lock on the lease row it checks, so a takeover, which
// updates that row, waits for the append to commit or roll back: the new owner's replay then sees every append
// the old owner made, and an append that starts after the takeover finds the lease gone and inserts nothing.
// `holder` empty: no fencing.
Result<PgResult> execAppend(PgConnection& connection, const StoreRecord& record, const std::string& holder);

// Makes the tables when they are missing and checks the format and schema version of those there.
Status ensureClusterSchema(PgConnection& connection, const std::string& software);

Result<std::unique_ptr<MapStore>> openPostgresStore(const PostgresStoreOptions& options);

}  // namespace cvislam::server::cluster
