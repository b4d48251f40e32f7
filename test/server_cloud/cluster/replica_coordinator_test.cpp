// ReplicaCoordinator on a real PostgreSQL, with loaders and droppers that stand for the server core: loads that
// take longer than the lease's TTL, leases lost to another replica and taken back, missions whose records do not
// load, and lookups in bulk. The coordinator's own threads run (renewal every ttl/3, loads on their thread).
#include "server_cloud/cluster/replica_coordinator.hpp"

#include <atomic>
#include <chrono>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "test/server_cloud/cluster/postgres_fixture.hpp"

namespace cvislam::server::cluster {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;

constexpr double kTtlS = 1.0;  // the shortest lease allowed: renewals every 1/3 s
// The sharing tests count where each mission went, so no live replica may lose a lease because its renewal ran
// late on a loaded machine: they use the default TTL and make the dead replica's leases lapse in SQL.
constexpr double kSharingTtlS = 3.0;

// What the core would do with its missions, recorded.
struct FakeCore {
  std::mutex mutex;
  std::map<std::string, int> loads;
  std::vector<std::string> dropped;
  std::map<std::string, std::chrono::milliseconds> load_time;
  std::set<std::string> broken;  // their records do not load

  ReplicaCoordinator::Loader loader() {
    return [this](const std::string& mission) -> Status {
      std::chrono::milliseconds sleep{0};
      {
        std::lock_guard lock(mutex);
        ++loads[mission];
        if (broken.count(mission) != 0U) {
          return Error{ErrorCode::kDataError, "store record 7 of mission '" + mission + "' fails its checksum"};
        }
        if (auto it = load_time.find(mission); it != load_time.end()) sleep = it->second;
      }
      std::this_thread::sleep_for(sleep);
      return Status::Ok();
    };
  }
  ReplicaCoordinator::Dropper dropper() {
    return [this](const std::string& mission) {
      std::lock_guard lock(mutex);
      dropped.push_back(mission);
    };
  }
  int loadsOf(const std::string& mission) {
    std::lock_guard lock(mutex);
    return loads[mission];
  }
  std::vector<std::string> droppedNow() {
    std::lock_guard lock(mutex);
    return dropped;
  }
};

class ReplicaCoordinatorTest : public PostgresTest {
 protected:
  std::unique_ptr<ReplicaCoordinator> coordinator(const std::string& holder, ReplicaOptions options = {},
                                                  double ttl_s = kTtlS) {
    return std::make_unique<ReplicaCoordinator>(
        leases(holder, ttl_s), leases(holder, ttl_s), core_.loader(), core_.dropper(), [] { return true; }, options);
  }
  // What a holder's death leaves once its TTL has passed: its heartbeat and leases lapsed (made so in SQL).
  void lapse(const std::string& holder) {
    auto c = PgConnection::open(conninfo_, "test");
    ASSERT_TRUE(c.ok());
    ASSERT_TRUE((*c)->exec("UPDATE cvislam_replicas SET expires_at = now() - interval '1 second' WHERE holder = $1",
                           PgParams().text(holder))
                    .ok());
    ASSERT_TRUE((*c)->exec("UPDATE cvislam_leases SET expires_at = now() - interval '1 second' WHERE holder = $1",
                           PgParams().text(holder))
                    .ok());
  }
  // Another replica takes the mission over in one statement, as its acquire after a lapse would (done in one step
  // so that the coordinator's running renewals cannot slip in between a lapse and the acquire).
  void takeOver(const std::string& mission, const std::string& holder) {
    auto c = PgConnection::open(conninfo_, "test");
    ASSERT_TRUE(c.ok());
    auto r = (*c)->exec(
        "UPDATE cvislam_leases SET holder = $2, address = '127.0.0.1:50999', epoch = epoch + 1, "
        "expires_at = now() + interval '30 seconds' WHERE mission = $1",
        PgParams().text(mission).text(holder));
    ASSERT_TRUE(r.ok()) << r.error().toString();
    ASSERT_EQ(r->affected(), 1);
  }
  // Claims until the mission is served here (the first claims are answered "loading").
  static Result<MissionOwner> claimServed(ReplicaCoordinator& c, const std::string& mission) {
    Result<MissionOwner> owner = c.claim(mission);
    for (int i = 0; i < 200 && !owner && owner.error().code() == ErrorCode::kUnavailable; ++i) {
      c.waitForLoads();
      owner = c.claim(mission);
    }
    return owner;
  }
  // Replicas a, b and c running, serving two, two and six missions (kOfC).
  struct ThreeReplicas {
    std::unique_ptr<ReplicaCoordinator> a, b, c;
  };
  static inline const std::vector<std::string> kOfC = {"c1", "c2", "c3", "c4", "c5", "c6"};
  ThreeReplicas threeReplicas() {
    ThreeReplicas r{coordinator("replica/a", {}, kSharingTtlS), coordinator("replica/b", {}, kSharingTtlS),
                    coordinator("replica/c", {}, kSharingTtlS)};
    for (auto* each : {r.a.get(), r.b.get(), r.c.get()}) each->start();
    for (const char* m : {"a1", "a2"}) EXPECT_TRUE(claimServed(*r.a, m).ok()) << m;
    for (const char* m : {"b1", "b2"}) EXPECT_TRUE(claimServed(*r.b, m).ok()) << m;
    for (const std::string& m : kOfC) EXPECT_TRUE(claimServed(*r.c, m).ok()) << m;
    return r;
  }
  FakeCore core_;
};

// A load longer than the TTL: the replica's other leases are renewed meanwhile (on their own connection, by their
// own thread), and a mission whose lease another replica took during the load is dropped, not served.
TEST_F(ReplicaCoordinatorTest, ALoadLongerThanTheTtlKeepsTheOtherLeasesAndServesNothingWhoseLeaseMoved) {
  core_.load_time["slow"] = std::chrono::milliseconds(2500);
  auto a = coordinator("replica/a");
  auto b = leases("replica/b");
  a->start();
  auto fast = claimServed(*a, "fast");
  ASSERT_TRUE(fast.ok()) << fast.error().toString();
  ASSERT_TRUE(fast->here);

  auto slow = a->claim("slow");  // its load has started: the Hello is told to come back
  ASSERT_FALSE(slow.ok());
  EXPECT_THAT(slow.error().message(), HasSubstr("is being loaded"));
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  // While it loads, replica b takes "slow" (a stalled, say): a must not serve it after its load.
  takeOver("slow", "replica/b");
  a->waitForLoads();

  EXPECT_THAT(a->served(), ElementsAre("fast"));
  EXPECT_THAT(core_.droppedNow(), ElementsAre("slow"));
  EXPECT_EQ(a->counters().lapsed_while_loading, 1U);
  auto held = b->acquire("fast");  // 2.5 s of load, more than twice the TTL: still a's
  ASSERT_TRUE(held.ok());
  EXPECT_EQ(held->holder, "replica/a");
  auto redirected = a->claim("slow");
  ASSERT_TRUE(redirected.ok()) << redirected.error().toString();
  EXPECT_FALSE(redirected->here);
  EXPECT_EQ(redirected->holder, "replica/b");
}

// Map reads ask owner(): while this replica still loads a mission it holds the lease of, a read is told to come
// back, not served a mission half replayed.
TEST_F(ReplicaCoordinatorTest, AMissionBeingLoadedIsNotOfferedToReadersUntilItsLoadEnds) {
  core_.load_time["m"] = std::chrono::milliseconds(1500);
  auto a = coordinator("replica/a");
  a->start();
  auto claimed = a->claim("m");
  ASSERT_FALSE(claimed.ok());  // its load has started
  auto during = a->owner("m");
  ASSERT_FALSE(during.ok()) << "a mission still loading was offered to a reader";
  EXPECT_EQ(during.error().code(), ErrorCode::kUnavailable);
  EXPECT_THAT(during.error().message(), HasSubstr("being loaded"));
  a->waitForLoads();
  auto after = a->owner("m");
  ASSERT_TRUE(after.ok()) << after.error().toString();
  EXPECT_TRUE(after->here);
}

// A lease lost to another replica ends the mission here (dropped); once that replica's lease lapses in turn, this
// replica takes the mission over again and loads it afresh.
TEST_F(ReplicaCoordinatorTest, ALostMissionIsDroppedAndTakenOverAgainWhenItsNewOwnerDies) {
  auto a = coordinator("replica/a");
  a->start();
  ASSERT_TRUE(claimServed(*a, "m").ok());
  ASSERT_THAT(a->served(), ElementsAre("m"));

  takeOver("m", "replica/b");  // a stalled past its TTL, say, and b took the mission
  a->tick();                   // a's next renewal finds the lease gone
  EXPECT_THAT(a->served(), IsEmpty());
  EXPECT_THAT(core_.droppedNow(), ElementsAre("m"));
  EXPECT_EQ(a->counters().lost, 1U);
  auto redirected = a->claim("m");
  ASSERT_TRUE(redirected.ok());
  EXPECT_EQ(redirected->holder, "replica/b");

  // b dies: its lease lapses, and a takes the mission back.
  auto c = PgConnection::open(conninfo_, "test");
  ASSERT_TRUE(c.ok());
  ASSERT_TRUE(
      (*c)->exec("UPDATE cvislam_leases SET expires_at = now() - interval '1 second' WHERE mission = 'm'").ok());
  for (int i = 0; i < 50 && a->served().empty(); ++i) {
    a->tick();
    a->waitForLoads();
  }
  EXPECT_THAT(a->served(), ElementsAre("m"));
  EXPECT_EQ(core_.loadsOf("m"), 2);
  EXPECT_EQ(a->counters().taken_over, 1U);
}

// A mission whose records do not load is tried again after a growing back-off, not at every renewal pass; a Hello
// for it is told why.
TEST_F(ReplicaCoordinatorTest, AMissionThatFailsToLoadIsRetriedAfterABackOffNotAtEveryPass) {
  core_.broken.insert("bad");
  ReplicaOptions options;
  options.retry_min_s = 30.0;
  auto a = coordinator("replica/a", options);
  auto z = leases("replica/z");
  ASSERT_TRUE(z->acquire("bad").ok());  // a replica that held it and died
  auto c = PgConnection::open(conninfo_, "test");
  ASSERT_TRUE(c.ok());
  ASSERT_TRUE(
      (*c)->exec("UPDATE cvislam_leases SET expires_at = now() - interval '1 second' WHERE mission = 'bad'").ok());
  a->start();
  std::this_thread::sleep_for(std::chrono::seconds(2));  // six renewal passes
  a->waitForLoads();
  EXPECT_EQ(core_.loadsOf("bad"), 1);
  EXPECT_EQ(a->counters().load_failures, 1U);
  EXPECT_THAT(core_.droppedNow(), ElementsAre("bad"));  // what the failed load applied goes
  auto refused = a->claim("bad");
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code(), ErrorCode::kUnavailable);
  EXPECT_THAT(refused.error().message(), HasSubstr("failed to load 1 time(s)"));
  // Why, by the number under which the server's log has it (the store's text names files and hosts).
  EXPECT_THAT(refused.error().message(), HasSubstr("server error #"));
  EXPECT_THAT(refused.error().message(), ::testing::Not(HasSubstr("fails its checksum")));
  EXPECT_EQ(core_.loadsOf("bad"), 1);
}

// Map-service lookups in bulk (listings, reads of other replicas' missions) are answered from a cache and do not
// hold up lease renewal: after three TTLs of them, every lease is still this replica's.
TEST_F(ReplicaCoordinatorTest, LookupsInBulkLeaveTheLeasesRenewed) {
  auto a = coordinator("replica/a");
  auto b = leases("replica/b");
  ASSERT_TRUE(b->acquire("elsewhere").ok());
  a->start();
  ASSERT_TRUE(claimServed(*a, "here").ok());
  std::atomic<bool> stop{false};
  std::atomic<long> lookups{0};
  std::vector<std::thread> readers;
  for (int t = 0; t < 2; ++t) {
    readers.emplace_back([&] {
      while (!stop.load()) {
        EXPECT_TRUE(a->others().ok());
        auto owner = a->owner("elsewhere");
        EXPECT_TRUE(owner.ok());
        lookups += 2;
      }
    });
  }
  std::this_thread::sleep_for(std::chrono::seconds(3));
  stop = true;
  for (auto& r : readers) r.join();
  std::printf("%ld lookups in 3 s\n", lookups.load());
  EXPECT_GT(lookups.load(), 1000);
  EXPECT_THAT(a->served(), ElementsAre("here"));
  EXPECT_EQ(a->counters().lost, 0U);
  EXPECT_EQ(b->acquire("here")->holder, "replica/a");
}

// Lapsed missions are shared out in name order, each to the live replica that then serves fewest; every replica
// computes the same share, so the shares of two replicas are disjoint and together cover every mission.
TEST(TakeoverShareTest, EachLapsedMissionGoesToTheReplicaServingFewestAndTheSharesAreDisjoint) {
  const std::vector<std::string> lapsed = {"m8", "m1", "m2", "m3", "m4", "m5", "m6", "m7"};
  const std::vector<ReplicaLoad> even = {{"a", "", 8}, {"b", "", 8}};
  EXPECT_THAT(takeoverShare(lapsed, even, "a"), ElementsAre("m1", "m3", "m5", "m7"));
  EXPECT_THAT(takeoverShare(lapsed, even, "b"), ElementsAre("m2", "m4", "m6", "m8"));
  // b serves 4 fewer: it takes the first four, then they alternate (ties go to a, first by name).
  const std::vector<ReplicaLoad> uneven = {{"a", "", 10}, {"b", "", 6}};
  EXPECT_THAT(takeoverShare(lapsed, uneven, "b"), ElementsAre("m1", "m2", "m3", "m4", "m6", "m8"));
  EXPECT_THAT(takeoverShare(lapsed, uneven, "a"), ElementsAre("m5", "m7"));
  // A replica missing from the list (its heartbeat not read back yet) counts as serving none.
  EXPECT_THAT(takeoverShare({"x", "y"}, {{"a", "", 3}}, "new"), ElementsAre("x", "y"));
  EXPECT_THAT(takeoverShare({"x", "y"}, {{"a", "", 3}, {"new", "", 0}}, "a"), IsEmpty());
}

// Replica c dies holding six missions while a and b serve two each: a and b share c's missions (three each)
// instead of the first to look taking all six, and each is loaded once more.
TEST_F(ReplicaCoordinatorTest, TheMissionsOfADeadReplicaAreSharedOverTheLiveOnes) {
  ThreeReplicas r = threeReplicas();
  ASSERT_FALSE(HasFailure());
  auto& [a, b, c] = r;
  c.reset();  // dies: its threads stop, nothing is released
  lapse("replica/c");

  for (int i = 0; i < 300 && a->served().size() + b->served().size() < 10; ++i) {  // 15 s at most
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  a->waitForLoads();
  b->waitForLoads();
  const std::vector<std::string> on_a = a->served();
  const std::vector<std::string> on_b = b->served();
  std::printf("after c died: a serves %zu, b serves %zu\n", on_a.size(), on_b.size());
  EXPECT_EQ(on_a.size() + on_b.size(), 10U);
  EXPECT_EQ(on_a.size(), 5U);
  EXPECT_EQ(on_b.size(), 5U);
  for (const std::string& m : kOfC) {
    EXPECT_EQ(core_.loadsOf(m), 2) << m;  // once by c, once by its new owner
  }
  EXPECT_EQ(a->counters().taken_over + b->counters().taken_over, 6U);
}

// The agents of a dead replica all reconnect to the next replica in their lists. Their Hellos must not pull every
// mission there: a Hello for a lapsed mission is taken only where the share puts it, and the others are told to
// connect again while the share's replica takes them over.
TEST_F(ReplicaCoordinatorTest, HellosForADeadReplicasMissionsFollowTheShareNotTheReplicaTheyReach) {
  ThreeReplicas r = threeReplicas();
  ASSERT_FALSE(HasFailure());
  auto& [a, b, c] = r;
  c.reset();
  lapse("replica/c");  // then every agent of c says Hello to a at once
  int told_to_come_back = 0;
  for (const std::string& m : kOfC) {
    auto answer = a->claim(m);
    if (!answer.ok() && answer.error().message().find("between replicas") != std::string::npos) ++told_to_come_back;
  }
  for (int i = 0; i < 300 && a->served().size() + b->served().size() < 10; ++i) {  // 15 s at most
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  a->waitForLoads();
  b->waitForLoads();
  std::printf("Hellos at a: %d of 6 told to connect again; a serves %zu, b serves %zu\n", told_to_come_back,
              a->served().size(), b->served().size());
  EXPECT_EQ(a->served().size(), 5U);
  EXPECT_EQ(b->served().size(), 5U);
}

// A replica that shuts down cleanly removes its heartbeat and releases its missions: the others share them at
// their next look, without waiting for a TTL.
TEST_F(ReplicaCoordinatorTest, AReplicaThatLeavesCleanlyHasItsMissionsSharedAtOnce) {
  auto a = coordinator("replica/a", {}, kSharingTtlS);
  auto b = coordinator("replica/b", {}, kSharingTtlS);
  auto c = coordinator("replica/c", {}, kSharingTtlS);
  for (auto* r : {a.get(), b.get(), c.get()}) r->start();
  for (const char* m : {"c1", "c2", "c3", "c4"}) ASSERT_TRUE(claimServed(*c, m).ok());
  ASSERT_TRUE(c->release().ok());
  const auto released = std::chrono::steady_clock::now();
  while (a->served().size() + b->served().size() < 4 &&
         std::chrono::steady_clock::now() - released < std::chrono::seconds(5)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const double took_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - released).count();
  a->waitForLoads();
  b->waitForLoads();
  EXPECT_EQ(a->served().size(), 2U);
  EXPECT_EQ(b->served().size(), 2U);
  EXPECT_LT(took_s, kSharingTtlS) << "the released missions waited for a TTL";
}

}  // namespace
}  // namespace cvislam::server::cluster
