// bench_map_service: what it costs to fetch a large map through cvislam.v1.MapService over loopback gRPC.
// SYNTHETIC map (test/server_cloud/maps/example_maps): two agents' keyframes in one map, each keyframe making 30
// new points and observing the previous keyframe's 30, 200 keypoints per keyframe. Measured per call, over
// `--repetitions` calls each, p50 / p99 / max:
//   snapshot   the copy under the map's read lock (what delays ingest into that map), in the core, no gRPC;
//   get        a GetMap client call from request to the last chunk, without and with observations + descriptors;
//   export     an ExportMap call (PLY, TUM, JSON of every map of the mission).
// Bytes are the serialized messages the client received.
//
//   bench_map_service [--keyframes 1000] [--repetitions 20] [--json OUT]
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <grpcpp/grpcpp.h>
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "cvislam/v1/map_service.grpc.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/maps/map_reader.hpp"
#include "server_cloud/service/grpc_server.hpp"
#include "test/bench/percentiles.hpp"
#include "test/server_cloud/maps/example_maps.hpp"

namespace {

using Clock = std::chrono::steady_clock;
namespace v1 = cvislam::v1;

double msSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

struct Series {
  std::vector<double> ms;
  std::size_t bytes = 0;
  std::size_t messages = 0;
  nlohmann::json json() const {
    return {{"p50_ms", cvislam::bench::percentile(ms, 0.5)},
            {"p99_ms", cvislam::bench::percentile(ms, 0.99)},
            {"max_ms", cvislam::bench::percentile(ms, 1.0)},
            {"bytes", bytes},
            {"messages", messages},
            {"calls", ms.size()}};
  }
};

}  // namespace

int main(int argc, char** argv) {
  int keyframes = 1000;
  int repetitions = 20;
  std::string json_path;
  CLI::App app{"bench_map_service: GetMap / ExportMap of a large synthetic map over loopback gRPC, p50/p99"};
  app.add_option("--keyframes", keyframes, "Keyframes in the fetched map (two agents, half each) [1000]")
      ->check(CLI::Range(2, 200000));
  app.add_option("--repetitions", repetitions, "Calls per measurement [20]")->check(CLI::Range(1, 10000));
  app.add_option("--json", json_path, "Also write the results here");
  CLI11_PARSE(app, argc, argv);

  cvislam::server::ServerOptions options;
  options.listen = "127.0.0.1:0";
  options.max_message_bytes = 64U << 20U;
  cvislam::server::ServerCore core(options);
  cvislam::test::ExampleMissionOptions example;
  example.keyframes_per_agent = static_cast<std::uint32_t>(keyframes / 2);
  std::fprintf(stderr, "filling a map of %d keyframes ...\n", keyframes);
  cvislam::test::fillExampleMission(core.missions(), example);
  auto started = cvislam::server::GrpcServer::start(core);
  if (!started) {
    std::fprintf(stderr, "bench_map_service: %s\n", started.error().toString().c_str());
    return 1;
  }
  auto server = std::move(started).value();
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(64 << 20);
  auto stub =
      v1::MapService::NewStub(grpc::CreateCustomChannel(server->address(), grpc::InsecureChannelCredentials(), args));

  Series snapshot;
  for (int i = 0; i < repetitions; ++i) {
    const auto t0 = Clock::now();
    auto s = cvislam::server::maps::snapshotMap(core.missions(), example.name, 0, {true, true});
    snapshot.ms.push_back(msSince(t0));
    if (!s) return 1;
  }

  const auto getMap = [&](bool full, Series& series) -> bool {
    v1::GetMapRequest request;
    request.set_mission(example.name);
    request.set_map_id(0);
    request.set_observations(full);
    request.set_descriptors(full);
    for (int i = 0; i < repetitions; ++i) {
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(60));
      const auto t0 = Clock::now();
      auto reader = stub->GetMap(&context, request);
      v1::MapChunk chunk;
      std::size_t bytes = 0;
      std::size_t chunks = 0;
      std::size_t kfs = 0;
      while (reader->Read(&chunk)) {
        bytes += chunk.ByteSizeLong();
        ++chunks;
        kfs += static_cast<std::size_t>(chunk.keyframes_size());
      }
      const grpc::Status status = reader->Finish();
      series.ms.push_back(msSince(t0));
      if (!status.ok() || kfs != static_cast<std::size_t>(2 * example.keyframes_per_agent)) {
        std::fprintf(stderr, "bench_map_service: GetMap failed: %s (%zu keyframes)\n", status.error_message().c_str(),
                     kfs);
        return false;
      }
      series.bytes = bytes;
      series.messages = chunks;
    }
    return true;
  };
  Series plain;
  Series full;
  if (!getMap(false, plain) || !getMap(true, full)) return 1;

  Series exported;
  for (int i = 0; i < repetitions; ++i) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(60));
    v1::ExportMapRequest request;
    request.set_mission(example.name);
    const auto t0 = Clock::now();
    auto reader = stub->ExportMap(&context, request);
    v1::ExportChunk chunk;
    std::size_t bytes = 0;
    std::size_t chunks = 0;
    while (reader->Read(&chunk)) {
      bytes += chunk.ByteSizeLong();
      ++chunks;
    }
    if (!reader->Finish().ok()) return 1;
    exported.ms.push_back(msSince(t0));
    exported.bytes = bytes;
    exported.messages = chunks;
  }
  server->shutdown();

  nlohmann::ordered_json out;
  out["map"] = {{"keyframes", 2 * example.keyframes_per_agent},
                {"points", 2 * example.keyframes_per_agent * example.points_per_keyframe},
                {"keypoints_per_keyframe", example.keypoints_per_keyframe}};
  out["snapshot_under_read_lock"] = snapshot.json();
  out["get_map"] = plain.json();
  out["get_map_observations_descriptors"] = full.json();
  out["export_mission"] = exported.json();
  std::printf("map of %u keyframes, %u points; %d calls each (p50 / p99 / max):\n", 2 * example.keyframes_per_agent,
              2 * example.keyframes_per_agent * example.points_per_keyframe, repetitions);
  const auto line = [](const char* what, const Series& s) {
    std::printf("  %-34s %8.2f %8.2f %8.2f ms", what, cvislam::bench::percentile(s.ms, 0.5),
                cvislam::bench::percentile(s.ms, 0.99), cvislam::bench::percentile(s.ms, 1.0));
    if (s.messages > 0) std::printf("  %8.2f MB in %zu messages", static_cast<double>(s.bytes) / 1e6, s.messages);
    std::printf("\n");
  };
  line("snapshot (read lock, with all)", snapshot);
  line("GetMap", plain);
  line("GetMap + observations, descriptors", full);
  line("ExportMap (whole mission)", exported);
  if (!json_path.empty()) {
    std::ofstream f(json_path);
    f << out.dump(2) << "\n";
  }
  return 0;
}
