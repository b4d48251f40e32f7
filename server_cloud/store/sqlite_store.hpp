// The embedded map store: one SQLite file (WAL journal), held by one server process at a time.
//
// Layout: a `meta` table (format, schema version, the software that created it) and a `records` table (one row
// per StoreRecord, with an FNV-1a checksum over its fields). Opening checks, and refuses with an error that names
// the file and what to do:
//   - a file that exists but is not a cvislam map store (also an empty one: the store is never silently made anew
//     over a file that was truncated to nothing);
//   - a store of another schema version;
//   - a damaged file (SQLite's quick_check: truncation, overwritten pages);
//   - a store another process holds (exclusive locking).
// replay() checks every record's checksum and names the first one that fails.
#pragma once

#include <filesystem>
#include <memory>
#include <string>

#include "common/core/result.hpp"
#include "server_cloud/store/map_store.hpp"

namespace cvislam::server {

struct SqliteStoreOptions {
  std::filesystem::path path;
  // When a commit returns: kFull survives power loss (fsync per commit), kNormal survives a process crash
  // (SIGKILL) but may lose the newest commits on power loss, kOff leaves it to the OS (tests, benchmarks).
  enum class Sync { kOff, kNormal, kFull };
  Sync sync = Sync::kFull;
  bool create_if_missing = true;
  bool check_on_open = true;  // SQLite's quick_check of the whole file
  // Read only, shared with other readers (a recording that several replay clients read); append() fails.
  bool read_only = false;
  std::string software = "cvislam_server";  // written into a new store's meta table

  [[nodiscard]] Status validate() const;
};

// "full", "normal", "off" (the config and command-line names).
Result<SqliteStoreOptions::Sync> parseStoreSync(const std::string& name);
std::string_view toString(SqliteStoreOptions::Sync sync);

// The schema version this build writes and reads.
inline constexpr int kStoreSchemaVersion = 1;

Result<std::unique_ptr<MapStore>> openSqliteStore(const SqliteStoreOptions& options);

}  // namespace cvislam::server
