// cvislam.v1.MapService over real loopback gRPC (port 0): listings and maps arrive as the core gives them,
// streamed in chunks; errors arrive as statuses naming the problem; a client that stops reading mid-stream
// leaves the server serving. Then the two clients as processes: cvislam_mapctl (tables, export, exit codes) and
// the Python client (python3-grpcio with the stubs the build generated), which writes a PLY.
#include "server_cloud/service/grpc_server.hpp"

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <grpcpp/grpcpp.h>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "cvislam/v1/map_service.grpc.pb.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/maps/map_export.hpp"
#include "server_cloud/maps/map_reader.hpp"
#include "test/server_cloud/maps/example_maps.hpp"
#include "test/support/run_command.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using ::testing::HasSubstr;

std::unique_ptr<grpc::ClientContext> callContext() {
  auto c = std::make_unique<grpc::ClientContext>();
  c->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
  return c;
}

std::string readFile(const std::filesystem::path& path) {
  std::ifstream in(path);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

class MapServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ServerOptions options;
    options.listen = "127.0.0.1:0";
    core_ = std::make_unique<ServerCore>(options);
    test::ExampleMissionOptions example;
    example.keyframes_per_agent = 40;
    test::fillExampleMission(core_->missions(), example);
    auto started = GrpcServer::start(*core_);
    ASSERT_TRUE(started.ok()) << started.error().toString();
    server_ = std::move(started).value();
    channel_ = grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials());
    stub_ = v1::MapService::NewStub(channel_);
  }
  void TearDown() override {
    if (server_) server_->shutdown(std::chrono::milliseconds(500));
  }

  // Every chunk of a GetMap, and the call's status.
  grpc::Status getMap(const v1::GetMapRequest& request, std::vector<v1::MapChunk>& chunks) {
    auto context = callContext();
    auto reader = stub_->GetMap(context.get(), request);
    v1::MapChunk chunk;
    while (reader->Read(&chunk)) chunks.push_back(chunk);
    return reader->Finish();
  }

  std::unique_ptr<ServerCore> core_;
  std::unique_ptr<GrpcServer> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::MapService::Stub> stub_;
};

TEST_F(MapServiceTest, HealthAndListingsOverTheWireAreTheCores) {
  v1::ListMissionsResponse missions;
  v1::ListMapsRequest maps_request;
  maps_request.set_mission("survey");
  v1::ListMapsResponse maps;

  grpc::health::v1::HealthCheckRequest health_request;
  health_request.set_service("cvislam.v1.MapService");
  grpc::health::v1::HealthCheckResponse health;

  const grpc::Status h =
      grpc::health::v1::Health::NewStub(channel_)->Check(callContext().get(), health_request, &health);
  const grpc::Status m = stub_->ListMissions(callContext().get(), {}, &missions);
  const grpc::Status l = stub_->ListMaps(callContext().get(), maps_request, &maps);

  ASSERT_TRUE(h.ok()) << h.error_message();
  EXPECT_EQ(health.status(), grpc::health::v1::HealthCheckResponse::SERVING);
  ASSERT_TRUE(m.ok()) << m.error_message();
  ASSERT_TRUE(l.ok()) << l.error_message();
  v1::ListMissionsResponse want_missions;
  maps::listMissions(core_->missions(), want_missions);
  v1::ListMapsResponse want_maps;
  ASSERT_TRUE(maps::listMaps(core_->missions(), "survey", want_maps).ok());
  EXPECT_EQ(missions.SerializeAsString(), want_missions.SerializeAsString());
  EXPECT_EQ(maps.SerializeAsString(), want_maps.SerializeAsString());
  EXPECT_EQ(maps.maps(0).keyframes(), 80U);
}

TEST_F(MapServiceTest, GetMapStreamsTheWholeMapInChunksWithinTheAskedSize) {
  v1::GetMapRequest request;
  request.set_mission("survey");
  request.set_map_id(0);
  request.set_observations(true);
  request.set_max_chunk_bytes(16384);
  std::vector<v1::MapChunk> chunks;

  const grpc::Status s = getMap(request, chunks);

  ASSERT_TRUE(s.ok()) << s.error_message();
  ASSERT_GT(chunks.size(), 10U);
  v1::MapChunk all;
  for (const auto& c : chunks) {
    EXPECT_LE(c.ByteSizeLong(), 16384U);
    all.MergeFrom(c);
  }
  EXPECT_TRUE(chunks.back().last());
  EXPECT_EQ(all.keyframes_size(), 80);
  EXPECT_EQ(all.points_size(), 80 * 30);
  // The same as the core's own chunks of a snapshot taken now (nothing changed in between).
  maps::SnapshotOptions with;
  with.observations = true;
  auto snapshot = maps::snapshotMap(core_->missions(), "survey", 0, with);
  ASSERT_TRUE(snapshot.ok());
  auto chunker = maps::MapChunker::create(std::move(snapshot).value(), 16384);
  ASSERT_TRUE(chunker.ok());
  v1::MapChunk want;
  v1::MapChunk chunk;
  while (chunker->next(chunk)) want.MergeFrom(chunk);
  all.clear_index();
  want.clear_index();
  EXPECT_EQ(all.SerializeAsString(), want.SerializeAsString());
}

TEST_F(MapServiceTest, RefusalsArriveAsStatusesNamingTheProblem) {
  v1::GetMapRequest unknown;
  unknown.set_mission("nowhere");
  v1::GetMapRequest tiny = unknown;
  tiny.set_mission("survey");
  tiny.set_max_chunk_bytes(100);
  v1::GetMapRequest merged = tiny;
  merged.set_max_chunk_bytes(0);
  merged.set_map_id(7);
  v1::GetTrajectoryRequest bad_agent;
  bad_agent.set_mission("survey");
  bad_agent.set_agent(70000);
  v1::ListMapsRequest unnamed;
  v1::ExportMapRequest export_unknown;
  export_unknown.set_mission("nowhere");

  std::vector<v1::MapChunk> chunks;
  const grpc::Status s_unknown = getMap(unknown, chunks);
  const grpc::Status s_tiny = getMap(tiny, chunks);
  const grpc::Status s_map = getMap(merged, chunks);
  v1::GetTrajectoryResponse trajectory;
  const grpc::Status s_agent = stub_->GetTrajectory(callContext().get(), bad_agent, &trajectory);
  v1::ListMapsResponse maps;
  const grpc::Status s_unnamed = stub_->ListMaps(callContext().get(), unnamed, &maps);
  auto context = callContext();
  auto reader = stub_->ExportMap(context.get(), export_unknown);
  v1::ExportChunk file;
  while (reader->Read(&file)) {
  }
  const grpc::Status s_export = reader->Finish();

  EXPECT_TRUE(chunks.empty());
  EXPECT_EQ(s_unknown.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(s_unknown.error_message(), HasSubstr("no mission 'nowhere'"));
  EXPECT_EQ(s_tiny.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(s_tiny.error_message(), HasSubstr("max_chunk_bytes 100"));
  EXPECT_EQ(s_map.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(s_map.error_message(), HasSubstr("no map 7"));
  EXPECT_EQ(s_agent.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(s_agent.error_message(), HasSubstr("70000"));
  EXPECT_EQ(s_unnamed.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(s_export.error_code(), grpc::StatusCode::NOT_FOUND);
}

TEST_F(MapServiceTest, AClientThatStopsReadingMidStreamLeavesTheServerServing) {
  for (int round = 0; round < 3; ++round) {
    v1::GetMapRequest request;
    request.set_mission("survey");
    request.set_max_chunk_bytes(4096);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
    auto reader = stub_->GetMap(&context, request);
    v1::MapChunk chunk;
    ASSERT_TRUE(reader->Read(&chunk));
    EXPECT_FALSE(chunk.last());
    context.TryCancel();
    EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::CANCELLED);
  }

  v1::GetMapRequest request;
  request.set_mission("survey");
  std::vector<v1::MapChunk> chunks;
  const grpc::Status s = getMap(request, chunks);

  ASSERT_TRUE(s.ok()) << s.error_message();
  ASSERT_EQ(chunks.size(), 1U);
  EXPECT_EQ(chunks[0].points_size(), 80 * 30);
}

// Map reads hold a copy of what they send until the client has read it. Clients that open them and never read get
// at most max_map_reads_per_address at once (the rest are refused), and those are cancelled at map_read_timeout_s,
// so their copies go.
TEST(MapReadLimits, ReadersThatNeverReadAreCappedPerAddressAndCancelledAtTheTimeout) {
  ServerOptions options;
  options.listen = "127.0.0.1:0";
  options.map_read_limits.per_address = 3;
  options.map_read_timeout_s = 0.5;
  ServerCore core(options);
  test::ExampleMissionOptions example;
  example.keyframes_per_agent = 1500;  // tens of megabytes: more than the transport buffers for a reader that waits
  test::fillExampleMission(core.missions(), example);
  auto server = GrpcServer::start(core);
  ASSERT_TRUE(server.ok()) << server.error().toString();
  // The client's flow-control window fixed at 64 KiB: gRPC's bandwidth probe would otherwise grow it, on an idle
  // loopback, until a whole map fits in the transport and a reader that never reads still gets everything.
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_HTTP2_BDP_PROBE, 0);
  args.SetInt(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, 64 << 10);
  auto stub = v1::MapService::NewStub(
      grpc::CreateCustomChannel((*server)->address(), grpc::InsecureChannelCredentials(), args));
  v1::GetMapRequest request;
  request.set_mission("survey");
  request.set_observations(true);
  request.set_descriptors(true);
  request.set_max_chunk_bytes(64U << 10U);

  constexpr int kReaders = 8;
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientReader<v1::MapChunk>>> readers;
  for (int i = 0; i < kReaders; ++i) {
    contexts.push_back(callContext());
    readers.push_back(stub->GetMap(contexts.back().get(), request));  // and never read
  }
  // Bounded waits on the condition rather than fixed sleeps: under a sanitizer the snapshots take seconds.
  for (int i = 0; i < 250 && core.mapReadLimits().openStreams() < 3U; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_EQ(core.mapReadLimits().openStreams(), 3U);
  // Past the timeout, still without reading: the server cancels the three and frees their slots.
  for (int i = 0; i < 1500 && core.mapReadLimits().openStreams() > 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  int refused = 0;
  int cancelled = 0;
  for (auto& reader : readers) {
    v1::MapChunk chunk;
    while (reader->Read(&chunk)) {
    }
    const grpc::Status status = reader->Finish();
    if (status.error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED) {
      ++refused;
      EXPECT_THAT(status.error_message(), HasSubstr("limits.max_map_reads_per_address"));
    } else {
      EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED) << status.error_message();
      ++cancelled;
    }
  }
  EXPECT_EQ(refused, kReaders - 3);
  EXPECT_EQ(cancelled, 3);
  EXPECT_EQ(core.mapReadLimits().openStreams(), 0U);
  (*server)->shutdown(std::chrono::milliseconds(500));
}

TEST_F(MapServiceTest, ExportOverTheWireGivesTheCoresFilesWhole) {
  v1::ExportMapRequest request;
  request.set_mission("survey");
  auto context = callContext();
  auto reader = stub_->ExportMap(context.get(), request);
  v1::ExportChunk chunk;
  std::map<std::string, std::string> files;
  int ends = 0;
  while (reader->Read(&chunk)) {
    files[chunk.file()] += chunk.data();
    ends += chunk.file_end() ? 1 : 0;
  }
  const grpc::Status s = reader->Finish();

  ASSERT_TRUE(s.ok()) << s.error_message();
  auto snapshots = maps::snapshotMission(core_->missions(), "survey");
  ASSERT_TRUE(snapshots.ok());
  const auto want = maps::exportMaps(snapshots.value());
  ASSERT_EQ(files.size(), want.size());
  EXPECT_EQ(ends, static_cast<int>(want.size()));
  for (const auto& f : want) EXPECT_EQ(files[f.name], f.data) << f.name;
}

TEST_F(MapServiceTest, MapctlPrintsTablesExportsFilesAndFailsClearly) {
  const test::TempDir dir;
  const std::string server = "--server " + server_->address() + " ";

  const auto list = test::runCommand(CVISLAM_MAPCTL_BINARY, server + "list");
  const auto maps = test::runCommand(CVISLAM_MAPCTL_BINARY, server + "maps survey");
  const auto get =
      test::runCommand(CVISLAM_MAPCTL_BINARY, server + "get survey 1 --out " + (dir.path() / "m1.ply").string());
  const auto exported = test::runCommand(CVISLAM_MAPCTL_BINARY,
                                         server + "export survey --map 0 --out " + (dir.path() / "export").string());
  const auto unknown = test::runCommand(CVISLAM_MAPCTL_BINARY, server + "maps nowhere");
  const auto unreachable = test::runCommand(CVISLAM_MAPCTL_BINARY, "--server 127.0.0.1:1 --timeout 2 list");
  const auto json = test::runCommand(CVISLAM_MAPCTL_BINARY, server + "--json maps survey");

  ASSERT_EQ(list.exit_code, 0) << list.output;
  EXPECT_THAT(list.output, HasSubstr("survey"));
  EXPECT_THAT(list.output, HasSubstr("1,2,3"));
  ASSERT_EQ(maps.exit_code, 0) << maps.output;
  EXPECT_THAT(maps.output, HasSubstr("agent1 map0"));
  EXPECT_THAT(maps.output, HasSubstr("2400"));  // map 0's points
  ASSERT_EQ(get.exit_code, 0) << get.output;
  EXPECT_THAT(get.output, HasSubstr("20 keyframes"));
  EXPECT_THAT(readFile(dir.path() / "m1.ply"), HasSubstr("element vertex 600\n"));
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "export" / "map0.ply"));
  EXPECT_THAT(exported.output, HasSubstr("exported 4 files"));
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "export" / "keyframes_agent2_map0.txt"));
  EXPECT_THAT(readFile(dir.path() / "export" / "map0.json"), HasSubstr("\"keyframes\": 80"));
  EXPECT_EQ(unknown.exit_code, 1);
  EXPECT_THAT(unknown.output, HasSubstr("NOT_FOUND"));
  EXPECT_THAT(unknown.output, HasSubstr("no mission 'nowhere'"));
  EXPECT_EQ(unreachable.exit_code, 1);
  EXPECT_THAT(unreachable.output, HasSubstr("is cvislam_server running there?"));
  ASSERT_EQ(json.exit_code, 0) << json.output;
  EXPECT_THAT(json.output, HasSubstr("\"origin_agent\": 1"));
}

TEST_F(MapServiceTest, ThePythonClientFetchesTheLargestMapAndWritesItsPoints) {
  const test::TempDir dir;
  const auto out = dir.path() / "map.ply";

  const auto run = test::runCommand("/usr/bin/python3", std::string(CVISLAM_MAP_CLIENT) + " --server " +
                                                            server_->address() + " --mission survey --stubs " +
                                                            CVISLAM_PY_STUBS + " --out " + out.string());
  const auto refused = test::runCommand("/usr/bin/python3", std::string(CVISLAM_MAP_CLIENT) + " --server " +
                                                                server_->address() + " --mission nowhere --stubs " +
                                                                CVISLAM_PY_STUBS + " --out " + out.string() + ".x");

  ASSERT_EQ(run.exit_code, 0) << run.output;
  EXPECT_THAT(run.output, HasSubstr("map 0 of survey: 80 keyframes, 2400 points"));
  const std::string ply = readFile(out);
  EXPECT_THAT(ply, HasSubstr("element vertex 2400\n"));
  std::size_t rows = 0;
  std::istringstream lines(ply.substr(ply.find("end_header\n") + 11));
  std::string line;
  while (std::getline(lines, line)) ++rows;
  EXPECT_EQ(rows, 2400U);
  EXPECT_EQ(refused.exit_code, 1) << refused.output;
  EXPECT_THAT(refused.output, HasSubstr("NOT_FOUND"));
}

MissionEvent keyframeAdded(std::uint32_t counter) {
  MissionEvent e;
  e.kind = MissionEvent::Kind::kKeyframeAdded;
  e.agent = 2;
  e.keyframe = KeyframeId{2, counter};
  return e;
}

// Reads responses until `n` events came (or the stream ended).
std::vector<v1::MissionEventMessage> readEvents(grpc::ClientReaderInterface<v1::WatchMissionResponse>& reader,
                                                std::size_t n, std::uint64_t* skipped = nullptr) {
  std::vector<v1::MissionEventMessage> events;
  v1::WatchMissionResponse response;
  while (events.size() < n && reader.Read(&response)) {
    if (skipped != nullptr) *skipped += response.skipped();
    events.insert(events.end(), response.events().begin(), response.events().end());
  }
  return events;
}

TEST_F(MapServiceTest, WatchStreamsWhatHappensAfterItStartsAndAnotherResumesFromANumber) {
  MissionEventLog& log = core_->missions().find("survey")->events();
  log.append(keyframeAdded(0));  // before the watch: not sent to a watch from 0
  v1::WatchMissionRequest request;
  request.set_mission("survey");
  auto context = callContext();
  auto reader = stub_->WatchMission(context.get(), request);
  // Nothing tells the client when the server registered the call, so events keep coming until it saw three.
  std::atomic<bool> seen{false};
  std::thread appender([&log, &seen] {
    for (std::uint32_t c = 1; c <= 500 && !seen; ++c) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      MissionEvent merged;
      merged.kind = MissionEvent::Kind::kMapsMerged;
      merged.map = 0;
      merged.from_map = c;
      log.append(merged);
    }
  });

  const auto events = readEvents(*reader, 3);
  seen = true;
  appender.join();
  context->TryCancel();
  (void)reader->Finish();

  ASSERT_GE(events.size(), 3U);
  EXPECT_GE(events[0].number(), 2U) << "event 1 came before the watch";
  EXPECT_EQ(events[1].number(), events[0].number() + 1);
  EXPECT_EQ(events[2].number(), events[0].number() + 2);
  EXPECT_EQ(events[1].kind(), v1::MissionEventMessage::MAPS_MERGED);
  EXPECT_EQ(events[1].from_map_id(), events[1].number() - 1);  // merged.from_map = c, appended as number c + 1
  EXPECT_GT(events[0].t_unix_ns(), 0);

  // A client that saw the first of them resumes from the next number, and gets the other two at once.
  request.set_from_event(events[0].number() + 1);
  auto again_context = callContext();
  auto again = stub_->WatchMission(again_context.get(), request);
  const auto resumed = readEvents(*again, 2);
  again_context->TryCancel();
  (void)again->Finish();
  ASSERT_GE(resumed.size(), 2U);
  EXPECT_EQ(resumed[0].number(), events[1].number());
  EXPECT_EQ(resumed[1].number(), events[2].number());
}

TEST_F(MapServiceTest, AWatcherFarBehindLearnsHowManyEventsTheServerNoLongerHolds) {
  MissionEventLog& log = core_->missions().find("survey")->events();
  const std::size_t total = MissionEventLog::kDefaultCapacity + 100;
  for (std::size_t i = 0; i < total; ++i) log.append(keyframeAdded(static_cast<std::uint32_t>(i)));
  v1::WatchMissionRequest request;
  request.set_mission("survey");
  request.set_from_event(1);
  auto context = callContext();
  auto reader = stub_->WatchMission(context.get(), request);

  std::uint64_t skipped = 0;
  const auto events = readEvents(*reader, MissionEventLog::kDefaultCapacity, &skipped);
  context->TryCancel();
  (void)reader->Finish();

  EXPECT_EQ(skipped, 100U);
  ASSERT_EQ(events.size(), MissionEventLog::kDefaultCapacity);
  EXPECT_EQ(events.front().number(), 101U);
  EXPECT_EQ(events.back().number(), total);
  EXPECT_EQ(events.back().keyframe().counter(), total - 1);
}

TEST_F(MapServiceTest, WatchingAnUnknownMissionIsNotFoundAndAStoppingServerEndsEveryWatch) {
  v1::WatchMissionRequest unknown;
  unknown.set_mission("nowhere");
  auto unknown_context = callContext();
  auto refused = stub_->WatchMission(unknown_context.get(), unknown);
  v1::WatchMissionResponse response;
  while (refused->Read(&response)) {
  }
  const grpc::Status s_unknown = refused->Finish();

  MissionEventLog& log = core_->missions().find("survey")->events();
  v1::WatchMissionRequest request;
  request.set_mission("survey");
  request.set_from_event(log.nextNumber());  // the event appended next, whenever the server registers the call
  auto context = callContext();
  auto reader = stub_->WatchMission(context.get(), request);
  log.append(keyframeAdded(5));
  ASSERT_EQ(readEvents(*reader, 1).size(), 1U);  // the stream is open and served
  server_->shutdown(std::chrono::milliseconds(5000));
  while (reader->Read(&response)) {
  }
  const grpc::Status s_stopped = reader->Finish();

  EXPECT_EQ(s_unknown.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(s_unknown.error_message(), HasSubstr("no mission 'nowhere'"));
  EXPECT_EQ(s_stopped.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(s_stopped.error_message(), HasSubstr("stopping"));
}

// Scale-out: a replica that lost a mission's lease ends its watches of it, so that watchers come back through the
// new owner instead of reading a log that no longer grows.
TEST_F(MapServiceTest, AWatchOfAMissionThisReplicaGaveUpEndsUnavailable) {
  MissionEventLog& log = core_->missions().find("survey")->events();
  v1::WatchMissionRequest request;
  request.set_mission("survey");
  request.set_from_event(log.nextNumber());
  auto context = callContext();
  auto reader = stub_->WatchMission(context.get(), request);
  log.append(keyframeAdded(5));
  ASSERT_EQ(readEvents(*reader, 1).size(), 1U);

  core_->dropMission("survey");

  v1::WatchMissionResponse response;
  while (reader->Read(&response)) {
  }
  const grpc::Status status = reader->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(status.error_message(), HasSubstr("moved to another replica"));
}

TEST_F(MapServiceTest, MapctlWatchPrintsEventsFromANumberAndSaysWhereToResume) {
  MissionEventLog& log = core_->missions().find("survey")->events();
  for (std::uint32_t c = 0; c < 5; ++c) log.append(keyframeAdded(c));
  MissionEvent corrected;
  corrected.kind = MissionEvent::Kind::kMapCorrected;
  corrected.map = 0;
  corrected.keyframes = 42;
  corrected.cause = "global BA";
  log.append(corrected);

  const auto run =
      test::runCommand(CVISLAM_MAPCTL_BINARY, "--server " + server_->address() + " watch survey --from 4 --count 3");

  ASSERT_EQ(run.exit_code, 0) << run.output;
  EXPECT_THAT(run.output, HasSubstr("#4       keyframe added     2:3 in map 0"));
  EXPECT_THAT(run.output, HasSubstr("#6       map corrected      map 0, 42 keyframes (global BA)"));
  EXPECT_THAT(run.output, HasSubstr("resume with --from 7"));
}

}  // namespace
}  // namespace cvislam::server
