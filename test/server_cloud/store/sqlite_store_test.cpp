// The embedded map store on real files: records come back in order with their fields, a batch is stored at most
// once, the store survives being closed, and every damaged or foreign file is refused at open or at replay with
// an error that names it (never a crash, never a store silently made anew).
#include "server_cloud/store/sqlite_store.hpp"

#include <sqlite3.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gmock/gmock.h>

#include <gtest/gtest.h>

#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using ::testing::HasSubstr;

StoreRecord batchRecord(const std::string& mission, AgentId agent, std::uint64_t sequence, std::size_t body_bytes) {
  std::string body(body_bytes, '\0');
  for (std::size_t i = 0; i < body.size(); ++i) body[i] = static_cast<char>((i * 31 + sequence * 7 + agent) & 0xFF);
  return StoreRecord{0, StoreRecord::Kind::kBatch, mission, agent, sequence, body};
}

class SqliteStoreTest : public ::testing::Test {
 protected:
  SqliteStoreOptions options() const {
    SqliteStoreOptions o;
    o.path = dir_ / "maps.db";
    o.sync = SqliteStoreOptions::Sync::kNormal;
    return o;
  }
  std::unique_ptr<MapStore> open() {
    auto store = openSqliteStore(options());
    EXPECT_TRUE(store.ok()) << store.error().toString();
    return store.ok() ? std::move(store).value() : nullptr;
  }
  std::vector<StoreRecord> all(const MapStore& store, const std::string& mission = "") {
    std::vector<StoreRecord> out;
    const Status s = store.replay(mission, [&](const StoreRecord& r) {
      out.push_back(r);
      return Status::Ok();
    });
    EXPECT_TRUE(s.ok()) << s.error().toString();
    return out;
  }
  // Runs SQL on the closed store's file, as a tool or a bug might.
  void tamper(const std::string& sql) {
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(options().path.c_str(), &db), SQLITE_OK);
    char* message = nullptr;
    const int rc = sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &message);
    EXPECT_EQ(rc, SQLITE_OK) << (message != nullptr ? message : "");
    sqlite3_free(message);
    sqlite3_close(db);
  }

  test::TempDir dir_;
};

TEST_F(SqliteStoreTest, RecordsComeBackInTheOrderAppendedWithEveryFieldPerMissionOrAll) {
  auto store = open();
  ASSERT_NE(store, nullptr);
  ASSERT_TRUE(store->append({0, StoreRecord::Kind::kHello, "hall", 3, 0, "hello-3"}).ok());
  ASSERT_TRUE(store->append(batchRecord("hall", 3, 1, 1000)).ok());
  ASSERT_TRUE(store->append(batchRecord("yard", 1, 1, 10)).ok());
  ASSERT_TRUE(store->append(batchRecord("hall", 3, 2, 0)).ok());

  const auto records = all(*store);
  ASSERT_EQ(records.size(), 4U);
  EXPECT_EQ(records[0].kind, StoreRecord::Kind::kHello);
  EXPECT_EQ(records[0].body, "hello-3");
  EXPECT_EQ(records[1].body, batchRecord("hall", 3, 1, 1000).body);
  EXPECT_EQ(records[2].mission, "yard");
  EXPECT_EQ(records[3].sequence, 2U);
  EXPECT_TRUE(records[3].body.empty());
  for (std::size_t i = 1; i < records.size(); ++i) EXPECT_GT(records[i].number, records[i - 1].number);

  const auto hall = all(*store, "hall");
  ASSERT_EQ(hall.size(), 3U);
  EXPECT_EQ(hall[2].sequence, 2U);
  EXPECT_EQ(*store->missions(), (std::vector<std::string>{"hall", "yard"}));
  EXPECT_EQ(store->counters().records, 4U);
  EXPECT_EQ(store->counters().bytes, 7U + 1000U + 10U);
}

TEST_F(SqliteStoreTest, ABatchIsStoredAtMostOnceAndHellosAsOftenAsTheyCome) {
  auto store = open();
  ASSERT_TRUE(store->append(batchRecord("hall", 3, 1, 10)).ok());
  const Status again = store->append(batchRecord("hall", 3, 1, 20));
  ASSERT_FALSE(again.ok());
  EXPECT_EQ(again.error().code(), ErrorCode::kAlreadyExists);
  EXPECT_THAT(again.error().message(), HasSubstr("batch 1 of agent 3 of mission 'hall'"));
  EXPECT_TRUE(store->append(batchRecord("hall", 4, 1, 10)).ok());  // another agent's batch 1
  EXPECT_TRUE(store->append({0, StoreRecord::Kind::kHello, "hall", 3, 0, "a"}).ok());
  EXPECT_TRUE(store->append({0, StoreRecord::Kind::kHello, "hall", 3, 0, "b"}).ok());
  EXPECT_EQ(all(*store).size(), 4U);
  EXPECT_EQ(all(*store)[0].body.size(), 10U);  // the first one, unchanged
}

TEST_F(SqliteStoreTest, WhatWasAppendedIsThereAfterTheStoreIsClosedAndOpenedAgain) {
  {
    auto store = open();
    for (std::uint64_t s = 1; s <= 50; ++s) ASSERT_TRUE(store->append(batchRecord("hall", 0, s, 3000)).ok());
  }
  auto store = open();
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(store->counters().records, 50U);
  const auto records = all(*store);
  ASSERT_EQ(records.size(), 50U);
  EXPECT_EQ(records[49].body, batchRecord("hall", 0, 50, 3000).body);
  EXPECT_TRUE(store->append(batchRecord("hall", 0, 51, 10)).ok());
  EXPECT_FALSE(store->append(batchRecord("hall", 0, 50, 10)).ok());
}

TEST_F(SqliteStoreTest, ASecondProcessOrHandleOnTheSameFileIsRefusedWhileTheFirstHoldsIt) {
  auto first = open();
  ASSERT_NE(first, nullptr);
  auto second = openSqliteStore(options());
  ASSERT_FALSE(second.ok());
  EXPECT_THAT(second.error().message(), HasSubstr("another cvislam_server"));
  EXPECT_THAT(second.error().message(), HasSubstr(options().path.string()));
}

TEST_F(SqliteStoreTest, AnEmptyFileIsRefusedRatherThanSilentlyMadeIntoANewStore) {
  test::writeTextFile(options().path, "");
  auto store = openSqliteStore(options());
  ASSERT_FALSE(store.ok());
  EXPECT_THAT(store.error().message(), HasSubstr("is not a cvislam map store"));
  EXPECT_EQ(std::filesystem::file_size(options().path), 0U);  // left as it was
}

TEST_F(SqliteStoreTest, AFileThatIsNotSqliteIsRefusedNamingIt) {
  test::writeTextFile(options().path, std::string(8192, 'x'));
  auto store = openSqliteStore(options());
  ASSERT_FALSE(store.ok());
  EXPECT_THAT(store.error().message(), HasSubstr(options().path.string()));
  EXPECT_THAT(store.error().message(), HasSubstr("not a readable SQLite file"));
}

TEST_F(SqliteStoreTest, AnotherSqliteDatabaseIsRefusedAsNotAStore) {
  tamper("CREATE TABLE other (x INTEGER)");
  auto store = openSqliteStore(options());
  ASSERT_FALSE(store.ok());
  EXPECT_THAT(store.error().message(), HasSubstr("is not a cvislam map store"));
}

TEST_F(SqliteStoreTest, AStoreOfAnotherSchemaVersionIsRefusedNamingBothVersions) {
  { open(); }
  tamper("UPDATE meta SET value = '7' WHERE key = 'schema'");
  auto store = openSqliteStore(options());
  ASSERT_FALSE(store.ok());
  EXPECT_EQ(store.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(store.error().message(), HasSubstr("schema version 7"));
  EXPECT_THAT(store.error().message(), HasSubstr("reads version " + std::to_string(kStoreSchemaVersion)));
}

TEST_F(SqliteStoreTest, ARecordWhoseBodyChangedFailsItsChecksumAtReplayNamingTheRecord) {
  {
    auto store = open();
    for (std::uint64_t s = 1; s <= 3; ++s) ASSERT_TRUE(store->append(batchRecord("hall", 2, s, 100)).ok());
  }
  tamper("UPDATE records SET body = zeroblob(100) WHERE sequence = 2");
  auto store = open();
  ASSERT_NE(store, nullptr);
  int visited = 0;
  const Status s = store->replay("", [&](const StoreRecord&) {
    ++visited;
    return Status::Ok();
  });
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(visited, 1);  // the first record, then the damaged one stops the replay
  EXPECT_THAT(s.error().message(), HasSubstr("record 2 (batch 2 of agent 2, mission 'hall') fails its checksum"));
}

TEST_F(SqliteStoreTest, ARecordMovedToAnotherAgentFailsItsChecksumToo) {
  {
    auto store = open();
    ASSERT_TRUE(store->append(batchRecord("hall", 2, 1, 100)).ok());
  }
  tamper("UPDATE records SET agent = 5");
  auto store = open();
  const Status s = store->replay("", [](const StoreRecord&) { return Status::Ok(); });
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.error().message(), HasSubstr("fails its checksum"));
}

TEST_F(SqliteStoreTest, ATruncatedStoreIsRefusedAtOpenOrReplayAndNeverCrashes) {
  {
    auto store = open();
    for (std::uint64_t s = 1; s <= 200; ++s) ASSERT_TRUE(store->append(batchRecord("hall", 1, s, 4000)).ok());
  }
  // Fold the WAL into the main file, so that truncating the file cuts records.
  tamper("PRAGMA wal_checkpoint(TRUNCATE)");
  const auto size = std::filesystem::file_size(options().path);
  ASSERT_GT(size, 200U * 4000U);
  for (const double keep : {0.5, 0.9, 0.01}) {
    SCOPED_TRACE(keep);
    std::filesystem::copy_file(options().path, dir_ / "whole.db", std::filesystem::copy_options::overwrite_existing);
    std::filesystem::resize_file(options().path, static_cast<std::uintmax_t>(static_cast<double>(size) * keep));
    auto store = openSqliteStore(options());
    std::string error;
    if (!store.ok()) {
      error = store.error().message();
    } else {
      const Status s = (*store)->replay("", [](const StoreRecord&) { return Status::Ok(); });
      ASSERT_FALSE(s.ok()) << "a store cut to " << keep << " of its size replayed without an error";
      error = s.error().message();
    }
    EXPECT_THAT(error, HasSubstr(options().path.string()));
    store = Error{ErrorCode::kInternal, "closed"};
    std::filesystem::copy_file(dir_ / "whole.db", options().path, std::filesystem::copy_options::overwrite_existing);
  }
}

TEST_F(SqliteStoreTest, AMissingStoreIsMadeUnlessCreationIsOff) {
  auto o = options();
  o.path = dir_ / "sub" / "new.db";
  o.create_if_missing = false;
  auto refused = openSqliteStore(o);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code(), ErrorCode::kNotFound);
  o.create_if_missing = true;
  auto made = openSqliteStore(o);
  ASSERT_TRUE(made.ok()) << made.error().toString();
  EXPECT_TRUE(std::filesystem::exists(o.path));
  EXPECT_THAT((*made)->describe(), HasSubstr("synchronous=normal"));
}

TEST(StoreSyncTest, NamesParseAndAnUnknownOneIsNamed) {
  EXPECT_EQ(*parseStoreSync("full"), SqliteStoreOptions::Sync::kFull);
  EXPECT_EQ(*parseStoreSync("normal"), SqliteStoreOptions::Sync::kNormal);
  EXPECT_EQ(*parseStoreSync("off"), SqliteStoreOptions::Sync::kOff);
  auto bad = parseStoreSync("sometimes");
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.error().message(), HasSubstr("'sometimes' is not one of full, normal, off"));
}

}  // namespace
}  // namespace cvislam::server
