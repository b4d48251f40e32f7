// Map persistence: the log of what the server accepted from its agents, from which it rebuilds every map stack.
//
// The server's maps are a function of what its agents sent: each agent's Hello (its sensors) and its map batches,
// applied in order. The store keeps exactly those, as the serialized messages, in the order the server accepted
// them. A batch is appended after ingest checked it and before ingest applies it, and the agent's acknowledgement
// follows the apply: so a batch is acknowledged only once it is durable, and a server that restarts replays the
// log and holds every batch it acknowledged, each once (a batch's (mission, agent, sequence) is stored at most
// once).
//
// What the server derives (merges, loop closures, global BA, redundancy removal) is not stored: place recognition
// and the back-end see the replayed keyframes as they saw the live ones and work it out again.
//
// An interface: server_cloud/store/sqlite_store.hpp is the embedded store of one server, and
// server_cloud/cluster/postgres_store.hpp the store that replicas share.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"

namespace cvislam::server {

struct StoreRecord {
  enum class Kind : std::uint8_t { kHello = 1, kBatch = 2 };
  std::uint64_t number = 0;  // the store's order of acceptance, from 1 (set by the store)
  Kind kind = Kind::kBatch;
  std::string mission;
  AgentId agent = 0;
  std::uint64_t sequence = 0;  // a batch's sequence; 0 for a Hello
  std::string body;            // the serialized v1::Hello or v1::MapBatch
};

std::string_view toString(StoreRecord::Kind kind);

// The checksum a store keeps beside each record: FNV-1a over every field, so that a flipped agent id is caught as
// surely as a flipped body byte.
std::uint64_t recordChecksum(StoreRecord::Kind kind, std::string_view mission, AgentId agent, std::uint64_t sequence,
                             std::string_view body);

// The checks every store makes on a record it reads back: `raw_kind` and `raw_agent` as stored (set into
// `record` when valid; its other fields are filled already) and the stored checksum. `where` names the record
// ("<store>: record 12"); the error says what is wrong with it and what to do.
Status checkStoredRecord(int raw_kind, std::int64_t raw_agent, std::uint64_t stored_checksum, const std::string& where,
                         StoreRecord& record);

struct StoreCounters {
  std::uint64_t records = 0;
  std::uint64_t bytes = 0;  // of the bodies
};

class MapStore {
 public:
  virtual ~MapStore() = default;

  // Appends `record` (its number is assigned) and returns once it is as durable as the store's options make it.
  // A second batch with the same (mission, agent, sequence) is refused with kAlreadyExists and changes nothing.
  // Safe to call from several threads.
  virtual Status append(const StoreRecord& record) = 0;

  // Calls `visit` for every record of `mission` (of every mission when empty) in the order they were appended,
  // after checking each one's checksum. Stops at the first error, its own or the one `visit` returns.
  virtual Status replay(const std::string& mission, const std::function<Status(const StoreRecord&)>& visit) const = 0;

  // The batch `sequence` of `agent` of `mission` as stored (checked like a replayed record), or nullopt when the
  // store does not hold it. What a session asks when an append's outcome is in doubt: an append that failed may
  // still have committed (the answer from the database was lost), so the store, not memory, says what that
  // sequence number holds.
  [[nodiscard]] virtual Result<std::optional<StoreRecord>> findBatch(const std::string& mission, AgentId agent,
                                                                     std::uint64_t sequence) const = 0;

  // The missions with records, by name.
  [[nodiscard]] virtual Result<std::vector<std::string>> missions() const = 0;
  [[nodiscard]] virtual StoreCounters counters() const = 0;
  // E.g. "sqlite /var/lib/cvislam/maps.db (synchronous=FULL)".
  [[nodiscard]] virtual std::string describe() const = 0;
};

}  // namespace cvislam::server
