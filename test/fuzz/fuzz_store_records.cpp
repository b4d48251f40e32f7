// Fuzzes what a server reads back from its store at start (a SQLite file, or PostgreSQL in scale-out): records whose
// kind, agent, sequence, mission name, body and checksum come from the input, checked as every store checks a record
// it reads (checkStoredRecord) and, when they pass, replayed into a fresh registry as a restart replays them
// (replayStored: Hellos, then batches through ingest). The input is a sequence of framed records (fuzz_target.hpp),
// each: kind (1 byte; its top bit asks for a wrong checksum), agent (2 bytes), sequence (1 byte), the mission
// name's length (1 byte), the name, then the body.
#include <memory>

#include "server_cloud/ingest/agent_session.hpp"
#include "server_cloud/stack/map_stack.hpp"
#include "server_cloud/store/map_store.hpp"
#include "test/fuzz/fuzz_target.hpp"
#include "test/server_cloud/link_messages.hpp"

namespace {

using namespace cvislam;

server::SessionOptions options() {
  server::SessionOptions o;
  o.ingest.max_keypoints_per_keyframe = 512;
  o.ingest.max_imu_samples_per_keyframe = 512;
  o.ingest.max_maps_per_agent = 8;
  return o;
}

std::string record(std::uint8_t kind, std::uint16_t agent, std::uint8_t sequence, const std::string& mission,
                   const std::string& body) {
  std::string out;
  out.push_back(static_cast<char>(kind));
  out.push_back(static_cast<char>(agent & 0xFFU));
  out.push_back(static_cast<char>(agent >> 8U));
  out.push_back(static_cast<char>(sequence));
  out.push_back(static_cast<char>(mission.size()));
  return out + mission + body;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  server::MissionRegistry missions;
  const server::SessionOptions session_options = options();
  std::uint64_t number = 0;
  for (const std::string& part : fuzz::frames(data, size, 32)) {
    if (part.size() < 5) continue;
    const auto kind = static_cast<std::uint8_t>(part[0]);
    const bool wrong_checksum = (kind & 0x80U) != 0;
    const int raw_kind = kind & 0x7FU;
    const std::int64_t raw_agent =
        static_cast<std::uint8_t>(part[1]) | (static_cast<std::int64_t>(static_cast<std::uint8_t>(part[2])) << 8U);
    const std::size_t name_size = static_cast<std::uint8_t>(part[4]);
    if (5 + name_size > part.size()) continue;
    server::StoreRecord r;
    r.number = ++number;
    r.sequence = static_cast<std::uint8_t>(part[3]);
    r.mission = part.substr(5, name_size);
    r.body = part.substr(5 + name_size);
    // The checksum as the store would have written it, for the kind and agent as they are when valid.
    const auto stored_kind = raw_kind == 1 ? server::StoreRecord::Kind::kHello : server::StoreRecord::Kind::kBatch;
    std::uint64_t checksum =
        server::recordChecksum(stored_kind, r.mission, static_cast<AgentId>(raw_agent), r.sequence, r.body);
    if (wrong_checksum) checksum ^= 0x5a5aU;
    const Status checked = server::checkStoredRecord(raw_kind, raw_agent, checksum, "fuzz record", r);
    if (wrong_checksum && checked.ok()) __builtin_trap();  // a flipped checksum must never pass
    if (!checked.ok()) continue;
    (void)server::replayStored(missions, session_options, r, {});
  }
  return 0;
}

std::vector<std::string> cvislam::fuzz::seeds() {
  const std::string hello = server::test::makeHello("fuzz", 3, 77).SerializeAsString();
  const std::string stereo = server::test::makeHello("fuzz", 2, 78, true).SerializeAsString();
  const std::string b1 = server::test::makeKeyframeBatch(1, 0, 2).SerializeAsString();
  const std::string b2 = server::test::makeKeyframeBatch(2, 2, 3).SerializeAsString();
  std::vector<std::string> out;
  out.push_back(fuzz::frame(record(1, 3, 0, "fuzz", hello)) + fuzz::frame(record(2, 3, 1, "fuzz", b1)) +
                fuzz::frame(record(2, 3, 2, "fuzz", b2)));
  out.push_back(fuzz::frame(record(1, 2, 0, "fuzz", stereo)) + fuzz::frame(record(2, 2, 1, "fuzz", b1)));
  out.push_back(fuzz::frame(record(1, 3, 0, "fuzz", hello)) + fuzz::frame(record(2, 3, 2, "fuzz", b2)));
  out.push_back(fuzz::frame(record(0x82, 3, 1, "fuzz", b1)));
  return out;
}
