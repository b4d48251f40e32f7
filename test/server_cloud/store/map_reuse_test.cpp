// Map reuse, driven without gRPC: a finished mission of one store is loaded into another server as a new mission.
// The map service's readers then serve the same map under the new name; the copy is durable in the loading
// server's store, so a restart neither loses nor doubles it; a load cut short goes on where it stopped; a new agent
// of the new mission joins beside the loaded ones; and a source without the mission is refused naming what it holds.
#include <memory>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.pb.h"
#include "cvislam/v1/map_service.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/maps/map_reader.hpp"
#include "server_cloud/store/sqlite_store.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/session_driver.hpp"
#include "test/server_cloud/store/faulty_stores.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using test::batchMessage;
using test::helloMessage;
using test::makeKeyframeBatch;
using ::testing::HasSubstr;

ServerOptions storeOptions(const std::filesystem::path& file) {
  ServerOptions o;
  o.store = file;
  o.store_sync = SqliteStoreOptions::Sync::kNormal;
  return o;
}

std::unique_ptr<MapStore> openSource(const std::filesystem::path& file) {
  SqliteStoreOptions o;
  o.path = file;
  o.create_if_missing = false;
  auto store = openSqliteStore(o);
  EXPECT_TRUE(store.ok()) << store.error().toString();
  return store.ok() ? std::move(store).value() : nullptr;
}

// The map listing of a mission, with its name taken out, to compare two missions' maps.
std::string mapsOf(const ServerCore& core, const std::string& mission) {
  v1::ListMapsResponse maps;
  const Status s = maps::listMaps(core.missions(), mission, maps);
  EXPECT_TRUE(s.ok()) << s.error().toString();
  maps.clear_mission();
  return maps.SerializeAsString();
}

class MapReuseTest : public ::testing::Test {
 protected:
  // Mission "day1" of two agents (7 and 3 keyframes), in the store day1.db, as a finished mission leaves it.
  void SetUp() override {
    auto core = std::make_unique<ServerCore>(storeOptions(dir_.path() / "day1.db"));
    ASSERT_TRUE(core->openStore().ok());
    for (std::uint32_t agent : {1U, 2U}) {
      auto session = core->openSession({});
      ASSERT_TRUE(test::sendTo(*session, helloMessage("day1", agent, 100 + agent)).ok());
      const std::uint32_t batches = agent == 1 ? 3 : 1;
      for (std::uint32_t b = 0; b < batches; ++b) {
        const std::uint32_t count = agent == 1 && b == 2 ? 3 : (agent == 1 ? 2 : 3);
        ASSERT_TRUE(test::sendTo(*session, batchMessage(makeKeyframeBatch(b + 1, 2 * b, count))).ok());
      }
      session->close(Status::Ok());
    }
    day1_maps_ = mapsOf(*core, "day1");
  }

  cvislam::test::TempDir dir_;
  std::string day1_maps_;
};

TEST_F(MapReuseTest, ALoadedMissionServesTheSameMapUnderItsNewName) {
  ServerCore core(storeOptions(dir_.path() / "day2.db"));
  ASSERT_TRUE(core.openStore().ok());
  auto source = openSource(dir_.path() / "day1.db");
  ASSERT_NE(source, nullptr);

  const auto loaded = core.loadMission(source.get(), "day1", "day2");

  ASSERT_TRUE(loaded.ok()) << loaded.error().toString();
  EXPECT_FALSE(loaded->already_held);
  EXPECT_EQ(loaded->hellos, 2U);
  EXPECT_EQ(loaded->batches, 4U);
  EXPECT_EQ(loaded->keyframes, 10U);
  EXPECT_EQ(core.missions().find("day1"), nullptr) << "only the new name is here";
  EXPECT_EQ(mapsOf(core, "day2"), day1_maps_);
  v1::GetTrajectoryResponse trajectory;
  ASSERT_TRUE(maps::getTrajectory(core.missions(), "day2", 1, trajectory).ok());
  EXPECT_EQ(trajectory.poses_size(), 7);
}

TEST_F(MapReuseTest, TheCopyIsDurableAndARestartNeitherLosesNorDoublesIt) {
  {
    ServerCore core(storeOptions(dir_.path() / "day2.db"));
    ASSERT_TRUE(core.openStore().ok());
    auto source = openSource(dir_.path() / "day1.db");
    ASSERT_TRUE(core.loadMission(source.get(), "day1", "day2").ok());
  }
  ServerCore restarted(storeOptions(dir_.path() / "day2.db"));
  const auto replayed = restarted.openStore();
  ASSERT_TRUE(replayed.ok()) << replayed.error().toString();
  EXPECT_EQ(replayed->keyframes, 10U) << "the copy was in the loading server's own store";
  auto source = openSource(dir_.path() / "day1.db");
  const auto again = restarted.loadMission(source.get(), "day1", "day2");  // the same command line again
  ASSERT_TRUE(again.ok()) << again.error().toString();
  EXPECT_TRUE(again->already_held);
  EXPECT_EQ(mapsOf(restarted, "day2"), day1_maps_);
}

TEST_F(MapReuseTest, ALoadCutShortGoesOnWhereItStopped) {
  {
    // What a crash after three of the six records leaves in the loading server's store.
    SqliteStoreOptions o;
    o.path = dir_.path() / "day2.db";
    auto partial = openSqliteStore(o);
    ASSERT_TRUE(partial.ok());
    auto source = openSource(dir_.path() / "day1.db");
    int copied = 0;
    ASSERT_TRUE(source
                    ->replay("day1",
                             [&](const StoreRecord& r) -> Status {
                               if (copied++ >= 3) return Status::Ok();
                               StoreRecord copy = r;
                               copy.mission = "day2";
                               if (copy.kind == StoreRecord::Kind::kHello) {
                                 v1::Hello hello;
                                 if (!hello.ParseFromString(copy.body)) {
                                   return Error{ErrorCode::kDataError, "the Hello does not parse"};
                                 }
                                 hello.set_mission("day2");
                                 copy.body = hello.SerializeAsString();
                               }
                               return (*partial)->append(copy);
                             })
                    .ok());
  }
  ServerCore core(storeOptions(dir_.path() / "day2.db"));
  ASSERT_TRUE(core.openStore().ok());
  auto source = openSource(dir_.path() / "day1.db");
  const auto loaded = core.loadMission(source.get(), "day1", "day2");
  ASSERT_TRUE(loaded.ok()) << loaded.error().toString();
  EXPECT_FALSE(loaded->already_held);
  EXPECT_EQ(loaded->hellos + loaded->batches, 3U) << "the three records the first load did not store";
  EXPECT_EQ(mapsOf(core, "day2"), day1_maps_);
}

TEST_F(MapReuseTest, ANewAgentJoinsTheLoadedMissionBesideItsAgents) {
  ServerCore core(storeOptions(dir_.path() / "day2.db"));
  ASSERT_TRUE(core.openStore().ok());
  auto source = openSource(dir_.path() / "day1.db");
  ASSERT_TRUE(core.loadMission(source.get(), "day1", "day2").ok());

  auto newcomer = core.openSession({});
  ASSERT_TRUE(test::sendTo(*newcomer, helloMessage("day2", 5, 555)).ok());
  ASSERT_TRUE(test::sendTo(*newcomer, batchMessage(makeKeyframeBatch(1, 0, 2))).ok());
  auto impostor = core.openSession({});
  const Status taken = test::sendTo(*impostor, helloMessage("day2", 1, 556));

  EXPECT_EQ(core.missions().find("day2")->agent(5)->read()->keyframes.size(), 2U);
  ASSERT_FALSE(taken.ok()) << "a new process took a loaded agent's id";
  EXPECT_EQ(taken.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(taken.error().message(), HasSubstr("another --agent-id"));
}

// A name the replay would refuse is refused before anything is written: the store still opens afterwards.
TEST_F(MapReuseTest, ALoadUnderAnInvalidNameWritesNothingAndTheStoreStillOpens) {
  for (const std::string& bad : {std::string("a/b"), std::string("x y"), std::string(".."), std::string(200, 'm')}) {
    SCOPED_TRACE(bad);
    {
      ServerCore core(storeOptions(dir_.path() / "day2.db"));
      ASSERT_TRUE(core.openStore().ok());
      auto source = openSource(dir_.path() / "day1.db");
      const auto loaded = core.loadMission(source.get(), "day1", bad);
      ASSERT_FALSE(loaded.ok());
      EXPECT_EQ(loaded.error().code(), ErrorCode::kInvalidArgument);
      EXPECT_EQ(core.store()->counters().records, 0U);
    }
    ServerCore restarted(storeOptions(dir_.path() / "day2.db"));
    const auto replayed = restarted.openStore();
    ASSERT_TRUE(replayed.ok()) << replayed.error().toString();
    EXPECT_EQ(replayed->batches, 0U);
  }
}

// The disk fills during a load: the load stops with an error that says what it was storing, and a later start
// with space goes on where it stopped (ALoadCutShortGoesOnWhereItStopped).
TEST_F(MapReuseTest, ALoadWhoseStoreRefusesRecordsStopsSayingWhatItWasStoring) {
  class FullStore final : public test::ForwardingStore {
   public:
    using ForwardingStore::ForwardingStore;
    Status append(const StoreRecord& r) override {
      if (++appends > 2) return Error{ErrorCode::kIoError, "database or disk is full"};
      return ForwardingStore::append(r);
    }
    int appends = 0;
  };
  SqliteStoreOptions o;
  o.path = dir_.path() / "day2.db";
  auto sqlite = openSqliteStore(o);
  ASSERT_TRUE(sqlite.ok());
  ServerCore core(ServerOptions{});
  ASSERT_TRUE(core.attachStore(std::make_unique<FullStore>(std::move(sqlite).value())).ok());
  auto source = openSource(dir_.path() / "day1.db");

  const auto loaded = core.loadMission(source.get(), "day1", "day2");

  ASSERT_FALSE(loaded.ok());
  EXPECT_EQ(loaded.error().code(), ErrorCode::kIoError);
  EXPECT_THAT(loaded.error().message(), HasSubstr("storing mission 'day2' (loaded from 'day1')"));
  EXPECT_THAT(loaded.error().message(), HasSubstr("disk is full"));
  EXPECT_EQ(core.store()->counters().records, 2U);
}

TEST_F(MapReuseTest, ASourceWithoutTheMissionIsRefusedNamingWhatItHolds) {
  ServerCore core(storeOptions(dir_.path() / "day2.db"));
  ASSERT_TRUE(core.openStore().ok());
  auto source = openSource(dir_.path() / "day1.db");
  const auto missing = core.loadMission(source.get(), "day0", "day2");
  const auto itself = core.loadMission(source.get(), "day1", "day1");
  ServerCore storeless(ServerOptions{});
  const auto nowhere = storeless.loadMission(nullptr, "day1", "day2");

  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(missing.error().message(), HasSubstr("holds no mission 'day0' (it holds: day1)"));
  EXPECT_EQ(core.missions().find("day2"), nullptr);
  ASSERT_FALSE(itself.ok());
  ASSERT_FALSE(nowhere.ok());
  EXPECT_THAT(nowhere.error().message(), HasSubstr("--load-from"));
}

}  // namespace
}  // namespace cvislam::server
