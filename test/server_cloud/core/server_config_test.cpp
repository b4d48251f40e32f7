// The server's config files as shipped: deploy/server_config.yaml documents the defaults, and the cluster's
// deploy/k8s/base/server.yaml and overlays/scaleout/server.yaml must load (unknown keys are refused) with the paths
// the StatefulSet mounts.
#include <filesystem>
#include <fstream>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "server_cloud/core/server_core.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using ::testing::HasSubstr;

const std::filesystem::path kSource = CVISLAM_SOURCE_DIR;

TEST(ServerConfigFiles, TheDocumentedConfigHoldsExactlyTheDefaults) {
  ServerOptions loaded;
  const Status s = loadServerConfig(kSource / "deploy" / "server_config.yaml", loaded);
  ASSERT_TRUE(s.ok()) << s.error().toString();
  EXPECT_EQ(loaded.describe(), ServerOptions{}.describe());
}

// Off loopback a server needs TLS and tokens, or the operator's word (--insecure) that the network is trusted.
TEST(ServerOptionsTest, AReachableAddressWithoutTlsOrTokensIsRefusedUnlessInsecure) {
  ServerOptions o;
  o.listen = "0.0.0.0:50051";
  const Status open = o.validate();
  ASSERT_FALSE(open.ok());
  EXPECT_THAT(open.error().message(), HasSubstr("without TLS and tokens"));
  EXPECT_THAT(open.error().message(), HasSubstr("--insecure"));
  o.tls_certificate = "server.crt";
  o.tls_private_key = "server.key";
  const Status tls_only = o.validate();
  ASSERT_FALSE(tls_only.ok());
  EXPECT_THAT(tls_only.error().message(), HasSubstr("without tokens"));
  o.tokens_file = "tokens";
  EXPECT_TRUE(o.validate().ok());

  ServerOptions insecure;
  insecure.listen = "10.0.0.7:50051";
  insecure.insecure = true;
  EXPECT_TRUE(insecure.validate().ok());
  EXPECT_THAT(insecure.describe(), HasSubstr("--insecure: reachable from other machines"));
  for (const char* loopback : {"127.0.0.1:0", "127.1.2.3:50051", "localhost:50051", "[::1]:50051"}) {
    ServerOptions local;
    local.listen = loopback;
    EXPECT_TRUE(local.validate().ok()) << loopback;
  }
}

TEST(ServerConfigFiles, TheClusterConfigLoadsWithThePathsTheStatefulSetMounts) {
  ServerOptions o;
  const Status s = loadServerConfig(kSource / "deploy" / "k8s" / "base" / "server.yaml", o);
  ASSERT_TRUE(s.ok()) << s.error().toString();
  ASSERT_TRUE(o.validate().ok()) << o.validate().error().toString();
  EXPECT_EQ(o.listen, "0.0.0.0:50051");
  EXPECT_EQ(o.health_listen, "0.0.0.0:50052");
  EXPECT_EQ(o.store, "/var/lib/cvislam/store.db");          // the StatefulSet's volumeClaimTemplate "store"
  EXPECT_EQ(o.tokens_file, "/etc/cvislam/secrets/tokens");  // the Secret's keys, mounted there
  EXPECT_EQ(o.tls_certificate, "/etc/cvislam/secrets/tls.crt");
  EXPECT_EQ(o.tls_private_key, "/etc/cvislam/secrets/tls.key");
}

TEST(ServerConfigFiles, TheScaleOutConfigLoadsAndNeedsTheAddressThePodGives) {
  ServerOptions o;
  const Status s = loadServerConfig(kSource / "deploy" / "k8s" / "overlays" / "scaleout" / "server.yaml", o);
  ASSERT_TRUE(s.ok()) << s.error().toString();
  EXPECT_TRUE(o.cluster.enabled());  // PG* variables from the pod fill in the rest of the connection
  EXPECT_TRUE(o.store.empty());      // the store is PostgreSQL: no file, no volume per replica
  EXPECT_EQ(o.tls_certificate, "/etc/cvislam/secrets/tls.crt");
  // Listening on 0.0.0.0, a replica cannot tell the others where it is: server-replicas.yaml passes --advertise.
  const Status without = o.validate();
  ASSERT_FALSE(without.ok());
  EXPECT_THAT(without.error().message(), HasSubstr("advertise"));
  o.cluster.advertise = "cvislam-server-1.cvislam-server-headless.cvislam.svc:50051";
  EXPECT_TRUE(o.validate().ok()) << o.validate().error().toString();
}

// Writes `text` as a config file and loads it into `o`.
Status loadConfigText(const std::string& text, ServerOptions& o) {
  cvislam::test::TempDir dir;
  std::ofstream(dir.path() / "config.yaml") << text;
  return loadServerConfig(dir.path() / "config.yaml", o);
}

TEST(ServerConfigFiles, AnUnknownKeyIsRefusedNamingIt) {
  ServerOptions o;
  const Status s = loadConfigText("server:\n  listen: 0.0.0.0:1\n  health_port: 50052\n", o);
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.error().message(), HasSubstr("health_port"));
}

TEST(ServerConfigFiles, AnUnknownGbaSolverIsRefusedNamingTheKeyAndTheChoices) {
  ServerOptions o;
  const Status s = loadConfigText("backend:\n  gba_solver: dense\n", o);
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.error().toString(), HasSubstr("backend.gba_solver"));
  EXPECT_THAT(s.error().toString(), HasSubstr("schur or ceres"));
  ASSERT_TRUE(loadConfigText("backend:\n  gba_solver: ceres\n", o).ok());
  EXPECT_EQ(o.backend.gba.solver, backend::GlobalBaOptions::Solver::kCeres);
}

TEST(ServerConfigFiles, ALoopsGbaWindowIsReadAndANegativeBoundIsRefusedNamingTheKey) {
  ServerOptions o;
  ASSERT_TRUE(loadConfigText("backend:\n  loop_window_move_m: 0.02\n  loop_window_move_deg: 0.3\n", o).ok());
  EXPECT_EQ(o.backend.loop_window_move_m, 0.02);
  EXPECT_EQ(o.backend.loop_window_move_deg, 0.3);
  ASSERT_TRUE(loadConfigText("backend:\n  loop_window_move_m: -0.01\n", o).ok());
  const Status s = o.validate();
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.error().toString(), HasSubstr("backend.loop_window_move_m"));
}

}  // namespace
}  // namespace cvislam::server
