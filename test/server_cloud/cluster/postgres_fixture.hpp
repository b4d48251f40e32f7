// A real PostgreSQL for the scale-out tests (deploy/local_postgres.sh starts one for the test program; every test
// gets a database of its own), and helpers over it: leases and stores of named holders, lapses made in SQL so that
// no test waits for a TTL, and sample records.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "server_cloud/cluster/mission_leases.hpp"
#include "server_cloud/cluster/pg_connection.hpp"
#include "server_cloud/cluster/postgres_store.hpp"
#include "test/support/run_command.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server::cluster {

const std::filesystem::path kSource = CVISLAM_SOURCE_DIR;

// One PostgreSQL for the whole test program.
class PostgresEnvironment : public ::testing::Environment {
 public:
  static std::string& conninfo() {
    static std::string value;
    return value;
  }
  void SetUp() override {
    std::filesystem::permissions(dir_.path(), std::filesystem::perms::owner_all | std::filesystem::perms::group_read |
                                                  std::filesystem::perms::group_exec |
                                                  std::filesystem::perms::others_read |
                                                  std::filesystem::perms::others_exec);  // the postgres user's
    const auto run =
        test::runCommand((kSource / "deploy" / "local_postgres.sh").string(), "start " + (dir_.path() / "pg").string());
    ASSERT_EQ(run.exit_code, 0) << "deploy/local_postgres.sh start: " << run.output
                                << "(deploy/install_deps.sh installs postgresql-15)";
    std::string line = run.output.substr(0, run.output.find('\n'));
    conninfo() = line;
  }
  void TearDown() override {
    (void)test::runCommand((kSource / "deploy" / "local_postgres.sh").string(),
                           "stop " + (dir_.path() / "pg").string());
  }

 private:
  test::TempDir dir_;
};

class PostgresTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_FALSE(PostgresEnvironment::conninfo().empty()) << "no PostgreSQL";
    static int next = 0;
    const std::string db = "cluster_test_" + std::to_string(++next);
    auto admin = PgConnection::open(PostgresEnvironment::conninfo(), "test admin");
    ASSERT_TRUE(admin.ok()) << admin.error().toString();
    ASSERT_TRUE((*admin)->execScript("CREATE DATABASE " + db).ok());
    conninfo_ = PostgresEnvironment::conninfo();
    conninfo_.replace(conninfo_.find("dbname=postgres"), std::string("dbname=postgres").size(), "dbname=" + db);
  }

  std::unique_ptr<MissionLeases> leases(const std::string& holder, double ttl_s = 30.0) {
    LeaseOptions o;
    o.conninfo = conninfo_;
    o.holder = holder;
    o.address = "127.0.0.1:" + std::to_string(50000 + holder.back());
    o.ttl_s = ttl_s;
    auto opened = MissionLeases::open(o);
    EXPECT_TRUE(opened.ok()) << opened.error().toString();
    return opened.ok() ? std::move(opened).value() : nullptr;
  }
  std::unique_ptr<MapStore> store(const std::string& holder) {
    PostgresStoreOptions o;
    o.conninfo = conninfo_;
    o.holder = holder;
    auto opened = openPostgresStore(o);
    EXPECT_TRUE(opened.ok()) << opened.error().toString();
    return opened.ok() ? std::move(opened).value() : nullptr;
  }
  // Moves the lease of `mission` into the past, as if its holder had stopped renewing a TTL ago.
  void lapse(const std::string& mission) {
    auto c = PgConnection::open(conninfo_, "test");
    ASSERT_TRUE(c.ok());
    auto r = (*c)->exec("UPDATE cvislam_leases SET expires_at = now() - interval '1 second' WHERE mission = $1",
                        PgParams().text(mission));
    ASSERT_TRUE(r.ok()) << r.error().toString();
    ASSERT_EQ(r->affected(), 1);
  }
  static StoreRecord batch(const std::string& mission, AgentId agent, std::uint64_t sequence) {
    StoreRecord r;
    r.kind = StoreRecord::Kind::kBatch;
    r.mission = mission;
    r.agent = agent;
    r.sequence = sequence;
    r.body = "batch " + std::to_string(agent) + "/" + std::to_string(sequence) + std::string(1, '\0') + "binary";
    return r;
  }
  static std::vector<std::uint64_t> sequences(const MapStore& s, const std::string& mission) {
    std::vector<std::uint64_t> out;
    const Status replayed = s.replay(mission, [&](const StoreRecord& r) {
      out.push_back(r.sequence);
      return Status::Ok();
    });
    EXPECT_TRUE(replayed.ok()) << replayed.error().toString();
    return out;
  }

  std::string conninfo_;
};

}  // namespace cvislam::server::cluster
