// Access over real loopback gRPC: a server with a tokens file, limits and (in the second fixture) TLS from a
// throwaway certificate that the test makes with openssl. Each mission's token opens that mission only, on the
// map service, the monitor and the agent link alike; calls without it, or with another mission's, end
// UNAUTHENTICATED; listings show only what the token opens; limits end RESOURCE_EXHAUSTED with the limit named.
// Over TLS, the agent link, cvislam_mapctl and the Python client work with the CA, and a plaintext client does not.
#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>

#include <grpcpp/grpcpp.h>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.grpc.pb.h"
#include "cvislam/v1/map_service.grpc.pb.h"
#include "cvislam/v1/monitor.grpc.pb.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/service/grpc_server.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/maps/example_maps.hpp"
#include "test/support/run_command.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using ::testing::HasSubstr;

const std::string kTokenSurvey = "survey-token-5f0c2a9e";
const std::string kTokenDepot = "depot-token-77b1c4d2";
const std::string kOperator = "operator-token-c0ffee11";
const std::string kTokenQuiet = "quiet-token-3a9d0e61";  // a mission declared, with nothing in it yet

std::unique_ptr<grpc::ClientContext> callContext(const std::string& token) {
  auto c = std::make_unique<grpc::ClientContext>();
  c->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
  if (!token.empty()) c->AddMetadata("authorization", "Bearer " + token);
  return c;
}

std::string readFile(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

// The Hello on a new stream presenting `token`: the Welcome's status (OK when one came).
grpc::Status hello(const std::shared_ptr<grpc::Channel>& channel, const std::string& mission, std::uint32_t agent,
                   const std::string& token) {
  auto stub = v1::AgentLink::NewStub(channel);
  auto context = callContext(token);
  auto stream = stub->Connect(context.get());
  stream->Write(test::helloMessage(mission, agent, 0x5e55'0000U + agent));
  v1::ServerDownlink down;
  if (stream->Read(&down) && down.has_welcome()) {
    stream->WritesDone();
    while (stream->Read(&down)) {
    }
    (void)stream->Finish();
    return grpc::Status::OK;
  }
  return stream->Finish();
}

class AccessTest : public ::testing::Test {
 protected:
  // Two missions, "survey" (the example maps) and "depot" (an agent's Hello), each with its token; the clients'
  // channel with `credentials` (plaintext when none).
  void start(ServerOptions options = {}, const std::shared_ptr<grpc::ChannelCredentials>& credentials = nullptr) {
    options.listen = "127.0.0.1:0";
    options.tokens_file = dir_.path() / "tokens";
    std::ofstream(options.tokens_file) << "survey " << kTokenSurvey << "\ndepot " << kTokenDepot << "\nquiet "
                                       << kTokenQuiet << "\n* " << kOperator << "\n";
    core_ = std::make_unique<ServerCore>(options);
    ASSERT_TRUE(core_->loadTokens().ok());
    cvislam::test::ExampleMissionOptions example;
    example.keyframes_per_agent = 10;
    cvislam::test::fillExampleMission(core_->missions(), example);
    auto started = GrpcServer::start(*core_);
    ASSERT_TRUE(started.ok()) << started.error().toString();
    server_ = std::move(started).value();
    channel_ = grpc::CreateChannel(server_->address(), credentials ? credentials : grpc::InsecureChannelCredentials());
    ASSERT_TRUE(hello(channel_, "depot", 1, kTokenDepot).ok());
    maps_ = v1::MapService::NewStub(channel_);
  }
  void TearDown() override {
    if (server_) server_->shutdown(std::chrono::milliseconds(500));
  }

  grpc::Status listMaps(const std::string& mission, const std::string& token) {
    v1::ListMapsRequest request;
    request.set_mission(mission);
    v1::ListMapsResponse response;
    return maps_->ListMaps(callContext(token).get(), request, &response);
  }
  cvislam::test::TempDir dir_;
  std::unique_ptr<ServerCore> core_;
  std::unique_ptr<GrpcServer> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::MapService::Stub> maps_;
};

TEST_F(AccessTest, EveryMapServiceCallNeedsItsMissionsToken) {
  start();
  for (const std::string& token : {std::string(), kTokenDepot, std::string("not-a-token-at-all-000")}) {
    SCOPED_TRACE("token '" + token + "'");
    const grpc::Status maps = listMaps("survey", token);
    EXPECT_EQ(maps.error_code(), grpc::StatusCode::UNAUTHENTICATED) << maps.error_message();

    v1::GetMapRequest get;
    get.set_mission("survey");
    auto get_context = callContext(token);
    auto get_reader = maps_->GetMap(get_context.get(), get);
    v1::MapChunk chunk;
    EXPECT_FALSE(get_reader->Read(&chunk)) << "a chunk of survey reached a caller without its token";
    EXPECT_EQ(get_reader->Finish().error_code(), grpc::StatusCode::UNAUTHENTICATED);

    v1::GetTrajectoryRequest trajectory;
    trajectory.set_mission("survey");
    trajectory.set_agent(1);
    v1::GetTrajectoryResponse poses;
    EXPECT_EQ(maps_->GetTrajectory(callContext(token).get(), trajectory, &poses).error_code(),
              grpc::StatusCode::UNAUTHENTICATED);
    EXPECT_EQ(poses.poses_size(), 0);

    v1::ExportMapRequest exported;
    exported.set_mission("survey");
    auto export_context = callContext(token);
    auto export_reader = maps_->ExportMap(export_context.get(), exported);
    v1::ExportChunk file;
    EXPECT_FALSE(export_reader->Read(&file));
    EXPECT_EQ(export_reader->Finish().error_code(), grpc::StatusCode::UNAUTHENTICATED);

    v1::WatchMissionRequest watch;
    watch.set_mission("survey");
    watch.set_from_event(1);
    auto watch_context = callContext(token);
    auto watch_reader = maps_->WatchMission(watch_context.get(), watch);
    v1::WatchMissionResponse events;
    EXPECT_FALSE(watch_reader->Read(&events));
    EXPECT_EQ(watch_reader->Finish().error_code(), grpc::StatusCode::UNAUTHENTICATED);

    v1::GetStatsRequest stats_request;
    stats_request.set_mission("survey");
    v1::ServerStats stats;
    EXPECT_EQ(v1::Monitor::NewStub(channel_)->GetStats(callContext(token).get(), stats_request, &stats).error_code(),
              grpc::StatusCode::UNAUTHENTICATED);
  }
  const grpc::Status wrong = listMaps("survey", kTokenDepot);
  EXPECT_THAT(wrong.error_message(), HasSubstr("does not open mission 'survey'"));
  EXPECT_THAT(wrong.error_message(), ::testing::Not(HasSubstr(kTokenSurvey)));
  EXPECT_TRUE(listMaps("survey", kTokenSurvey).ok());
  EXPECT_TRUE(listMaps("survey", kOperator).ok());
  EXPECT_TRUE(listMaps("depot", kTokenDepot).ok());
}

TEST_F(AccessTest, ListingsShowOnlyTheMissionsTheTokenOpens) {
  start();
  const auto list = [&](const std::string& token) {
    v1::ListMissionsResponse response;
    const grpc::Status s = maps_->ListMissions(callContext(token).get(), {}, &response);
    EXPECT_TRUE(s.ok()) << s.error_message();
    std::string names;
    for (const auto& m : response.missions()) names += m.name() + " ";
    return names;
  };
  const auto stats = [&](const std::string& token) {
    v1::ServerStats out;
    const grpc::Status s = v1::Monitor::NewStub(channel_)->GetStats(callContext(token).get(), {}, &out);
    EXPECT_TRUE(s.ok()) << s.error_message();
    std::string missions;
    for (const auto& a : out.agents()) missions += a.mission() + " ";
    return missions;
  };
  EXPECT_EQ(list(kTokenSurvey), "survey ");
  EXPECT_EQ(list(kTokenDepot), "depot ");
  EXPECT_EQ(list(kOperator), "depot survey ");
  v1::ListMissionsResponse anonymous;
  EXPECT_EQ(maps_->ListMissions(callContext("").get(), {}, &anonymous).error_code(), grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_EQ(maps_->ListMissions(callContext("made-up-token-0000").get(), {}, &anonymous).error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_EQ(stats(kTokenDepot), "depot ");
  EXPECT_THAT(stats(kOperator), HasSubstr("survey"));
  // Health stays open: probes carry no token.
  grpc::health::v1::HealthCheckResponse health;
  EXPECT_TRUE(grpc::health::v1::Health::NewStub(channel_)->Check(callContext("").get(), {}, &health).ok());
}

TEST_F(AccessTest, AnAgentWritesOnlyToTheMissionItsTokenOpens) {
  start();
  const grpc::Status none = hello(channel_, "depot", 2, "");
  const grpc::Status other = hello(channel_, "depot", 2, kTokenSurvey);
  const grpc::Status unlisted = hello(channel_, "elsewhere", 2, kTokenDepot);
  EXPECT_EQ(none.error_code(), grpc::StatusCode::UNAUTHENTICATED) << none.error_message();
  EXPECT_EQ(other.error_code(), grpc::StatusCode::UNAUTHENTICATED) << other.error_message();
  EXPECT_EQ(unlisted.error_code(), grpc::StatusCode::UNAUTHENTICATED) << unlisted.error_message();
  EXPECT_THAT(none.error_message(), HasSubstr("authorization: Bearer"));
  EXPECT_EQ(core_->missions().find("depot")->findAgent(2), nullptr);
  EXPECT_EQ(core_->missions().find("elsewhere"), nullptr);
  EXPECT_TRUE(hello(channel_, "depot", 2, kTokenDepot).ok());
}

TEST_F(AccessTest, LimitsEndCallsWithResourceExhaustedNamingTheLimit) {
  ServerOptions options;
  options.session.max_agents_per_mission = 2;
  options.session.max_missions = 2;  // survey and depot
  options.rate_limit.rate_per_s = 1.0;
  options.rate_limit.burst = 8.0;
  start(options);  // one agent stream of depot so far (one request)

  ASSERT_TRUE(hello(channel_, "depot", 2, kTokenDepot).ok());
  const grpc::Status third_agent = hello(channel_, "depot", 3, kTokenDepot);
  EXPECT_EQ(third_agent.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(third_agent.error_message(), HasSubstr("limits.max_agents_per_mission"));
  // A third mission, even for the operator.
  const grpc::Status third_mission = hello(channel_, "spare", 1, kOperator);
  EXPECT_EQ(third_mission.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(third_mission.error_message(), HasSubstr("limits.max_missions"));

  // The depot client's bucket (its streams counted on its address before their Hellos); the survey client has a
  // bucket of its own.
  int refused = 0;
  grpc::Status last;
  for (int i = 0; i < 12; ++i) {
    const grpc::Status s = listMaps("depot", kTokenDepot);
    if (!s.ok()) {
      ++refused;
      last = s;
    }
  }
  EXPECT_GE(refused, 3);
  EXPECT_EQ(last.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(last.error_message(), HasSubstr("ListMaps refused: client ipv4:127.0.0.1 (token #"));
  EXPECT_THAT(last.error_message(), HasSubstr("limits.requests_per_s"));
  EXPECT_TRUE(listMaps("survey", kTokenSurvey).ok());
}

// Tokens made up one after another from one address share that address's bucket: they neither get a full bucket
// each nor take anything from a genuine client's.
TEST_F(AccessTest, MadeUpTokensFromOneAddressShareOneRateLimit) {
  ServerOptions options;
  options.rate_limit.rate_per_s = 1.0;
  options.rate_limit.burst = 8.0;
  start(options);
  int unauthenticated = 0;
  int limited = 0;
  grpc::Status last;
  for (int i = 0; i < 30; ++i) {
    const grpc::Status s = listMaps("survey", "made-up-token-" + std::to_string(1000 + i));
    unauthenticated += s.error_code() == grpc::StatusCode::UNAUTHENTICATED ? 1 : 0;
    if (s.error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED) {
      ++limited;
      last = s;
    }
  }
  EXPECT_LE(unauthenticated, 12);
  EXPECT_GE(limited, 18);
  EXPECT_THAT(last.error_message(), HasSubstr("client ipv4:127.0.0.1 (unauthenticated)"));
  EXPECT_TRUE(listMaps("survey", kTokenSurvey).ok());
}

// The mark replicas put on a call they pass on grants an outside client nothing: its token is still checked, and
// a listing with it and no good token is still refused.
TEST_F(AccessTest, AForgedForwardingMarkGrantsNothing) {
  start();
  const auto marked = [](const std::string& token) {
    auto c = callContext(token);
    c->AddMetadata("cvislam-forwarded", "1");
    return c;
  };
  v1::ListMapsRequest maps_request;
  maps_request.set_mission("survey");
  v1::ListMapsResponse maps_response;
  EXPECT_EQ(maps_->ListMaps(marked("").get(), maps_request, &maps_response).error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_EQ(maps_->ListMaps(marked(kTokenDepot).get(), maps_request, &maps_response).error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
  v1::ListMissionsResponse missions;
  EXPECT_EQ(maps_->ListMissions(marked("").get(), {}, &missions).error_code(), grpc::StatusCode::UNAUTHENTICATED);
  ASSERT_TRUE(maps_->ListMissions(marked(kTokenDepot).get(), {}, &missions).ok());
  ASSERT_EQ(missions.missions_size(), 1);
  EXPECT_EQ(missions.missions(0).name(), "depot");
  EXPECT_TRUE(maps_->ListMaps(marked(kTokenSurvey).get(), maps_request, &maps_response).ok());
}

// Nothing a caller is refused with tells it which other missions exist: a mission not in the tokens file and a
// wrong token read the same, and NOT_FOUND names no mission.
TEST_F(AccessTest, RefusalsAndNotFoundNameNoOtherMission) {
  start();
  const grpc::Status unlisted = listMaps("elsewhere", kTokenDepot);
  const grpc::Status wrong = listMaps("survey", kTokenDepot);
  ASSERT_EQ(unlisted.error_code(), grpc::StatusCode::UNAUTHENTICATED);
  ASSERT_EQ(wrong.error_code(), grpc::StatusCode::UNAUTHENTICATED);
  std::string unlisted_text = unlisted.error_message();
  unlisted_text.replace(unlisted_text.find("elsewhere"), 9, "survey");
  EXPECT_EQ(unlisted_text, wrong.error_message());
  const grpc::Status empty = listMaps("quiet", kTokenQuiet);
  EXPECT_EQ(empty.error_code(), grpc::StatusCode::NOT_FOUND);
  for (const char* other : {"survey", "depot"}) {
    EXPECT_THAT(empty.error_message(), ::testing::Not(HasSubstr(other)));
  }
}

// TLS from certificate files: the certificate is made here, with openssl, and trusted as its own CA.
class TlsTest : public AccessTest {
 protected:
  void SetUp() override {
    const std::string key = (dir_.path() / "server.key").string();
    const std::string cert = (dir_.path() / "server.crt").string();
    const auto made = cvislam::test::runCommand(
        "openssl", "req -x509 -newkey rsa:2048 -nodes -keyout " + key + " -out " + cert +
                       " -days 2 -subj /CN=localhost -addext subjectAltName=DNS:localhost,IP:127.0.0.1");
    ASSERT_EQ(made.exit_code, 0) << "openssl could not make the test certificate: " << made.output;
    ServerOptions options;
    options.tls_certificate = cert;
    options.tls_private_key = key;
    options.health_listen = "127.0.0.1:0";
    ca_ = cert;
    grpc::SslCredentialsOptions tls;
    tls.pem_root_certs = readFile(cert);
    start(options, grpc::SslCredentials(tls));  // its agent's Hello goes over TLS
  }
  std::string ca_;
};

TEST_F(TlsTest, TheAgentLinkAndTheMapServiceSpeakTlsAndPlaintextIsRefused) {
  EXPECT_TRUE(hello(channel_, "depot", 1, kTokenDepot).ok());
  EXPECT_TRUE(listMaps("survey", kTokenSurvey).ok());
  EXPECT_EQ(listMaps("survey", kTokenDepot).error_code(), grpc::StatusCode::UNAUTHENTICATED);

  auto plain = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
  v1::ListMapsRequest request;
  request.set_mission("survey");
  v1::ListMapsResponse response;
  auto context = callContext(kTokenSurvey);
  context->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(3));
  const grpc::Status s = v1::MapService::NewStub(plain)->ListMaps(context.get(), request, &response);
  EXPECT_EQ(s.error_code(), grpc::StatusCode::UNAVAILABLE) << s.error_message();
  EXPECT_EQ(response.maps_size(), 0);
}

TEST_F(TlsTest, MapctlAndThePythonClientWorkWithTheCaAndTheToken) {
  const std::string server = "--server " + server_->address() + " --timeout 10 ";
  const auto ok = cvislam::test::runCommand(CVISLAM_MAPCTL_BINARY,
                                            server + "--tls-ca " + ca_ + " --token " + kTokenSurvey + " maps survey");
  const auto from_env = cvislam::test::runCommand("CVISLAM_TOKEN=" + kTokenSurvey + " " + CVISLAM_MAPCTL_BINARY,
                                                  server + "--tls-ca " + ca_ + " list");
  const auto no_token = cvislam::test::runCommand(CVISLAM_MAPCTL_BINARY, server + "--tls-ca " + ca_ + " maps survey");
  const auto no_tls =
      cvislam::test::runCommand(CVISLAM_MAPCTL_BINARY, "--server " + server_->address() + " --timeout 3 --token " +
                                                           kTokenSurvey + " maps survey");
  EXPECT_EQ(ok.exit_code, 0) << ok.output;
  EXPECT_THAT(ok.output, HasSubstr("survey"));
  EXPECT_EQ(from_env.exit_code, 0) << from_env.output;
  EXPECT_THAT(from_env.output, HasSubstr("survey"));
  EXPECT_THAT(from_env.output, ::testing::Not(HasSubstr("depot")));
  EXPECT_EQ(no_token.exit_code, 1) << no_token.output;
  EXPECT_THAT(no_token.output, HasSubstr("UNAUTHENTICATED"));
  EXPECT_THAT(no_token.output, HasSubstr("--token"));
  EXPECT_EQ(no_tls.exit_code, 1) << no_tls.output;

  const std::string ply = (dir_.path() / "survey.ply").string();
  const std::string client = std::string(CVISLAM_MAP_CLIENT) + " --stubs " + CVISLAM_PY_STUBS + " --server " +
                             server_->address() + " --mission survey --tls-ca " + ca_ + " --out " + ply;
  const auto python = cvislam::test::runCommand("/usr/bin/python3", client + " --token " + kTokenSurvey);
  const auto python_refused = cvislam::test::runCommand("/usr/bin/python3", client + " --token " + kTokenDepot);
  EXPECT_EQ(python.exit_code, 0) << python.output;
  EXPECT_THAT(readFile(ply), HasSubstr("element vertex"));
  EXPECT_EQ(python_refused.exit_code, 1) << python_refused.output;
  EXPECT_THAT(python_refused.output, HasSubstr("UNAUTHENTICATED"));
}

// Kubernetes' gRPC probes cannot speak TLS: the plaintext health port answers for the server and each service,
// and serves nothing else.
TEST_F(TlsTest, ThePlaintextHealthPortAnswersProbesAndServesNothingElse) {
  ASSERT_NE(server_->healthPort(), 0);
  ASSERT_NE(server_->healthPort(), server_->port());
  auto plain =
      grpc::CreateChannel("127.0.0.1:" + std::to_string(server_->healthPort()), grpc::InsecureChannelCredentials());
  auto health = grpc::health::v1::Health::NewStub(plain);
  for (const char* service : {"", "cvislam.v1.AgentLink", "cvislam.v1.MapService", "cvislam.v1.Monitor"}) {
    grpc::health::v1::HealthCheckRequest request;
    request.set_service(service);
    grpc::health::v1::HealthCheckResponse response;
    const grpc::Status s = health->Check(callContext("").get(), request, &response);
    ASSERT_TRUE(s.ok()) << service << ": " << s.error_message();
    EXPECT_EQ(response.status(), grpc::health::v1::HealthCheckResponse::SERVING) << service;
  }
  v1::ListMapsRequest request;
  request.set_mission("survey");
  v1::ListMapsResponse response;
  const grpc::Status maps =
      v1::MapService::NewStub(plain)->ListMaps(callContext(kTokenSurvey).get(), request, &response);
  EXPECT_EQ(maps.error_code(), grpc::StatusCode::UNIMPLEMENTED) << maps.error_message();
  EXPECT_EQ(hello(plain, "depot", 2, kTokenDepot).error_code(), grpc::StatusCode::UNIMPLEMENTED);

  server_->shutdown(std::chrono::milliseconds(100));  // a stopping server says so on the probe port first
  grpc::health::v1::HealthCheckResponse after;
  const grpc::Status gone = health->Check(callContext("").get(), {}, &after);
  EXPECT_TRUE(!gone.ok() || after.status() == grpc::health::v1::HealthCheckResponse::NOT_SERVING);
}

TEST(TlsOptions, AMissingOrBrokenCertificateStopsTheStartNamingTheFile) {
  cvislam::test::TempDir dir;
  std::ofstream(dir.path() / "not.pem") << "hello\n";
  ServerOptions options;
  options.listen = "127.0.0.1:0";
  options.tls_certificate = dir.path() / "missing.crt";
  options.tls_private_key = dir.path() / "not.pem";
  ServerCore core(options);
  const auto missing = GrpcServer::start(core);
  ASSERT_FALSE(missing.ok());
  EXPECT_THAT(missing.error().message(), HasSubstr("missing.crt"));

  options.tls_certificate = dir.path() / "not.pem";
  ServerCore core2(options);
  const auto broken = GrpcServer::start(core2);
  ASSERT_FALSE(broken.ok());
  EXPECT_THAT(broken.error().message(), HasSubstr("not.pem is not a PEM file"));

  options.tls_private_key.clear();
  EXPECT_THAT(options.validate().error().message(), HasSubstr("both a certificate and its private key"));
  options.tls_certificate.clear();
  options.health_listen = options.listen;
  EXPECT_THAT(options.validate().error().message(), HasSubstr("health_listen must be another port"));
  options.health_listen = "50052";
  EXPECT_THAT(options.validate().error().message(), HasSubstr("give host:port"));
}

}  // namespace
}  // namespace cvislam::server
