// The scale-out store on a real PostgreSQL (deploy/local_postgres.sh starts one for this process; every test gets
// a database of its own): mission leases (taking, lapsing, epochs, release) and the shared map store (appends
// fenced by the lease, duplicates refused, replay in order across pages, checksums). Lapses are made by moving a
// lease's expiry into the past in SQL, so that no test waits for a TTL.
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <future>
#include <memory>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "server_cloud/cluster/mission_leases.hpp"
#include "server_cloud/cluster/pg_connection.hpp"
#include "server_cloud/cluster/postgres_store.hpp"
#include "test/server_cloud/cluster/postgres_fixture.hpp"

namespace cvislam::server::cluster {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::Not;

const auto* const kEnvironment = ::testing::AddGlobalTestEnvironment(new PostgresEnvironment);

using ClusterStoreTest = PostgresTest;

TEST_F(ClusterStoreTest, AFreeMissionIsTakenAndAHeldOneNamesItsHolder) {
  auto a = leases("replica/a");
  auto b = leases("replica/b");
  auto taken = a->acquire("m1");
  ASSERT_TRUE(taken.ok()) << taken.error().toString();
  EXPECT_EQ(taken->holder, "replica/a");
  EXPECT_EQ(taken->epoch, 1);
  EXPECT_GT(taken->remaining_s, 20.0);
  auto refused = b->acquire("m1");  // held: b learns who serves it, and does not get it
  ASSERT_TRUE(refused.ok()) << refused.error().toString();
  EXPECT_EQ(refused->holder, "replica/a");
  EXPECT_EQ(refused->address, a->options().address);
  EXPECT_EQ(refused->epoch, 1);
  auto again = a->acquire("m1");  // the holder's own acquire keeps the epoch
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->epoch, 1);
}

TEST_F(ClusterStoreTest, ALapsedLeaseGoesToTheNextHolderWithTheNextEpochAndTheOldHolderLosesIt) {
  auto a = leases("replica/a");
  auto b = leases("replica/b");
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(a->acquire("m2").ok());
  lapse("m1");
  auto lapsed = a->lapsed();
  ASSERT_TRUE(lapsed.ok());
  EXPECT_THAT(*lapsed, ElementsAre("m1"));
  auto taken = b->acquire("m1");
  ASSERT_TRUE(taken.ok());
  EXPECT_EQ(taken->holder, "replica/b");
  EXPECT_EQ(taken->epoch, 2);
  auto renewed = a->renew();  // a still holds m2 only
  ASSERT_TRUE(renewed.ok());
  EXPECT_THAT(*renewed, ElementsAre("m2"));
  auto back = a->acquire("m1");
  ASSERT_TRUE(back.ok());
  EXPECT_EQ(back->holder, "replica/b");
}

TEST_F(ClusterStoreTest, AReleasedLeaseIsFreeAtOnce) {
  auto a = leases("replica/a");
  auto b = leases("replica/b");
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(b->release("m1").ok());  // not b's: nothing changes
  EXPECT_EQ(b->acquire("m1")->holder, "replica/a");
  ASSERT_TRUE(a->release("m1").ok());
  auto taken = b->acquire("m1");
  ASSERT_TRUE(taken.ok());
  EXPECT_EQ(taken->holder, "replica/b");
  EXPECT_EQ(taken->epoch, 2);
}

TEST_F(ClusterStoreTest, OtherHoldersNamesEachLiveReplicaOnce) {
  auto a = leases("replica/a");
  auto b = leases("replica/b");
  auto c = leases("replica/c");
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(a->acquire("m2").ok());
  ASSERT_TRUE(b->acquire("m3").ok());
  auto seen_by_c = c->otherHolders();
  ASSERT_TRUE(seen_by_c.ok());
  ASSERT_EQ(seen_by_c->size(), 2U);
  EXPECT_EQ((*seen_by_c)[0].holder, "replica/a");
  EXPECT_EQ((*seen_by_c)[1].holder, "replica/b");
  lapse("m3");  // b's only lease lapsed: b no longer counts
  auto seen_by_a = a->otherHolders();
  ASSERT_TRUE(seen_by_a.ok());
  EXPECT_THAT(*seen_by_a, IsEmpty());
}

TEST_F(ClusterStoreTest, AppendsAreFencedByTheMissionsLease) {
  auto a = leases("replica/a");
  auto b = leases("replica/b");
  auto store_a = store("replica/a");
  auto store_b = store("replica/b");
  const Status before = store_a->append(batch("m1", 0, 1));  // nobody holds m1 yet
  ASSERT_FALSE(before.ok());
  EXPECT_EQ(before.error().code(), ErrorCode::kFailedPrecondition);
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(store_a->append(batch("m1", 0, 1)).ok());
  const Status not_b = store_b->append(batch("m1", 0, 2));
  ASSERT_FALSE(not_b.ok());
  EXPECT_EQ(not_b.error().code(), ErrorCode::kFailedPrecondition);
  // a stalls, its lease lapses and b takes over: a's late append must not land behind b's back.
  lapse("m1");
  ASSERT_EQ(b->acquire("m1")->holder, "replica/b");
  const Status late = store_a->append(batch("m1", 0, 2));
  ASSERT_FALSE(late.ok());
  EXPECT_EQ(late.error().code(), ErrorCode::kFailedPrecondition);
  ASSERT_TRUE(store_b->append(batch("m1", 0, 2)).ok());
  EXPECT_THAT(sequences(*store_b, "m1"), ElementsAre(1, 2));
}

// An append that is still in flight when its holder's lease lapses and another replica takes the mission over
// (the statement started in time, its commit comes late). The new owner's replay, which follows its acquire, must
// see the appended row; otherwise it would hold the agent's sequence N-1 while the store holds N.
TEST_F(ClusterStoreTest, AnAppendInFlightAcrossATakeoverIsSeenByTheNewOwnersReplay) {
  auto a = leases("replica/a");
  auto b = leases("replica/b");
  auto store_b = store("replica/b");
  ASSERT_TRUE(a->acquire("m1").ok());
  // The old owner's append, in a transaction held open as a slow commit would hold it.
  auto in_flight = PgConnection::open(conninfo_, "in-flight append");
  ASSERT_TRUE(in_flight.ok());
  ASSERT_TRUE((*in_flight)->execScript("BEGIN").ok());
  auto appended = execAppend(**in_flight, batch("m1", 0, 1), "replica/a");
  ASSERT_TRUE(appended.ok()) << appended.error().toString();
  ASSERT_EQ(appended->affected(), 1);
  // Meanwhile: the lease lapses, b takes the mission and replays it at once, as a takeover does.
  auto takeover = std::async(std::launch::async, [&] {
    lapse("m1");
    auto taken = b->acquire("m1");
    EXPECT_TRUE(taken.ok());
    EXPECT_EQ(taken.ok() ? taken->holder : "", "replica/b");
    return sequences(*store_b, "m1");
  });
  const bool waited = takeover.wait_for(std::chrono::milliseconds(500)) == std::future_status::timeout;
  ASSERT_TRUE((*in_flight)->execScript("COMMIT").ok());
  const std::vector<std::uint64_t> replayed = takeover.get();
  EXPECT_TRUE(waited) << "the takeover did not wait for the append in flight";
  EXPECT_THAT(replayed, ElementsAre(1)) << "the new owner's replay missed an append that then committed";
  EXPECT_THAT(sequences(*store_b, "m1"), ElementsAre(1));
}

TEST_F(ClusterStoreTest, FindBatchGivesTheStoredBodyOrNothing) {
  auto a = leases("replica/a");
  auto s = store("replica/a");
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(s->append(batch("m1", 3, 1)).ok());
  ASSERT_TRUE(s->append(batch("m1", 3, 2)).ok());
  auto found = s->findBatch("m1", 3, 2);
  ASSERT_TRUE(found.ok()) << found.error().toString();
  ASSERT_TRUE(found->has_value());
  EXPECT_EQ((*found)->body, batch("m1", 3, 2).body);
  EXPECT_EQ((*found)->agent, 3U);
  for (const auto& [mission, agent, sequence] :
       std::vector<std::tuple<std::string, AgentId, std::uint64_t>>{{"m1", 3, 3}, {"m1", 4, 1}, {"m2", 3, 1}}) {
    auto none = s->findBatch(mission, agent, sequence);
    ASSERT_TRUE(none.ok());
    EXPECT_FALSE(none->has_value()) << mission << " " << agent << " " << sequence;
  }
}

// A statement that waits on the database (here a lock another session holds, as a hung or partitioned database
// would make it wait) fails within the statement timeout instead of blocking the replica's appends for ever.
TEST_F(ClusterStoreTest, AnAppendBlockedInTheDatabaseFailsWithinTheStatementTimeout) {
  auto a = leases("replica/a");
  ASSERT_TRUE(a->acquire("m1").ok());
  PostgresStoreOptions o;
  o.conninfo = conninfo_;
  o.holder = "replica/a";
  o.timeouts.statement_ms = 1000;
  auto s = openPostgresStore(o);
  ASSERT_TRUE(s.ok()) << s.error().toString();
  auto blocker = PgConnection::open(conninfo_, "blocker");
  ASSERT_TRUE(blocker.ok());
  ASSERT_TRUE((*blocker)->execScript("BEGIN; LOCK TABLE cvislam_records IN ACCESS EXCLUSIVE MODE").ok());
  const auto start = std::chrono::steady_clock::now();
  const Status blocked = (*s)->append(batch("m1", 0, 1));
  const double waited_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  ASSERT_TRUE((*blocker)->execScript("ROLLBACK").ok());
  ASSERT_FALSE(blocked.ok());
  EXPECT_THAT(blocked.error().message(), HasSubstr("statement timeout"));
  EXPECT_LT(waited_s, 5.0);
  EXPECT_GE(waited_s, 0.9);
  ASSERT_TRUE((*s)->append(batch("m1", 0, 1)).ok());  // the connection still works
}

TEST_F(ClusterStoreTest, ADuplicateBatchIsRefusedAndChangesNothing) {
  auto a = leases("replica/a");
  auto s = store("replica/a");
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(s->append(batch("m1", 3, 1)).ok());
  ASSERT_TRUE(s->append(batch("m1", 4, 1)).ok());  // another agent's sequence 1
  StoreRecord changed = batch("m1", 3, 1);
  changed.body = "something else";
  const Status dup = s->append(changed);
  ASSERT_FALSE(dup.ok());
  EXPECT_EQ(dup.error().code(), ErrorCode::kAlreadyExists);
  std::vector<std::string> bodies;
  ASSERT_TRUE(s->replay("m1", [&](const StoreRecord& r) {
                 bodies.push_back(r.body);
                 return Status::Ok();
               }).ok());
  EXPECT_THAT(bodies, ElementsAre(batch("m1", 3, 1).body, batch("m1", 4, 1).body));
}

TEST_F(ClusterStoreTest, ReplayKeepsTheOrderOfAcceptanceAcrossPagesAndMissions) {
  auto a = leases("replica/a");
  auto s = store("replica/a");
  ASSERT_TRUE(a->acquire("m1").ok());
  ASSERT_TRUE(a->acquire("m2").ok());
  for (std::uint64_t i = 1; i <= 600; ++i) {  // more than one page of the replay's reads
    ASSERT_TRUE(s->append(batch(i % 3 == 0 ? "m2" : "m1", 1, i)).ok());
  }
  const std::vector<std::uint64_t> m1 = sequences(*s, "m1");
  ASSERT_EQ(m1.size(), 400U);
  EXPECT_TRUE(std::is_sorted(m1.begin(), m1.end()));
  EXPECT_EQ(m1.front(), 1U);
  EXPECT_EQ(m1.back(), 599U);
  EXPECT_EQ(sequences(*s, "").size(), 600U);  // every mission
  auto missions = s->missions();
  ASSERT_TRUE(missions.ok());
  EXPECT_THAT(*missions, ElementsAre("m1", "m2"));
}

TEST_F(ClusterStoreTest, ACorruptRecordStopsTheReplayNamingIt) {
  auto a = leases("replica/a");
  auto s = store("replica/a");
  ASSERT_TRUE(a->acquire("m1").ok());
  for (std::uint64_t i = 1; i <= 3; ++i) ASSERT_TRUE(s->append(batch("m1", 0, i)).ok());
  auto c = PgConnection::open(conninfo_, "test");
  ASSERT_TRUE(c.ok());
  ASSERT_TRUE((*c)->exec("UPDATE cvislam_records SET body = 'flipped' WHERE sequence = 2").ok());
  std::vector<std::uint64_t> seen;
  const Status replayed = s->replay("m1", [&](const StoreRecord& r) {
    seen.push_back(r.sequence);
    return Status::Ok();
  });
  ASSERT_FALSE(replayed.ok());
  EXPECT_THAT(replayed.error().message(), HasSubstr("record"));
  EXPECT_THAT(replayed.error().message(), HasSubstr("checksum"));
  EXPECT_THAT(seen, ElementsAre(1));
}

TEST_F(ClusterStoreTest, AnUnreachableDatabaseIsNamedWithoutItsPassword) {
  LeaseOptions o;
  o.conninfo = "host=127.0.0.1 port=1 user=cvislam password=hunter2 dbname=cvislam connect_timeout=2";
  o.holder = "replica/a";
  o.address = "127.0.0.1:50051";
  auto opened = MissionLeases::open(o);
  ASSERT_FALSE(opened.ok());
  EXPECT_THAT(opened.error().toString(), HasSubstr("127.0.0.1"));
  EXPECT_THAT(opened.error().toString(), Not(HasSubstr("hunter2")));
  // In URI form too.
  EXPECT_EQ(redactConninfo("postgresql://cvislam:hunter2@db:5432/cvislam?sslmode=require"),
            "postgresql://cvislam:***@db:5432/cvislam?sslmode=require");
  EXPECT_EQ(redactConninfo("host=db password='a b' user=x"), "host=db password=*** user=x");
}

}  // namespace
}  // namespace cvislam::server::cluster
