// Fuzzes what an API client sends the map service and the monitor: the first byte picks the call, the rest is
// parsed as its request message and run through the checks and the core's answer exactly as the adapter does
// (token, then listing, snapshot and chunking, export, event log; the monitor's token checks) against a small example
// mission. A second framed part is the call's "authorization" metadata value.
#include <memory>

#include "cvislam/v1/map_service.pb.h"
#include "cvislam/v1/monitor.pb.h"
#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/maps/map_export.hpp"
#include "server_cloud/maps/map_reader.hpp"
#include "test/fuzz/fuzz_target.hpp"
#include "test/server_cloud/maps/example_maps.hpp"

namespace {

using namespace cvislam;

const char* const kToken = "survey-mission-token-01";

// The server's state for every input: an example mission (read only by these calls) and its token.
struct Server {
  server::MissionRegistry missions;
  server::MissionTokens tokens;
};

const Server& server() {
  static const Server* const instance = [] {
    auto* s = new Server;
    test::ExampleMissionOptions example;
    example.keyframes_per_agent = 6;
    example.points_per_keyframe = 8;
    example.keypoints_per_keyframe = 40;
    test::fillExampleMission(s->missions, example);
    auto tokens = server::MissionTokens::parse(std::string("survey ") + kToken + "\n", "fuzz tokens");
    if (!tokens) __builtin_trap();
    s->tokens = std::move(tokens).value();
    return s;
  }();
  return *instance;
}

enum Call : std::uint8_t { kListMissions, kListMaps, kGetMap, kGetTrajectory, kExportMap, kWatch, kGetStats, kCalls };

void serve(std::uint8_t call, const std::string& body, const std::string& authorization) {
  const Server& c = server();
  const std::string token(server::bearerToken(authorization));
  const auto allowed = [&](const std::string& mission) { return c.tokens.authorize(mission, token).ok(); };
  switch (static_cast<Call>(call % kCalls)) {
    case kListMissions: {
      v1::ListMissionsRequest request;
      if (!request.ParseFromString(body)) return;
      v1::ListMissionsResponse response;
      server::maps::listMissions(c.missions, response);
      return;
    }
    case kListMaps: {
      v1::ListMapsRequest request;
      if (!request.ParseFromString(body) || !allowed(request.mission())) return;
      v1::ListMapsResponse response;
      (void)server::maps::listMaps(c.missions, request.mission(), response);
      return;
    }
    case kGetMap: {
      v1::GetMapRequest request;
      if (!request.ParseFromString(body) || !allowed(request.mission())) return;
      server::maps::SnapshotOptions options;
      options.observations = request.observations();
      options.descriptors = request.descriptors();
      auto snapshot = server::maps::snapshotMap(c.missions, request.mission(), request.map_id(), options);
      if (!snapshot) return;
      auto chunker = server::maps::MapChunker::create(std::move(snapshot).value(), request.max_chunk_bytes());
      if (!chunker) return;
      v1::MapChunk chunk;
      for (int i = 0; i < 100000 && chunker->next(chunk); ++i) {
      }
      return;
    }
    case kGetTrajectory: {
      v1::GetTrajectoryRequest request;
      if (!request.ParseFromString(body) || !allowed(request.mission()) || request.agent() > 0xFFFFU) return;
      v1::GetTrajectoryResponse response;
      (void)server::maps::getTrajectory(c.missions, request.mission(), static_cast<AgentId>(request.agent()), response);
      return;
    }
    case kExportMap: {
      v1::ExportMapRequest request;
      if (!request.ParseFromString(body) || !allowed(request.mission())) return;
      if (request.has_map_id()) {
        auto one = server::maps::snapshotMap(c.missions, request.mission(), request.map_id());
        if (one) (void)server::maps::exportMaps({std::move(one).value()});
      } else {
        auto all = server::maps::snapshotMission(c.missions, request.mission());
        if (all) (void)server::maps::exportMaps(*all);
      }
      return;
    }
    case kWatch: {
      v1::WatchMissionRequest request;
      if (!request.ParseFromString(body) || request.mission().empty() || !allowed(request.mission())) return;
      auto mission = c.missions.find(request.mission());
      if (!mission) return;
      (void)mission->events().read(request.from_event(), 512);
      return;
    }
    case kGetStats: {  // the monitor's checks (its statistics are ServerCore's, outside this target)
      v1::GetStatsRequest request;
      if (!request.ParseFromString(body)) return;
      if (!request.mission().empty()) (void)allowed(request.mission());
      for (const auto& mission : c.missions.missions()) (void)allowed(mission->name());
      return;
    }
    case kCalls:
      return;
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const auto parts = fuzz::frames(data + 1, size - 1, 2);
  serve(data[0], parts.empty() ? std::string() : parts[0], parts.size() > 1 ? parts[1] : std::string());
  return 0;
}

std::vector<std::string> cvislam::fuzz::seeds() {
  const std::string auth = frame(std::string("Bearer ") + kToken);
  std::vector<std::string> out;
  const auto add = [&](Call call, const google::protobuf::Message& request) {
    out.push_back(std::string(1, static_cast<char>(call)) + frame(request.SerializeAsString()) + auth);
  };
  v1::ListMapsRequest list;
  list.set_mission("survey");
  add(kListMissions, v1::ListMissionsRequest{});
  add(kListMaps, list);
  v1::GetMapRequest get;
  get.set_mission("survey");
  get.set_map_id(0);
  get.set_observations(true);
  get.set_descriptors(true);
  get.set_max_chunk_bytes(4096);
  add(kGetMap, get);
  v1::GetTrajectoryRequest trajectory;
  trajectory.set_mission("survey");
  trajectory.set_agent(1);
  add(kGetTrajectory, trajectory);
  v1::ExportMapRequest exported;
  exported.set_mission("survey");
  add(kExportMap, exported);
  exported.set_map_id(1);
  add(kExportMap, exported);
  v1::WatchMissionRequest watch;
  watch.set_mission("survey");
  watch.set_from_event(2);
  add(kWatch, watch);
  v1::GetStatsRequest stats;
  stats.set_mission("survey");
  add(kGetStats, stats);
  return out;
}
