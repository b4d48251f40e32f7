#include "server_cloud/store/sqlite_store.hpp"

#include <sqlite3.h>

#include <cstdio>
#include <mutex>
#include <optional>
#include <string_view>
#include <utility>
#include <vector>

namespace cvislam::server {

Status SqliteStoreOptions::validate() const {
  if (path.empty()) return Error{ErrorCode::kInvalidArgument, "store path is empty"};
  return Status::Ok();
}

Result<SqliteStoreOptions::Sync> parseStoreSync(const std::string& name) {
  if (name == "full") return SqliteStoreOptions::Sync::kFull;
  if (name == "normal") return SqliteStoreOptions::Sync::kNormal;
  if (name == "off") return SqliteStoreOptions::Sync::kOff;
  return Error{ErrorCode::kInvalidArgument, "store sync '" + name + "' is not one of full, normal, off"};
}

std::string_view toString(SqliteStoreOptions::Sync sync) {
  switch (sync) {
    case SqliteStoreOptions::Sync::kFull:
      return "full";
    case SqliteStoreOptions::Sync::kNormal:
      return "normal";
    case SqliteStoreOptions::Sync::kOff:
      return "off";
  }
  return "unknown";
}

namespace {

constexpr const char* kFormat = "cvislam map store";

struct DbCloser {
  void operator()(sqlite3* db) const { sqlite3_close_v2(db); }
};
struct StmtFinalizer {
  void operator()(sqlite3_stmt* s) const { sqlite3_finalize(s); }
};
using Db = std::unique_ptr<sqlite3, DbCloser>;
using Stmt = std::unique_ptr<sqlite3_stmt, StmtFinalizer>;

class SqliteStore final : public MapStore {
 public:
  SqliteStore(Db db, SqliteStoreOptions options, StoreCounters counters)
      : db_(std::move(db)), options_(std::move(options)), counters_(counters) {}

  Status prepare() {
    auto insert =
        compile("INSERT INTO records (kind, mission, agent, sequence, body, checksum) VALUES (?1, ?2, ?3, ?4, ?5, ?6)");
    if (!insert) return insert.error();
    insert_ = std::move(insert).value();
    return Status::Ok();
  }

  Status append(const StoreRecord& r) override {
    std::lock_guard lock(mutex_);
    sqlite3_stmt* s = insert_.get();
    sqlite3_reset(s);
    sqlite3_clear_bindings(s);
    sqlite3_bind_int(s, 1, static_cast<int>(r.kind));
    sqlite3_bind_text(s, 2, r.mission.data(), static_cast<int>(r.mission.size()), SQLITE_STATIC);
    sqlite3_bind_int64(s, 3, static_cast<sqlite3_int64>(r.agent));
    sqlite3_bind_int64(s, 4, static_cast<sqlite3_int64>(r.sequence));
    sqlite3_bind_blob64(s, 5, r.body.data(), r.body.size(), SQLITE_STATIC);
    sqlite3_bind_int64(s, 6,
                       static_cast<sqlite3_int64>(recordChecksum(r.kind, r.mission, r.agent, r.sequence, r.body)));
    const int rc = sqlite3_step(s);
    sqlite3_reset(s);
    if (rc == SQLITE_CONSTRAINT) {
      return Error{ErrorCode::kAlreadyExists, "the store holds batch " + std::to_string(r.sequence) + " of agent " +
                                                  std::to_string(r.agent) + " of mission '" + r.mission + "' already"};
    }
    if (rc != SQLITE_DONE) return sqliteError("appending a " + std::string(toString(r.kind)) + " record");
    ++counters_.records;
    counters_.bytes += r.body.size();
    return Status::Ok();
  }

  Status replay(const std::string& mission, const std::function<Status(const StoreRecord&)>& visit) const override {
    // In pages, the lock released while the records are visited: visiting applies them to a mission and takes its
    // agents' locks, and a session holds its agent's lock while it appends. A replay that held the store across
    // its visits would order those two locks the other way round, and would stall every other mission's appends
    // for as long as a long mission takes to load.
    constexpr int kPage = 256;
    std::int64_t after = 0;
    std::vector<StoreRecord> page;
    for (;;) {
      page.clear();
      Status failed = Status::Ok();
      {
        std::lock_guard lock(mutex_);
        auto select = compile(mission.empty()
                                  ? "SELECT number, kind, mission, agent, sequence, body, checksum FROM records WHERE "
                                    "number > ?1 ORDER BY number LIMIT ?2"
                                  : "SELECT number, kind, mission, agent, sequence, body, checksum FROM records WHERE "
                                    "number > ?1 AND mission = ?3 ORDER BY number LIMIT ?2");
        if (!select) return select.error();
        sqlite3_stmt* s = select->get();
        sqlite3_bind_int64(s, 1, after);
        sqlite3_bind_int(s, 2, kPage);
        if (!mission.empty()) sqlite3_bind_text(s, 3, mission.data(), static_cast<int>(mission.size()), SQLITE_STATIC);
        for (;;) {
          const int rc = sqlite3_step(s);
          if (rc == SQLITE_DONE) break;
          if (rc != SQLITE_ROW) {
            failed = sqliteError("reading the records");
            break;
          }
          StoreRecord& r = page.emplace_back();
          if (failed = readRow(s, r); !failed.ok()) {
            page.pop_back();
            break;
          }
        }
      }
      // The records before a bad one are visited first, as a replay that read them one by one would have.
      for (const StoreRecord& r : page) {
        if (Status st = visit(r); !st.ok()) return st;
        after = static_cast<std::int64_t>(r.number);
      }
      if (!failed.ok()) return failed;
      if (page.size() < static_cast<std::size_t>(kPage)) return Status::Ok();
    }
  }

  [[nodiscard]] Result<std::optional<StoreRecord>> findBatch(const std::string& mission, AgentId agent,
                                                             std::uint64_t sequence) const override {
    std::lock_guard lock(mutex_);
    auto select = compile(
        "SELECT number, kind, mission, agent, sequence, body, checksum FROM records WHERE kind = 2 AND mission = ?1 "
        "AND agent = ?2 AND sequence = ?3");
    if (!select) return select.error();
    sqlite3_stmt* s = select->get();
    sqlite3_bind_text(s, 1, mission.data(), static_cast<int>(mission.size()), SQLITE_STATIC);
    sqlite3_bind_int64(s, 2, static_cast<sqlite3_int64>(agent));
    sqlite3_bind_int64(s, 3, static_cast<sqlite3_int64>(sequence));
    const int rc = sqlite3_step(s);
    if (rc == SQLITE_DONE) return std::optional<StoreRecord>();
    if (rc != SQLITE_ROW) return sqliteError("looking up a batch");
    StoreRecord r;
    if (Status st = readRow(s, r); !st.ok()) return st.error();
    return std::optional<StoreRecord>(std::move(r));
  }

  [[nodiscard]] Result<std::vector<std::string>> missions() const override {
    std::lock_guard lock(mutex_);
    auto select = compile("SELECT DISTINCT mission FROM records ORDER BY mission");
    if (!select) return select.error();
    std::vector<std::string> out;
    for (;;) {
      const int rc = sqlite3_step(select->get());
      if (rc == SQLITE_DONE) break;
      if (rc != SQLITE_ROW) return sqliteError("listing the missions");
      const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(select->get(), 0));
      out.emplace_back(text != nullptr ? text : "");
    }
    return out;
  }

  [[nodiscard]] StoreCounters counters() const override {
    std::lock_guard lock(mutex_);
    return counters_;
  }

  [[nodiscard]] std::string describe() const override {
    return "sqlite " + options_.path.string() + " (synchronous=" + std::string(toString(options_.sync)) + ")";
  }

 private:
  [[nodiscard]] Result<Stmt> compile(const char* sql) const {
    sqlite3_stmt* s = nullptr;
    if (sqlite3_prepare_v2(db_.get(), sql, -1, &s, nullptr) != SQLITE_OK) {
      sqlite3_finalize(s);
      return sqliteError("preparing a statement");
    }
    return Stmt(s);
  }
  // One row of "SELECT number, kind, mission, agent, sequence, body, checksum", checked.
  Status readRow(sqlite3_stmt* s, StoreRecord& r) const {
    r.number = static_cast<std::uint64_t>(sqlite3_column_int64(s, 0));
    const int kind = sqlite3_column_int(s, 1);
    const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(s, 2));
    r.mission.assign(text != nullptr ? text : "", static_cast<std::size_t>(sqlite3_column_bytes(s, 2)));
    const sqlite3_int64 agent = sqlite3_column_int64(s, 3);
    r.sequence = static_cast<std::uint64_t>(sqlite3_column_int64(s, 4));
    const void* body = sqlite3_column_blob(s, 5);
    r.body.assign(body != nullptr ? static_cast<const char*>(body) : "",
                  static_cast<std::size_t>(sqlite3_column_bytes(s, 5)));
    const auto stored_checksum = static_cast<std::uint64_t>(sqlite3_column_int64(s, 6));
    const std::string where = options_.path.string() + ": record " + std::to_string(r.number);
    return checkStoredRecord(kind, agent, stored_checksum, where, r);
  }
  [[nodiscard]] Error sqliteError(const std::string& what) const {
    return Error{ErrorCode::kIoError,
                 "map store " + options_.path.string() + ": " + what + ": " + sqlite3_errmsg(db_.get())};
  }

  Db db_;
  SqliteStoreOptions options_;
  mutable std::mutex mutex_;  // one connection: its statements are used by one thread at a time
  Stmt insert_;
  StoreCounters counters_;
};

Status exec(sqlite3* db, const std::string& path, const char* sql, const char* what) {
  char* message = nullptr;
  if (sqlite3_exec(db, sql, nullptr, nullptr, &message) != SQLITE_OK) {
    std::string text = message != nullptr ? message : sqlite3_errmsg(db);
    sqlite3_free(message);
    return Error{ErrorCode::kIoError, "map store " + path + ": " + what + ": " + text};
  }
  return Status::Ok();
}

// The single value of a one-row, one-column query, as text; nullopt when no row.
Result<std::optional<std::string>> queryText(sqlite3* db, const std::string& path, const char* sql) {
  sqlite3_stmt* raw = nullptr;
  if (sqlite3_prepare_v2(db, sql, -1, &raw, nullptr) != SQLITE_OK) {
    sqlite3_finalize(raw);
    return Error{ErrorCode::kIoError, "map store " + path + ": " + sqlite3_errmsg(db)};
  }
  Stmt s(raw);
  const int rc = sqlite3_step(raw);
  if (rc == SQLITE_DONE) return std::optional<std::string>();
  if (rc != SQLITE_ROW) return Error{ErrorCode::kIoError, "map store " + path + ": " + sqlite3_errmsg(db)};
  const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(raw, 0));
  return std::optional<std::string>(text != nullptr ? text : "");
}

}  // namespace

Result<std::unique_ptr<MapStore>> openSqliteStore(const SqliteStoreOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  const std::string path = options.path.string();
  std::error_code ec;
  const bool exists = std::filesystem::exists(options.path, ec);
  if (!exists && !options.create_if_missing) {
    return Error{ErrorCode::kNotFound, "map store " + path + " does not exist"};
  }
  if (!exists && options.path.has_parent_path()) std::filesystem::create_directories(options.path.parent_path(), ec);

  if (options.read_only && !exists) return Error{ErrorCode::kNotFound, "map store " + path + " does not exist"};
  sqlite3* raw = nullptr;
  const int flags =
      (options.read_only ? SQLITE_OPEN_READONLY : (SQLITE_OPEN_READWRITE | (exists ? 0 : SQLITE_OPEN_CREATE))) |
      SQLITE_OPEN_NOMUTEX;
  const int rc = sqlite3_open_v2(path.c_str(), &raw, flags, nullptr);
  Db db(raw);
  if (rc != SQLITE_OK) {
    return Error{ErrorCode::kIoError,
                 "map store " + path + ": cannot open: " + (raw != nullptr ? sqlite3_errmsg(raw) : "out of memory")};
  }
  sqlite3_extended_result_codes(raw, 0);
  // Readers of one recording share it and may meet each other setting up its WAL index: they wait for that.
  sqlite3_busy_timeout(raw, options.read_only ? 5000 : 0);
  // One process holds the store: a second server on the same file is refused at once (readers share it).
  if (Status s = exec(raw, path, options.read_only ? "PRAGMA query_only=1" : "PRAGMA locking_mode=EXCLUSIVE",
                      "setting the locking mode");
      !s.ok()) {
    return s.error();
  }
  if (exists) {
    // A file SQLite cannot read at all, or one held by another process, fails here.
    auto tables = queryText(raw, path, "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = 'meta'");
    if (!tables) {
      return tables.error().withContext(
          "it is not a readable SQLite file (damaged or truncated?), or another "
          "cvislam_server holds it");
    }
    if (!*tables || **tables == "0") {
      return Error{ErrorCode::kDataError,
                   "map store " + path +
                       " exists but is not a cvislam map store (it has no meta table; an empty file is refused too, "
                       "so that a truncated store is never silently started afresh): give another path or move the "
                       "file aside"};
    }
  }
  if (options.read_only) {
    // Nothing to set up: a recording is read as it is.
  } else if (Status s = exec(raw, path, "PRAGMA journal_mode=WAL", "choosing the WAL journal"); !s.ok()) {
    return s.error();
  }
  const char* sync = options.sync == SqliteStoreOptions::Sync::kFull     ? "PRAGMA synchronous=FULL"
                     : options.sync == SqliteStoreOptions::Sync::kNormal ? "PRAGMA synchronous=NORMAL"
                                                                         : "PRAGMA synchronous=OFF";
  if (Status s = exec(raw, path, options.read_only ? "SELECT 1" : sync, "setting synchronous"); !s.ok()) {
    return s.error();
  }
  // Take the exclusive lock now rather than at the first append.
  if (Status s = exec(raw, path, options.read_only ? "SELECT 1" : "BEGIN IMMEDIATE; COMMIT",
                      "locking (is another cvislam_server using this store?)");
      !s.ok()) {
    return s.error();
  }

  if (!exists) {
    const std::string create =
        "BEGIN;"
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);"
        "CREATE TABLE records (number INTEGER PRIMARY KEY AUTOINCREMENT, kind INTEGER NOT NULL, "
        "  mission TEXT NOT NULL, agent INTEGER NOT NULL, sequence INTEGER NOT NULL, body BLOB NOT NULL, "
        "  checksum INTEGER NOT NULL);"
        "CREATE UNIQUE INDEX records_batch ON records (mission, agent, sequence) WHERE kind = 2;"
        "CREATE INDEX records_mission ON records (mission, number);"
        "INSERT INTO meta VALUES ('format', '" +
        std::string(kFormat) + "'), ('schema', '" + std::to_string(kStoreSchemaVersion) + "');";
    if (Status s = exec(raw, path, create.c_str(), "creating the tables"); !s.ok()) return s.error();
    // The software's name is bound, never spliced into the SQL.
    sqlite3_stmt* by = nullptr;
    if (sqlite3_prepare_v2(raw, "INSERT INTO meta VALUES ('created_by', ?1)", -1, &by, nullptr) != SQLITE_OK) {
      sqlite3_finalize(by);
      return Error{ErrorCode::kIoError, "map store " + path + ": " + sqlite3_errmsg(raw)};
    }
    Stmt created_by(by);
    sqlite3_bind_text(by, 1, options.software.data(), static_cast<int>(options.software.size()), SQLITE_STATIC);
    if (sqlite3_step(by) != SQLITE_DONE) {
      return Error{ErrorCode::kIoError, "map store " + path + ": writing its meta data: " + sqlite3_errmsg(raw)};
    }
    if (Status s = exec(raw, path, "COMMIT", "creating the tables"); !s.ok()) return s.error();
  } else {
    if (options.check_on_open) {
      auto check = queryText(raw, path, "PRAGMA quick_check");
      if (!check) return check.error().withContext("checking the file");
      if (!*check || **check != "ok") {
        return Error{ErrorCode::kDataError, "map store " + path + " is damaged (SQLite quick_check: " +
                                                (*check ? **check : std::string("no answer")) +
                                                "): restore it from a backup or move it aside"};
      }
    }
    auto format = queryText(raw, path, "SELECT value FROM meta WHERE key = 'format'");
    if (!format) return format.error();
    if (!*format || **format != kFormat) {
      return Error{ErrorCode::kDataError, "map store " + path + " is not a cvislam map store (its format is '" +
                                              (*format ? **format : std::string()) + "')"};
    }
    auto schema = queryText(raw, path, "SELECT value FROM meta WHERE key = 'schema'");
    if (!schema) return schema.error();
    if (!*schema || **schema != std::to_string(kStoreSchemaVersion)) {
      auto by = queryText(raw, path, "SELECT value FROM meta WHERE key = 'created_by'");
      const std::string creator = by && *by ? **by : std::string("an unknown version");
      return Error{ErrorCode::kFailedPrecondition,
                   "map store " + path + " has schema version " + (*schema ? **schema : std::string("(none)")) +
                       " (made by " + creator + "); this server reads version " + std::to_string(kStoreSchemaVersion) +
                       ": open it with the server that wrote it"};
    }
  }

  StoreCounters counters;
  auto count = queryText(raw, path, "SELECT count(*) || ' ' || coalesce(sum(length(body)), 0) FROM records");
  if (!count) return count.error().withContext("counting the records");
  unsigned long long records = 0;
  unsigned long long bytes = 0;
  if (*count && std::sscanf((*count)->c_str(), "%llu %llu", &records, &bytes) == 2) {
    counters.records = records;
    counters.bytes = bytes;
  }
  auto store = std::make_unique<SqliteStore>(std::move(db), options, counters);
  if (Status s = store->prepare(); !s.ok()) return s.error();
  return std::unique_ptr<MapStore>(std::move(store));
}

}  // namespace cvislam::server
