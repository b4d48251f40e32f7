// The server core with a map store, driven without gRPC: a core that is dropped (as a SIGKILL would drop it) and
// made again over the same store holds every batch it acknowledged, each once; the agent reconnects and goes on
// where it was; a batch the store refuses is neither applied nor acknowledged; and a store that cannot be replayed
// stops the start with an error that names the record.
#include <memory>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include <gmock/gmock.h>

#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/store/sqlite_store.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/session_driver.hpp"
#include "test/server_cloud/store/faulty_stores.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using test::batchMessage;
using test::helloMessage;
using test::InDoubtStore;
using test::makeKeyframeBatch;
using ::testing::HasSubstr;

const std::string kMission = "hall-1";
constexpr std::uint32_t kAgent = 4;
constexpr std::uint64_t kSession = 0x5eed'0001;

// The store's seam for a disk that fails: Hellos are kept, batches refused.
class RefusingStore final : public MapStore {
 public:
  Status append(const StoreRecord& r) override {
    if (r.kind == StoreRecord::Kind::kBatch) return Error{ErrorCode::kIoError, "disk full"};
    ++hellos;
    return Status::Ok();
  }
  Status replay(const std::string&, const std::function<Status(const StoreRecord&)>&) const override {
    return Status::Ok();
  }
  [[nodiscard]] Result<std::optional<StoreRecord>> findBatch(const std::string&, AgentId,
                                                             std::uint64_t) const override {
    return std::optional<StoreRecord>();
  }
  [[nodiscard]] Result<std::vector<std::string>> missions() const override { return std::vector<std::string>{}; }
  [[nodiscard]] StoreCounters counters() const override { return {}; }
  [[nodiscard]] std::string describe() const override { return "refusing"; }
  int hellos = 0;
};

class DurableCoreTest : public ::testing::Test {
 protected:
  ServerOptions options() const {
    ServerOptions o;
    o.store = dir_ / "maps.db";
    o.store_sync = SqliteStoreOptions::Sync::kNormal;
    return o;
  }
  std::unique_ptr<ServerCore> startCore(RecoveryReport* report = nullptr) {
    auto core = std::make_unique<ServerCore>(options());
    auto recovered = core->openStore();
    EXPECT_TRUE(recovered.ok()) << recovered.error().toString();
    if (report != nullptr && recovered.ok()) *report = *recovered;
    return core;
  }
  Status send(AgentSession& session, const v1::AgentUplink& message) {
    return test::sendTo(session, message, &reply_, &reply_due_);
  }
  void sendOk(AgentSession& session, const v1::AgentUplink& message) {
    const Status s = send(session, message);
    ASSERT_TRUE(s.ok()) << s.error().toString();
  }
  // A store written as a server would have written it: the agent's Hello, then these (sequence, body) batches.
  void writeStore(const std::vector<std::pair<std::uint64_t, std::string>>& batches) {
    SqliteStoreOptions o;
    o.path = options().store;
    auto store = openSqliteStore(o);
    ASSERT_TRUE(store.ok()) << store.error().toString();
    const std::string hello = test::makeHello(kMission, kAgent, kSession).SerializeAsString();
    ASSERT_TRUE((*store)->append({0, StoreRecord::Kind::kHello, kMission, kAgent, 0, hello}).ok());
    for (const auto& [sequence, body] : batches) {
      ASSERT_TRUE((*store)->append({0, StoreRecord::Kind::kBatch, kMission, kAgent, sequence, body}).ok());
    }
  }
  // The agent's keyframe counters in the mission's maps, each as often as a map holds it.
  static std::multiset<std::uint32_t> keyframesInMaps(const ServerCore& core) {
    std::multiset<std::uint32_t> out;
    for (const auto& map : core.missions().find(kMission)->stack().maps()) {
      for (const auto& [id, kf] : map->read()->keyframes()) out.insert(id.counter);
    }
    return out;
  }

  cvislam::test::TempDir dir_;
  v1::ServerDownlink reply_;
  bool reply_due_ = false;
};

TEST_F(DurableCoreTest, ARestartedCoreHoldsEveryAcknowledgedBatchOnceAndTheAgentGoesOnWhereItWas) {
  std::multiset<std::uint32_t> before;
  std::size_t points_before = 0;
  {
    auto core = startCore();
    auto session = core->openSession({});
    sendOk(*session, helloMessage(kMission, kAgent, kSession));
    for (std::uint64_t s = 1; s <= 5; ++s) {
      sendOk(*session, batchMessage(makeKeyframeBatch(s, static_cast<std::uint32_t>(2 * (s - 1)), 2)));
    }
    before = keyframesInMaps(*core);
    points_before = core->missions().find(kMission)->agent(kAgent)->read()->points.size();
    // Dropped without a goodbye, as a killed process would be (closing a session writes nothing to the store).
  }
  ASSERT_EQ(before.size(), 10U);

  RecoveryReport report;
  auto core = startCore(&report);
  EXPECT_EQ(report.hellos, 1U);
  EXPECT_EQ(report.batches, 5U);
  EXPECT_EQ(report.keyframes, 10U);
  EXPECT_EQ(report.missions, 1U);
  EXPECT_EQ(report.agents, 1U);
  EXPECT_EQ(keyframesInMaps(*core), before);
  {
    auto record = core->missions().find(kMission)->agent(kAgent)->read();
    EXPECT_EQ(record->stored_sequence, 5U);
    EXPECT_EQ(record->points.size(), points_before);
    EXPECT_FALSE(record->connected);
  }

  // The same agent process reconnects: told batch 5 is stored; it sends 5 again (it never saw the ack) and 6.
  auto session = core->openSession({});
  sendOk(*session, helloMessage(kMission, kAgent, kSession));
  EXPECT_EQ(reply_.welcome().stored_sequence(), 5U);
  EXPECT_EQ(reply_.welcome().keyframes_held(), 10U);
  sendOk(*session, batchMessage(makeKeyframeBatch(5, 8, 2)));
  sendOk(*session, batchMessage(makeKeyframeBatch(6, 10, 2)));
  const auto after = keyframesInMaps(*core);
  EXPECT_EQ(after.size(), 12U);
  EXPECT_EQ(std::set<std::uint32_t>(after.begin(), after.end()).size(), 12U);  // each once
  EXPECT_EQ(core->missions().find(kMission)->agent(kAgent)->read()->duplicate_batches, 1U);
  // One Hello (the reconnect's said the same, so it was not stored again) and batches 1..6.
  EXPECT_EQ(core->store()->counters().records, 1U + 5U + 1U);
}

TEST_F(DurableCoreTest, AnotherProcessClaimingTheAgentAfterARestartIsStillRefused) {
  {
    auto core = startCore();
    auto session = core->openSession({});
    sendOk(*session, helloMessage(kMission, kAgent, kSession));
    sendOk(*session, batchMessage(makeKeyframeBatch(1, 0, 2)));
  }
  auto core = startCore();
  auto session = core->openSession({});
  const Status s = send(*session, helloMessage(kMission, kAgent, kSession + 1));
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(s.error().message(), HasSubstr("streamed by another process before"));
}

TEST_F(DurableCoreTest, ABatchTheStoreRefusesIsNeitherAppliedNorAcknowledgedAndEndsTheStreamUnavailable) {
  ServerCore core(ServerOptions{});
  auto store = std::make_unique<RefusingStore>();
  RefusingStore* refusing = store.get();
  ASSERT_TRUE(core.attachStore(std::move(store)).ok());
  auto session = core.openSession({});
  sendOk(*session, helloMessage(kMission, kAgent, kSession));
  EXPECT_EQ(refusing->hellos, 1);
  const Status s = send(*session, batchMessage(makeKeyframeBatch(1, 0, 2)));
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kUnavailable);
  // The store's own words stay in the server's log: the agent gets the number they are under.
  EXPECT_THAT(s.error().message(), HasSubstr("batch 1: the server could not store it (server error #"));
  EXPECT_THAT(s.error().message(), ::testing::Not(HasSubstr("disk full")));
  auto mission = core.missions().find(kMission);
  auto record = mission->agent(kAgent)->read();
  EXPECT_EQ(record->stored_sequence, 0U);
  EXPECT_TRUE(record->keyframes.empty());
  EXPECT_TRUE(mission->stack().maps().empty());
  EXPECT_EQ(mission->events().nextNumber(), 2U);  // the connection only
}

TEST_F(DurableCoreTest, ABatchStoredWhoseCommitAnswerWasLostCountsAsStoredAtTheAgentsNextHello) {
  SqliteStoreOptions o;
  o.path = dir_ / "maps.db";
  auto sqlite = openSqliteStore(o);
  ASSERT_TRUE(sqlite.ok()) << sqlite.error().toString();
  ServerCore core(ServerOptions{});
  ASSERT_TRUE(core.attachStore(std::make_unique<InDoubtStore>(std::move(sqlite).value(), 1)).ok());
  {
    auto session = core.openSession({});
    sendOk(*session, helloMessage(kMission, kAgent, kSession));
    const Status lost = send(*session, batchMessage(makeKeyframeBatch(1, 0, 2)));
    ASSERT_FALSE(lost.ok());  // in doubt: neither applied nor acknowledged, the stream ends
    EXPECT_EQ(lost.error().code(), ErrorCode::kUnavailable);
    EXPECT_EQ(core.missions().find(kMission)->agent(kAgent)->read()->stored_sequence, 0U);
  }
  // The agent reconnects. The store holds batch 1: the Welcome says so, so that the agent never builds another
  // batch 1 from what it holds now. A resend of the same batch 1 is a duplicate.
  auto session = core.openSession({});
  sendOk(*session, helloMessage(kMission, kAgent, kSession));
  EXPECT_EQ(reply_.welcome().stored_sequence(), 1U);
  EXPECT_EQ(reply_.welcome().resend_from_sequence(), 0U);
  sendOk(*session, batchMessage(makeKeyframeBatch(1, 0, 2)));
  sendOk(*session, batchMessage(makeKeyframeBatch(2, 2, 2)));
  {
    auto record = core.missions().find(kMission)->agent(kAgent)->read();
    EXPECT_EQ(record->stored_sequence, 2U);
    EXPECT_EQ(record->caught_up_batches, 1U);
    EXPECT_EQ(record->duplicate_batches, 1U);
  }
  EXPECT_EQ(keyframesInMaps(core).size(), 4U);
  std::vector<std::uint64_t> stored;
  ASSERT_TRUE(core.store()
                  ->replay(kMission,
                           [&](const StoreRecord& r) {
                             if (r.kind == StoreRecord::Kind::kBatch) stored.push_back(r.sequence);
                             return Status::Ok();
                           })
                  .ok());
  EXPECT_EQ(stored, (std::vector<std::uint64_t>{1, 2}));  // each once
}

// The store may still hold a number that memory does not, if an append commits after the Hello looked (another
// replica's late commit). A batch under that number with other content is not applied: the stored one is, the
// stream ends, and the next Welcome asks the agent to send its content again.
TEST_F(DurableCoreTest, ABatchThatDiffersFromTheOneStoredUnderItsNumberGivesWayToTheStoredOne) {
  SqliteStoreOptions o;
  o.path = dir_ / "maps.db";
  auto sqlite = openSqliteStore(o);
  ASSERT_TRUE(sqlite.ok()) << sqlite.error().toString();
  MapStore* raw = sqlite->get();
  auto owned = std::make_unique<ServerCore>(ServerOptions{});
  ServerCore& core = *owned;
  ASSERT_TRUE(core.attachStore(std::move(sqlite).value()).ok());
  auto session = core.openSession({});
  sendOk(*session, helloMessage(kMission, kAgent, kSession));
  sendOk(*session, batchMessage(makeKeyframeBatch(1, 0, 2)));
  // Batch 2 with keyframes 2 and 3 lands in the store behind the session's back.
  const std::string first_attempt = makeKeyframeBatch(2, 2, 2).SerializeAsString();
  ASSERT_TRUE(raw->append({0, StoreRecord::Kind::kBatch, kMission, kAgent, 2, first_attempt}).ok());
  // The agent's batch 2 is another: keyframes 2 to 4.
  const Status conflict = send(*session, batchMessage(makeKeyframeBatch(2, 2, 3)));
  ASSERT_FALSE(conflict.ok());
  EXPECT_EQ(conflict.error().code(), ErrorCode::kAborted);
  EXPECT_THAT(conflict.error().message(), HasSubstr("differs from the batch 2 the server had stored"));
  {
    auto record = core.missions().find(kMission)->agent(kAgent)->read();
    EXPECT_EQ(record->stored_sequence, 2U);
    EXPECT_EQ(record->resend_conflicts, 1U);
  }
  EXPECT_EQ(keyframesInMaps(core), (std::multiset<std::uint32_t>{0, 1, 2, 3}));  // what the store holds

  auto again = core.openSession({});
  sendOk(*again, helloMessage(kMission, kAgent, kSession));
  EXPECT_EQ(reply_.welcome().stored_sequence(), 2U);
  EXPECT_EQ(reply_.welcome().resend_from_sequence(), 2U);
  // The agent sends batch 2's content again as batch 3: keyframe 4 comes, 2 and 3 are duplicates.
  v1::MapBatch resent = makeKeyframeBatch(3, 2, 3);
  sendOk(*again, batchMessage(resent));
  EXPECT_EQ(keyframesInMaps(core), (std::multiset<std::uint32_t>{0, 1, 2, 3, 4}));
  EXPECT_EQ(core.missions().find(kMission)->agent(kAgent)->read()->resend_from, 0U);  // told, and it answered

  // What memory holds is what a restart replays.
  const auto before = keyframesInMaps(core);
  again.reset();
  session.reset();
  owned.reset();
  auto restarted = startCore();
  EXPECT_EQ(keyframesInMaps(*restarted), before);
}

// A reconnect loop of one agent (the same process, the same Hello): the store gets that Hello once, and the
// mission's event log gets a bounded number of connection events, so map events are not pushed out.
TEST_F(DurableCoreTest, AReconnectLoopStoresTheHelloOnceAndIsCutOffBeforeItFloodsTheEventLog) {
  auto core = startCore();
  int refused = 0;
  Status last;
  for (int i = 0; i < 200; ++i) {
    auto session = core->openSession({});
    const Status s = send(*session, helloMessage(kMission, kAgent, kSession));
    if (!s.ok()) {
      ++refused;
      last = s;
      continue;
    }
    if (i == 0) sendOk(*session, batchMessage(makeKeyframeBatch(1, 0, 2)));
  }
  const ServerOptions o = options();
  EXPECT_EQ(core->store()->counters().records, 2U);  // one Hello, one batch
  EXPECT_GE(refused, 200 - static_cast<int>(o.session.agent_hello_burst) - 1);
  EXPECT_EQ(last.error().code(), ErrorCode::kResourceExhausted);
  EXPECT_THAT(last.error().message(), HasSubstr("limits.agent_hellos_per_minute"));
  const auto events = core->missions().find(kMission)->events().read(1, 1000);
  EXPECT_EQ(events.skipped, 0U);
  EXPECT_LE(events.events.size(), 2 * static_cast<std::size_t>(o.session.agent_hello_burst) + 4);
  EXPECT_EQ(core->missions().find(kMission)->agent(kAgent)->read()->hellos_refused,
            static_cast<std::uint64_t>(refused));
}

// The disk fills while an agent says Hello: the Hello is refused UNAVAILABLE, nothing about the agent changes,
// and the agent comes in once the store takes records again.
TEST_F(DurableCoreTest, AHelloTheStoreCannotKeepIsRefusedAndChangesNothing) {
  class FullDiskStore final : public test::ForwardingStore {
   public:
    using ForwardingStore::ForwardingStore;
    Status append(const StoreRecord& r) override {
      if (full) return Error{ErrorCode::kIoError, "database or disk is full"};
      return ForwardingStore::append(r);
    }
    bool full = true;
  };
  SqliteStoreOptions o;
  o.path = dir_ / "maps.db";
  auto sqlite = openSqliteStore(o);
  ASSERT_TRUE(sqlite.ok());
  auto store = std::make_unique<FullDiskStore>(std::move(sqlite).value());
  FullDiskStore* disk = store.get();
  ServerCore core(ServerOptions{});
  ASSERT_TRUE(core.attachStore(std::move(store)).ok());
  auto session = core.openSession({});
  const Status refused = send(*session, helloMessage(kMission, kAgent, kSession));
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code(), ErrorCode::kUnavailable);
  EXPECT_THAT(refused.error().message(), HasSubstr("could not store the Hello"));
  {
    auto record = core.missions().find(kMission)->agent(kAgent)->read();
    EXPECT_FALSE(record->connected);
    EXPECT_EQ(record->connections, 0U);
    EXPECT_FALSE(record->sensors.has_value());
  }
  EXPECT_EQ(core.missions().find(kMission)->events().nextNumber(), 1U);  // nothing logged
  disk->full = false;
  auto again = core.openSession({});
  sendOk(*again, helloMessage(kMission, kAgent, kSession));
  sendOk(*again, batchMessage(makeKeyframeBatch(1, 0, 2)));
  EXPECT_EQ(core.store()->counters().records, 2U);
}

TEST_F(DurableCoreTest, AStoreWithAGapInAnAgentsBatchesStopsTheStartNamingTheRecord) {
  writeStore(
      {{1, makeKeyframeBatch(1, 0, 2).SerializeAsString()}, {3, makeKeyframeBatch(3, 4, 2).SerializeAsString()}});
  ServerCore core(options());
  auto recovered = core.openStore();
  ASSERT_FALSE(recovered.ok());
  EXPECT_THAT(recovered.error().message(), HasSubstr("store record 3 (batch of agent 4, mission 'hall-1')"));
  EXPECT_THAT(recovered.error().message(), HasSubstr("batch 3 follows batch 1: the store has a gap"));
  EXPECT_EQ(core.store(), nullptr);  // nothing is served from it
}

TEST_F(DurableCoreTest, ARecordWhoseBodyDoesNotParseOrApplyStopsTheStartNamingIt) {
  for (const std::string& body : {std::string("\xff\xff\xff\xff", 4), std::string()}) {
    SCOPED_TRACE(body.size());
    std::filesystem::remove(options().store);
    writeStore({{1, body}});
    ServerCore core(options());
    auto recovered = core.openStore();
    ASSERT_FALSE(recovered.ok());
    EXPECT_THAT(recovered.error().message(), HasSubstr("store record 2"));
  }
}

TEST_F(DurableCoreTest, WithoutAStorePathNothingIsOpenedAndNothingIsWritten) {
  ServerCore core(ServerOptions{});
  auto recovered = core.openStore();
  ASSERT_TRUE(recovered.ok());
  EXPECT_EQ(core.store(), nullptr);
  EXPECT_TRUE(std::filesystem::is_empty(dir_.path()));
}

}  // namespace
}  // namespace cvislam::server
