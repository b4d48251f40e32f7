#include "server_cloud/cluster/postgres_store.hpp"

#include <mutex>
#include <utility>

#include "server_cloud/cluster/pg_connection.hpp"

namespace cvislam::server::cluster {

namespace {

constexpr const char* kFormat = "cvislam map store";
// Any constant: serialises the replicas' schema set-up.
constexpr const char* kSchemaLock = "SELECT pg_advisory_xact_lock(7340021)";

class PostgresStore final : public MapStore {
 public:
  PostgresStore(std::unique_ptr<PgConnection> connection, PostgresStoreOptions options, StoreCounters counters)
      : connection_(std::move(connection)), options_(std::move(options)), counters_(counters) {}

  Status append(const StoreRecord& r) override {
    std::lock_guard lock(mutex_);
    auto result = execAppend(*connection_, r, options_.holder);
    if (!result) {
      if (result.error().code() == ErrorCode::kAlreadyExists) {
        return Error{ErrorCode::kAlreadyExists, "the store holds batch " + std::to_string(r.sequence) + " of agent " +
                                                    std::to_string(r.agent) + " of mission '" + r.mission +
                                                    "' already"};
      }
      return result.error();
    }
    if (result->affected() != 1) {
      return Error{ErrorCode::kFailedPrecondition,
                   "replica " + options_.holder + " does not hold the lease of mission '" + r.mission +
                       "' any more (it lapsed, or another replica took the mission over): nothing was stored"};
    }
    ++counters_.records;
    counters_.bytes += r.body.size();
    return Status::Ok();
  }

  Status replay(const std::string& mission, const std::function<Status(const StoreRecord&)>& visit) const override {
    // In pages, so that a long mission is never held in memory twice.
    constexpr std::int64_t kPage = 256;
    std::int64_t after = 0;
    StoreRecord r;
    for (;;) {
      PgParams params;
      params.i64(after).i64(kPage);
      std::string sql = "SELECT number, kind, mission, agent, sequence, body, checksum FROM cvislam_records WHERE ";
      if (!mission.empty()) {
        params.text(mission);
        sql += "mission = $3 AND ";
      }
      sql += "number > $1 ORDER BY number LIMIT $2";
      std::unique_lock lock(mutex_);
      auto rows = connection_->exec(sql, params);
      lock.unlock();
      if (!rows) return rows.error().withContext("reading the records");
      for (int i = 0; i < rows->rows(); ++i) {
        if (Status s = readRow(*rows, i, r); !s.ok()) return s;
        if (Status s = visit(r); !s.ok()) return s;
        after = static_cast<std::int64_t>(r.number);
      }
      if (rows->rows() < kPage) return Status::Ok();
    }
  }

  [[nodiscard]] Result<std::optional<StoreRecord>> findBatch(const std::string& mission, AgentId agent,
                                                             std::uint64_t sequence) const override {
    PgParams params;
    params.text(mission).i32(static_cast<std::int32_t>(agent)).i64(static_cast<std::int64_t>(sequence));
    std::unique_lock lock(mutex_);
    auto rows = connection_->exec(
        "SELECT number, kind, mission, agent, sequence, body, checksum FROM cvislam_records "
        "WHERE kind = 2 AND mission = $1 AND agent = $2 AND sequence = $3",
        params);
    lock.unlock();
    if (!rows) return rows.error().withContext("looking up a batch");
    if (rows->rows() == 0) return std::optional<StoreRecord>();
    StoreRecord r;
    if (Status s = readRow(*rows, 0, r); !s.ok()) return s.error();
    return std::optional<StoreRecord>(std::move(r));
  }

  [[nodiscard]] Result<std::vector<std::string>> missions() const override {
    std::lock_guard lock(mutex_);
    auto rows = connection_->exec("SELECT DISTINCT mission FROM cvislam_records ORDER BY mission");
    if (!rows) return rows.error();
    std::vector<std::string> out;
    for (int i = 0; i < rows->rows(); ++i) out.emplace_back(rows->bytes(i, 0));
    return out;
  }

  [[nodiscard]] StoreCounters counters() const override {
    std::lock_guard lock(mutex_);
    return counters_;
  }

  [[nodiscard]] std::string describe() const override {
    return connection_->describe() + (options_.holder.empty()
                                          ? std::string(" (no fencing)")
                                          : " (appends fenced by the leases of " + options_.holder + ")");
  }

 private:
  // Row `i` of "SELECT number, kind, mission, agent, sequence, body, checksum", checked.
  Status readRow(const PgResult& rows, int i, StoreRecord& r) const {
    r.number = static_cast<std::uint64_t>(rows.i64(i, 0));
    r.mission.assign(rows.bytes(i, 2));
    r.sequence = static_cast<std::uint64_t>(rows.i64(i, 4));
    r.body.assign(rows.bytes(i, 5));
    const std::string where = connection_->describe() + ": record " + std::to_string(r.number);
    return checkStoredRecord(rows.i16(i, 1), rows.i32(i, 3), static_cast<std::uint64_t>(rows.i64(i, 6)), where, r);
  }

  std::unique_ptr<PgConnection> connection_;
  PostgresStoreOptions options_;
  mutable std::mutex mutex_;  // one connection: one statement at a time
  StoreCounters counters_;    // what this process appended
};

}  // namespace

Result<PgResult> execAppend(PgConnection& connection, const StoreRecord& r, const std::string& holder) {
  PgParams params;
  params.i16(static_cast<std::int16_t>(r.kind))
      .text(r.mission)
      .i32(static_cast<std::int32_t>(r.agent))
      .i64(static_cast<std::int64_t>(r.sequence))
      .bytes(r.body)
      .i64(static_cast<std::int64_t>(recordChecksum(r.kind, r.mission, r.agent, r.sequence, r.body)));
  std::string sql =
      "INSERT INTO cvislam_records (kind, mission, agent, sequence, body, checksum) "
      "SELECT $1, $2, $3, $4, $5, $6";
  if (!holder.empty()) {
    params.text(holder);
    // FOR SHARE: a concurrent takeover's update of the row waits for this statement's transaction; one that
    // committed first is seen here (READ COMMITTED re-reads a locked row) and the holder no longer matches.
    sql +=
        " FROM (SELECT 1 FROM cvislam_leases WHERE mission = $2 AND holder = $7 AND expires_at > now() FOR SHARE) "
        "AS fence";
  }
  return connection.exec(sql, params);
}

Status PostgresStoreOptions::validate() const {
  if (conninfo.empty())
    return Error{ErrorCode::kInvalidArgument, "the shared store needs a PostgreSQL connection string"};
  return Status::Ok();
}

Status ensureClusterSchema(PgConnection& connection, const std::string& software) {
  const std::string create =
      std::string("BEGIN;") + kSchemaLock +
      ";"
      "CREATE TABLE IF NOT EXISTS cvislam_meta (key text PRIMARY KEY, value text NOT NULL);"
      "CREATE TABLE IF NOT EXISTS cvislam_records (number bigserial PRIMARY KEY, "
      "  kind smallint NOT NULL, mission text NOT NULL, agent integer NOT NULL, "
      "  sequence bigint NOT NULL, body bytea NOT NULL, checksum bigint NOT NULL);"
      "CREATE UNIQUE INDEX IF NOT EXISTS cvislam_records_batch "
      "  ON cvislam_records (mission, agent, sequence) WHERE kind = 2;"
      "CREATE INDEX IF NOT EXISTS cvislam_records_mission ON cvislam_records (mission, number);"
      "CREATE TABLE IF NOT EXISTS cvislam_leases (mission text PRIMARY KEY, holder text NOT NULL, "
      "  address text NOT NULL, epoch bigint NOT NULL, expires_at timestamptz NOT NULL);"
      "CREATE TABLE IF NOT EXISTS cvislam_replicas (holder text PRIMARY KEY, address text NOT NULL, "
      "  expires_at timestamptz NOT NULL);"
      "INSERT INTO cvislam_meta VALUES ('format', '" +
      kFormat + "'), ('schema', '" + std::to_string(kClusterSchemaVersion) +
      "') ON CONFLICT (key) DO NOTHING;"
      "COMMIT;";
  if (Status s = connection.execScript(create); !s.ok()) {
    (void)connection.execScript("ROLLBACK");
    return s.error().withContext("making the tables");
  }
  if (auto by = connection.exec("INSERT INTO cvislam_meta VALUES ('created_by', $1) ON CONFLICT (key) DO NOTHING",
                                PgParams().text(software));
      !by) {
    return by.error();
  }
  auto meta = connection.exec("SELECT key, value FROM cvislam_meta WHERE key IN ('format', 'schema') ORDER BY key");
  if (!meta) return meta.error();
  std::string format;
  std::string schema;
  for (int i = 0; i < meta->rows(); ++i) {
    (meta->bytes(i, 0) == "format" ? format : schema) = std::string(meta->bytes(i, 1));
  }
  if (format != kFormat) {
    return Error{ErrorCode::kDataError, connection.describe() +
                                            " holds a cvislam_meta table that is not a cvislam "
                                            "map store's (format '" +
                                            format + "'): give another database"};
  }
  if (schema != std::to_string(kClusterSchemaVersion)) {
    return Error{ErrorCode::kFailedPrecondition,
                 connection.describe() + " has map store schema version " + schema + "; this server reads version " +
                     std::to_string(kClusterSchemaVersion) + ": run the replicas of the version that wrote it"};
  }
  return Status::Ok();
}

Result<std::unique_ptr<MapStore>> openPostgresStore(const PostgresStoreOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto connection = PgConnection::open(options.conninfo, "map store", options.timeouts);
  if (!connection) return connection.error();
  if (Status s = ensureClusterSchema(**connection, options.software); !s.ok()) return s.error();
  return std::unique_ptr<MapStore>(
      std::make_unique<PostgresStore>(std::move(connection).value(), options, StoreCounters{}));
}

}  // namespace cvislam::server::cluster
