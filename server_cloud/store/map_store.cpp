#include "server_cloud/store/map_store.hpp"

#include "common/core/hash.hpp"

namespace cvislam::server {

std::string_view toString(StoreRecord::Kind kind) {
  switch (kind) {
    case StoreRecord::Kind::kHello:
      return "hello";
    case StoreRecord::Kind::kBatch:
      return "batch";
  }
  return "unknown";
}

std::uint64_t recordChecksum(StoreRecord::Kind kind, std::string_view mission, AgentId agent, std::uint64_t sequence,
                             std::string_view body) {
  Fnv1a64 hash;
  const auto add = [&](std::uint64_t v) {
    char bytes[8];
    for (int i = 0; i < 8; ++i) bytes[i] = static_cast<char>((v >> (8 * i)) & 0xFFU);
    hash.add(std::string_view(bytes, 8));
  };
  add(static_cast<std::uint64_t>(kind));
  add(mission.size());
  hash.add(mission);
  add(agent);
  add(sequence);
  add(body.size());
  hash.add(body);
  return hash.value();
}

Status checkStoredRecord(int raw_kind, std::int64_t raw_agent, std::uint64_t stored_checksum, const std::string& where,
                         StoreRecord& r) {
  if (raw_kind != static_cast<int>(StoreRecord::Kind::kHello) &&
      raw_kind != static_cast<int>(StoreRecord::Kind::kBatch)) {
    return Error{ErrorCode::kDataError, where + " has the unknown kind " + std::to_string(raw_kind) +
                                            ": the store is damaged or was written by another version"};
  }
  if (raw_agent < 0 || raw_agent > 0xFFFF) {
    return Error{ErrorCode::kDataError, where + " names agent " + std::to_string(raw_agent) + ", which is over 65535"};
  }
  r.kind = static_cast<StoreRecord::Kind>(raw_kind);
  r.agent = static_cast<AgentId>(raw_agent);
  if (recordChecksum(r.kind, r.mission, r.agent, r.sequence, r.body) != stored_checksum) {
    return Error{ErrorCode::kDataError, where + " (" + std::string(toString(r.kind)) + " " +
                                            std::to_string(r.sequence) + " of agent " + std::to_string(r.agent) +
                                            ", mission '" + r.mission +
                                            "') fails its checksum: the store is damaged; restore it from a backup "
                                            "or move it aside"};
  }
  return Status::Ok();
}

}  // namespace cvislam::server
