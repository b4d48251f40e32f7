// cvislam_mapctl: reads a running cvislam_server's maps over cvislam.v1.MapService.
//
//   cvislam_mapctl [--server HOST:PORT] [--token T] [--tls-ca CA.pem] [--json] [--timeout S] list
//   cvislam_mapctl ... maps MISSION
//   cvislam_mapctl ... get MISSION MAP [--observations] [--descriptors] [--chunk-bytes N] [--out FILE.json|FILE.ply]
//   cvislam_mapctl ... trajectory MISSION AGENT [--out FILE.txt]
//   cvislam_mapctl ... export MISSION [--map M] --out DIR | --mcap FILE
//   cvislam_mapctl ... watch MISSION [--from N] [--count N] [--seconds S]
//
// Tables by default; --json prints the server's answer as JSON instead (get: a summary, since a map can be large;
// its content goes to --out). Exit status: 0 done, 1 the server refused or could not be reached (the message says
// which and why), 2 bad command line.
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <CLI/CLI.hpp>

#include "common/core/text.hpp"
#include "cvislam/v1/map_service.grpc.pb.h"
#include "server_cloud/viewer/foxglove_messages.hpp"
#include "server_cloud/viewer/mcap_recorder.hpp"

namespace {

namespace v1 = cvislam::v1;

struct Globals {
  std::string server = "127.0.0.1:50051";
  bool json = false;
  double timeout_s = 30.0;
  std::string token;
  std::string tls_ca;
};

std::unique_ptr<grpc::ClientContext> context(const Globals& g) {
  auto c = std::make_unique<grpc::ClientContext>();
  if (!g.token.empty()) c->AddMetadata("authorization", "Bearer " + g.token);
  c->set_deadline(std::chrono::system_clock::now() +
                  std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::duration<double>(g.timeout_s)));
  return c;
}

const char* grpcCodeName(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::INVALID_ARGUMENT:
      return "INVALID_ARGUMENT";
    case grpc::StatusCode::NOT_FOUND:
      return "NOT_FOUND";
    case grpc::StatusCode::UNAVAILABLE:
      return "UNAVAILABLE";
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::UNIMPLEMENTED:
      return "UNIMPLEMENTED";
    case grpc::StatusCode::UNAUTHENTICATED:
      return "UNAUTHENTICATED";
    case grpc::StatusCode::PERMISSION_DENIED:
      return "PERMISSION_DENIED";
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::CANCELLED:
      return "CANCELLED";
    case grpc::StatusCode::INTERNAL:
      return "INTERNAL";
    default:
      return "error";
  }
}

int failed(const Globals& g, const grpc::Status& status) {
  const char* hint = "";
  if (status.error_code() == grpc::StatusCode::UNAVAILABLE ||
      status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED) {
    hint = " (is cvislam_server running there? --server HOST:PORT)";
  } else if (status.error_code() == grpc::StatusCode::UNIMPLEMENTED) {
    hint = " (the server there does not offer cvislam.v1.MapService: an older build, or not a cvislam_server)";
  }
  std::fprintf(stderr, "cvislam_mapctl: %s at %s: %s%s\n", grpcCodeName(status.error_code()), g.server.c_str(),
               status.error_message().c_str(), hint);
  return 1;
}

void printJson(const google::protobuf::Message& message) {
  std::string text;
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = true;
  options.always_print_primitive_fields = true;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(message, &text, options);
  std::cout << text;
}

std::string agentList(const google::protobuf::RepeatedField<std::uint32_t>& agents) {
  std::string out;
  for (std::uint32_t a : agents) out += (out.empty() ? "" : ",") + std::to_string(a);
  return out.empty() ? "-" : out;
}

int list(const Globals& g, v1::MapService::Stub& stub) {
  v1::ListMissionsResponse response;
  const auto c = context(g);
  if (auto s = stub.ListMissions(c.get(), {}, &response); !s.ok()) return failed(g, s);
  if (g.json) {
    printJson(response);
    return 0;
  }
  std::printf("%-20s %-16s %9s %5s %10s %10s\n", "mission", "agents", "connected", "maps", "keyframes", "points");
  for (const auto& m : response.missions()) {
    std::printf("%-20s %-16s %9u %5u %10llu %10llu\n", m.name().c_str(), agentList(m.agents()).c_str(),
                m.connected_agents(), m.maps(), static_cast<unsigned long long>(m.keyframes()),
                static_cast<unsigned long long>(m.points()));
  }
  if (response.missions().empty()) std::printf("(no missions on %s yet)\n", g.server.c_str());
  return 0;
}

int maps(const Globals& g, v1::MapService::Stub& stub, const std::string& mission) {
  v1::ListMapsRequest request;
  request.set_mission(mission);
  v1::ListMapsResponse response;
  const auto c = context(g);
  if (auto s = stub.ListMaps(c.get(), request, &response); !s.ok()) return failed(g, s);
  if (g.json) {
    printJson(response);
    return 0;
  }
  std::printf("mission %s\n%5s %-16s %10s %8s %10s %13s %8s %-10s\n", mission.c_str(), "map", "agents", "keyframes",
              "refined", "points", "observations", "edges", "frame of");
  for (const auto& m : response.maps()) {
    const std::string origin =
        "agent" + std::to_string(m.origin_agent()) + " map" + std::to_string(m.origin_agent_map());
    std::printf("%5u %-16s %10llu %8llu %10llu %13llu %8llu %s\n", m.map_id(), agentList(m.agents()).c_str(),
                static_cast<unsigned long long>(m.keyframes()), static_cast<unsigned long long>(m.refined_keyframes()),
                static_cast<unsigned long long>(m.points()), static_cast<unsigned long long>(m.observations()),
                static_cast<unsigned long long>(m.covisibility_edges()), origin.c_str());
  }
  return 0;
}

bool writePly(const std::filesystem::path& path, const v1::MapChunk& map) {
  std::ofstream out(path);
  out << "ply\nformat ascii 1.0\nelement vertex " << map.points_size()
      << "\nproperty float x\nproperty float y\nproperty float z\nproperty uint observations\nend_header\n";
  char line[128];
  for (const auto& p : map.points()) {
    std::snprintf(line, sizeof(line), "%.5f %.5f %.5f %u\n", p.p_m().x(), p.p_m().y(), p.p_m().z(), p.observations());
    out << line;
  }
  return static_cast<bool>(out);
}

// One map, its chunks merged. On an error it prints why and returns the exit status.
struct FetchedMap {
  v1::MapChunk all;
  std::size_t chunks = 0;
  std::size_t bytes = 0;
  std::size_t largest = 0;
};
std::variant<FetchedMap, int> fetchMap(const Globals& g, v1::MapService::Stub& stub, const v1::GetMapRequest& request) {
  FetchedMap fetched;
  const auto c = context(g);
  auto reader = stub.GetMap(c.get(), request);
  v1::MapChunk chunk;
  bool last = false;
  while (reader->Read(&chunk)) {
    ++fetched.chunks;
    const std::size_t n = chunk.ByteSizeLong();
    fetched.bytes += n;
    fetched.largest = std::max(fetched.largest, n);
    last = chunk.last();
    fetched.all.MergeFrom(chunk);
  }
  if (auto s = reader->Finish(); !s.ok()) return failed(g, s);
  if (!last) {
    std::fprintf(stderr, "cvislam_mapctl: the server ended GetMap without its last chunk (%zu chunks read)\n",
                 fetched.chunks);
    return 1;
  }
  return fetched;
}

int get(const Globals& g, v1::MapService::Stub& stub, const v1::GetMapRequest& request,
        const std::filesystem::path& out_path) {
  const auto start = std::chrono::steady_clock::now();
  auto result = fetchMap(g, stub, request);
  if (const int* status = std::get_if<int>(&result)) return *status;
  FetchedMap& fetched = std::get<FetchedMap>(result);
  v1::MapChunk& all = fetched.all;  // every chunk merged: the whole map
  const std::size_t chunks = fetched.chunks;
  const std::size_t bytes = fetched.bytes;
  const std::size_t largest = fetched.largest;
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::map<std::uint32_t, std::size_t> per_agent;
  for (const auto& kf : all.keyframes()) ++per_agent[kf.id().agent()];
  if (g.json) {
    v1::MapChunk summary;
    *summary.mutable_map() = all.map();
    printJson(summary);
  } else {
    std::printf(
        "mission %s map %u: %d keyframes (%llu refined), %d points, %zu chunks, %.2f MB, largest chunk "
        "%.1f kB, %.3f s\n",
        request.mission().c_str(), request.map_id(), all.keyframes_size(),
        static_cast<unsigned long long>(all.map().refined_keyframes()), all.points_size(), chunks,
        static_cast<double>(bytes) / 1e6, static_cast<double>(largest) / 1e3, seconds);
    for (const auto& [agent, n] : per_agent) std::printf("  agent %u: %zu keyframes\n", agent, n);
  }
  if (!out_path.empty()) {
    bool ok = false;
    if (out_path.extension() == ".ply") {
      ok = writePly(out_path, all);
    } else {
      std::string text;
      google::protobuf::util::JsonPrintOptions options;
      options.preserve_proto_field_names = true;
      all.clear_index();
      all.clear_last();
      ok = google::protobuf::util::MessageToJsonString(all, &text, options).ok();
      std::ofstream out(out_path);
      out << text << "\n";
      ok = ok && static_cast<bool>(out);
    }
    if (!ok) {
      std::fprintf(stderr, "cvislam_mapctl: cannot write %s\n", out_path.c_str());
      return 1;
    }
    std::fprintf(stderr, "wrote %s\n", out_path.c_str());
  }
  return 0;
}

int trajectory(const Globals& g, v1::MapService::Stub& stub, const v1::GetTrajectoryRequest& request,
               const std::filesystem::path& out_path) {
  v1::GetTrajectoryResponse response;
  const auto c = context(g);
  if (auto s = stub.GetTrajectory(c.get(), request, &response); !s.ok()) return failed(g, s);
  if (!out_path.empty()) {
    std::ofstream out(out_path);
    out << "# t[s] x y z qx qy qz qw: agent " << request.agent() << "'s keyframes, each in its server map's frame\n";
    char line[256];
    for (const auto& p : response.poses()) {
      const auto& T = p.t_m_s();
      std::snprintf(line, sizeof(line), "%lld.%09lld %.6f %.6f %.6f %.9f %.9f %.9f %.9f\n",
                    static_cast<long long>(p.t_ns() / 1000000000), static_cast<long long>(p.t_ns() % 1000000000),
                    T.px(), T.py(), T.pz(), static_cast<double>(T.qx()), static_cast<double>(T.qy()),
                    static_cast<double>(T.qz()), static_cast<double>(T.qw()));
      out << line;
    }
    if (!out) {
      std::fprintf(stderr, "cvislam_mapctl: cannot write %s\n", out_path.c_str());
      return 1;
    }
    std::fprintf(stderr, "wrote %s\n", out_path.c_str());
  }
  if (g.json) {
    printJson(response);
    return 0;
  }
  std::set<std::uint32_t> maps;
  std::size_t refined = 0;
  for (const auto& p : response.poses()) {
    maps.insert(p.map_id());
    refined += p.refined() ? 1 : 0;
  }
  if (response.poses().empty()) return 0;
  const auto& first = response.poses(0);
  const auto& last = response.poses(response.poses_size() - 1);
  std::printf("mission %s agent %u: %d keyframes (%zu refined) in %zu map(s), t %.3f to %.3f s\n",
              response.mission().c_str(), response.agent(), response.poses_size(), refined, maps.size(),
              static_cast<double>(first.t_ns()) * 1e-9, static_cast<double>(last.t_ns()) * 1e-9);
  return 0;
}

int exportMap(const Globals& g, v1::MapService::Stub& stub, const v1::ExportMapRequest& request,
              const std::filesystem::path& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) {
    std::fprintf(stderr, "cvislam_mapctl: cannot create %s: %s\n", dir.c_str(), ec.message().c_str());
    return 1;
  }
  const auto start = std::chrono::steady_clock::now();
  const auto c = context(g);
  auto reader = stub.ExportMap(c.get(), request);
  v1::ExportChunk chunk;
  std::map<std::string, std::string> files;
  std::set<std::string> complete;
  while (reader->Read(&chunk)) {
    const std::string& name = chunk.file();
    if (name.empty() || name.find('/') != std::string::npos || name == "." || name == "..") {
      std::fprintf(stderr, "cvislam_mapctl: the server sent a file name that is not a plain name: '%s'\n",
                   name.c_str());
      return 1;
    }
    files[name] += chunk.data();
    if (chunk.file_end()) complete.insert(name);
  }
  if (auto s = reader->Finish(); !s.ok()) return failed(g, s);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::size_t total = 0;
  for (const auto& [name, data] : files) {
    if (complete.count(name) == 0) {
      std::fprintf(stderr, "cvislam_mapctl: %s came incomplete (no file_end)\n", name.c_str());
      return 1;
    }
    std::ofstream out(dir / name, std::ios::binary);
    out << data;
    if (!out) {
      std::fprintf(stderr, "cvislam_mapctl: cannot write %s\n", (dir / name).c_str());
      return 1;
    }
    std::printf("%10zu bytes  %s\n", data.size(), (dir / name).c_str());
    total += data.size();
  }
  std::printf("exported %zu files, %.2f MB, in %.3f s\n", files.size(), static_cast<double>(total) / 1e6, seconds);
  return 0;
}

// The mission's maps as the live viewer draws them (cvislam_server --viewer-listen), into one MCAP file: the
// keyframes (linked along each agent's own sequence: the map service sends no covisibility), each map's points, and
// each agent's trajectory in the map that holds its newest keyframes, all stamped now.
int exportMcap(const Globals& g, v1::MapService::Stub& stub, const std::string& mission,
               std::optional<std::uint32_t> only_map, const std::filesystem::path& file) {
  namespace viewer = cvislam::server::viewer;
  v1::ListMapsRequest list_request;
  list_request.set_mission(mission);
  v1::ListMapsResponse listed;
  {
    const auto c = context(g);
    if (auto s = stub.ListMaps(c.get(), list_request, &listed); !s.ok()) return failed(g, s);
  }
  const std::int64_t t_ns =
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch()).count();
  const auto pose = [](const v1::Pose& p) {
    const auto d = [](float v) { return static_cast<double>(v); };
    return cvislam::geometry::SE3d(Eigen::Quaterniond(d(p.qw()), d(p.qx()), d(p.qy()), d(p.qz())),
                                   Eigen::Vector3d(p.px(), p.py(), p.pz()));
  };
  std::vector<viewer::FeedChannel> channels{{"/" + mission + "/keyframes", viewer::kSceneUpdateSchema}};
  std::vector<viewer::FeedMessage> messages;
  std::vector<viewer::KeyframeEntity> entities;
  // Per agent: (time, map, pose) of every keyframe.
  std::map<std::uint32_t, std::vector<std::tuple<std::int64_t, std::uint32_t, cvislam::geometry::SE3d>>> agents;
  for (const v1::MapInfo& info : listed.maps()) {
    if (only_map && info.map_id() != *only_map) continue;
    v1::GetMapRequest request;
    request.set_mission(mission);
    request.set_map_id(info.map_id());
    auto result = fetchMap(g, stub, request);
    if (const int* status = std::get_if<int>(&result)) return *status;
    const v1::MapChunk& map = std::get<FetchedMap>(result).all;
    const std::string frame = mission + "/map" + std::to_string(info.map_id());
    // Each agent map's keyframes by time: each is linked to the one before.
    std::map<std::pair<std::uint32_t, std::uint32_t>, std::vector<const v1::MapKeyframe*>> sequences;
    for (const v1::MapKeyframe& k : map.keyframes()) sequences[{k.id().agent(), k.agent_map()}].push_back(&k);
    for (auto& [key, sequence] : sequences) {
      std::sort(sequence.begin(), sequence.end(), [](const auto* a, const auto* b) { return a->t_ns() < b->t_ns(); });
      for (std::size_t i = 0; i < sequence.size(); ++i) {
        const v1::MapKeyframe& k = *sequence[i];
        viewer::KeyframeEntity e;
        e.id = {static_cast<cvislam::AgentId>(k.id().agent()), k.id().counter()};
        e.map = info.map_id();
        e.frame_id = frame;
        e.T_frame_body = pose(k.t_m_s());
        if (i > 0) e.segments = {e.T_frame_body.translation(), pose(sequence[i - 1]->t_m_s()).translation()};
        entities.push_back(std::move(e));
        agents[key.first].emplace_back(k.t_ns(), info.map_id(), pose(k.t_m_s()));
      }
    }
    std::vector<Eigen::Vector3f> points;
    points.reserve(static_cast<std::size_t>(map.points_size()));
    for (const v1::MapPointState& p : map.points()) {
      points.emplace_back(static_cast<float>(p.p_m().x()), static_cast<float>(p.p_m().y()),
                          static_cast<float>(p.p_m().z()));
    }
    channels.push_back({"/" + mission + "/map" + std::to_string(info.map_id()) + "/points", viewer::kPointCloudSchema});
    messages.push_back({channels.size() - 1, t_ns, viewer::pointCloud(t_ns, frame, points)});
  }
  messages.insert(messages.begin(), {0, t_ns, viewer::sceneUpdate(t_ns, entities, {})});
  for (auto& [agent, keyframes] : agents) {
    std::sort(keyframes.begin(), keyframes.end(),
              [](const auto& a, const auto& b) { return std::get<0>(a) < std::get<0>(b); });
    const std::uint32_t newest_map = std::get<1>(keyframes.back());
    std::vector<cvislam::geometry::SE3d> poses;
    for (const auto& [t, map, T] : keyframes) {
      if (map == newest_map) poses.push_back(T);
    }
    channels.push_back({"/" + mission + "/agent" + std::to_string(agent) + "/trajectory", viewer::kPosesInFrameSchema});
    messages.push_back(
        {channels.size() - 1, t_ns, viewer::posesInFrame(t_ns, mission + "/map" + std::to_string(newest_map), poses)});
  }
  auto recorder = viewer::McapRecorder::create(file);
  if (!recorder) {
    std::fprintf(stderr, "cvislam_mapctl: %s\n", recorder.error().message().c_str());
    return 1;
  }
  if (auto s = recorder->write(channels, messages); !s.ok()) {
    std::fprintf(stderr, "cvislam_mapctl: %s\n", s.error().message().c_str());
    return 1;
  }
  if (auto s = recorder->close(); !s.ok()) {
    std::fprintf(stderr, "cvislam_mapctl: %s\n", s.error().message().c_str());
    return 1;
  }
  std::printf("wrote %s: %zu keyframes, %zu channels, %llu messages (%.2f MB)\n", file.c_str(), entities.size(),
              channels.size(), static_cast<unsigned long long>(recorder->messages()),
              static_cast<double>(std::filesystem::file_size(file)) / 1e6);
  return 0;
}

const char* kindName(v1::MissionEventMessage::Kind kind) {
  switch (kind) {
    case v1::MissionEventMessage::AGENT_CONNECTED:
      return "agent connected";
    case v1::MissionEventMessage::AGENT_DISCONNECTED:
      return "agent disconnected";
    case v1::MissionEventMessage::KEYFRAME_ADDED:
      return "keyframe added";
    case v1::MissionEventMessage::KEYFRAME_REMOVED:
      return "keyframe removed";
    case v1::MissionEventMessage::MAPS_MERGED:
      return "maps merged";
    case v1::MissionEventMessage::MAP_CORRECTED:
      return "map corrected";
    default:
      return "unknown";
  }
}

// Prints events as they come until `count` were printed (0: no limit), `seconds` passed (0: none) or the server
// ends the stream. The last line says which event to resume from.
int watch(const Globals& g, v1::MapService::Stub& stub, const v1::WatchMissionRequest& request, std::uint64_t count,
          double seconds) {
  grpc::ClientContext c;
  if (!g.token.empty()) c.AddMetadata("authorization", "Bearer " + g.token);
  if (seconds > 0) {
    c.set_deadline(std::chrono::system_clock::now() +
                   std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::duration<double>(seconds)));
  }
  auto reader = stub.WatchMission(&c, request);
  v1::WatchMissionResponse response;
  std::uint64_t printed = 0;
  std::uint64_t next = request.from_event();
  while (reader->Read(&response)) {
    if (response.skipped() > 0) {
      std::printf("(%llu older events are no longer held by the server)\n",
                  static_cast<unsigned long long>(response.skipped()));
    }
    for (const auto& e : response.events()) {
      if (g.json) {
        std::string text;
        (void)google::protobuf::util::MessageToJsonString(e, &text);
        std::printf("%s\n", text.c_str());
      } else {
        std::string what;
        switch (e.kind()) {
          case v1::MissionEventMessage::AGENT_CONNECTED:
          case v1::MissionEventMessage::AGENT_DISCONNECTED:
            what = "agent " + std::to_string(e.agent());
            break;
          case v1::MissionEventMessage::KEYFRAME_ADDED:
          case v1::MissionEventMessage::KEYFRAME_REMOVED:
            what = std::to_string(e.keyframe().agent()) + ":" + std::to_string(e.keyframe().counter()) + " in map " +
                   std::to_string(e.map_id());
            break;
          case v1::MissionEventMessage::MAPS_MERGED:
            what = "map " + std::to_string(e.from_map_id()) + " into map " + std::to_string(e.map_id());
            break;
          case v1::MissionEventMessage::MAP_CORRECTED:
            what = "map " + std::to_string(e.map_id()) + ", " + std::to_string(e.keyframes()) + " keyframes";
            break;
          default:
            break;
        }
        if (!e.cause().empty()) what += " (" + e.cause() + ")";
        std::printf("#%-7llu %-18s %s\n", static_cast<unsigned long long>(e.number()), kindName(e.kind()),
                    what.c_str());
      }
      next = e.number() + 1;
      std::fflush(stdout);
      if (count > 0 && ++printed >= count) {
        c.TryCancel();
        break;
      }
    }
    if (count > 0 && printed >= count) break;
  }
  const grpc::Status status = reader->Finish();
  const bool ended_by_us =
      (count > 0 && printed >= count) || (seconds > 0 && status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED);
  if (!g.json) std::fprintf(stderr, "resume with --from %llu\n", static_cast<unsigned long long>(next));
  if (!ended_by_us && !status.ok()) return failed(g, status);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Globals g;
  CLI::App app{"cvislam_mapctl: read a cvislam_server's maps (missions, maps, keyframes, points, trajectories)"};
  app.add_option("--server", g.server, "The server's host:port [127.0.0.1:50051]");
  app.add_flag("--json", g.json, "Print the answer as JSON instead of tables");
  app.add_option("--timeout", g.timeout_s, "Seconds each call may take [30]")->check(CLI::PositiveNumber);
  app.add_option("--token", g.token,
                 "The mission's token, when the server has a tokens file [$CVISLAM_TOKEN; none]. The environment "
                 "variable keeps it out of the process list");
  app.add_option("--tls-ca", g.tls_ca, "Speak TLS, trusting the server certificate's CA in this PEM file [plaintext]");
  app.require_subcommand(1);

  app.add_subcommand("list", "Every mission on the server, with its agents and counts");

  std::string mission;
  auto* maps_cmd = app.add_subcommand("maps", "The maps of one mission's stack");
  maps_cmd->add_option("mission", mission, "Mission name")->required();

  v1::GetMapRequest get_request;
  std::uint32_t map_id = 0;
  bool observations = false;
  bool descriptors = false;
  std::uint32_t chunk_bytes = 0;
  std::filesystem::path out;
  auto* get_cmd = app.add_subcommand("get", "Fetch one map (streamed in chunks); --out saves it as JSON or PLY");
  get_cmd->add_option("mission", mission, "Mission name")->required();
  get_cmd->add_option("map", map_id, "Map id (see 'maps')")->required();
  get_cmd->add_flag("--observations", observations, "Include each keyframe's observations");
  get_cmd->add_flag("--descriptors", descriptors, "Include each point's ORB descriptor");
  get_cmd->add_option("--chunk-bytes", chunk_bytes, "Largest chunk the server may send; 0: its default (1 MiB)");
  get_cmd->add_option("--out", out, "Write the map: FILE.ply (points) or any other name (JSON, everything)");

  std::uint32_t agent = 0;
  auto* traj_cmd = app.add_subcommand("trajectory", "One agent's keyframe trajectory as the server holds it");
  traj_cmd->add_option("mission", mission, "Mission name")->required();
  traj_cmd->add_option("agent", agent, "Agent id")->required();
  traj_cmd->add_option("--out", out, "Write it as TUM text (t x y z qx qy qz qw)");

  std::optional<std::uint32_t> export_map;
  std::filesystem::path mcap_file;
  auto* export_cmd = app.add_subcommand(
      "export", "Files of a mission's maps: PLY points, TUM keyframes, JSON summary; or an MCAP file for Foxglove");
  export_cmd->add_option("mission", mission, "Mission name")->required();
  export_cmd->add_option("--map", export_map, "Only this map [every map]");
  auto* out_option = export_cmd->add_option("--out", out, "Folder to write the files into");
  auto* mcap_option = export_cmd->add_option(
      "--mcap", mcap_file,
      "Write the maps as the live viewer draws them (keyframes, points, trajectories) into this MCAP file");
  out_option->excludes(mcap_option);

  std::uint64_t from_event = 0;
  std::uint64_t count = 0;
  double seconds = 0;
  auto* watch_cmd = app.add_subcommand("watch", "Print what happens to a mission's maps as it happens");
  watch_cmd->add_option("mission", mission, "Mission name")->required();
  watch_cmd->add_option("--from", from_event, "First event number; 0: only new events [0]");
  watch_cmd->add_option("--count", count, "Stop after this many events; 0: never [0]");
  watch_cmd->add_option("--seconds", seconds, "Stop after this long; 0: never [0]")->check(CLI::NonNegativeNumber);

  CLI11_PARSE(app, argc, argv);

  auto channel_args = grpc::ChannelArguments();
  channel_args.SetMaxReceiveMessageSize(64 << 20);
  if (g.token.empty()) {
    if (const char* from_env = std::getenv("CVISLAM_TOKEN"); from_env != nullptr) g.token = from_env;
  }
  if (!g.token.empty() && !cvislam::text::isPrintableToken(g.token)) {
    std::fprintf(stderr, "cvislam_mapctl: --token may hold printable ASCII characters only, without spaces\n");
    return 2;
  }
  std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
  if (!g.tls_ca.empty()) {
    auto pem = cvislam::text::readPemFile(g.tls_ca, "CA file (--tls-ca)");
    if (!pem) {
      std::fprintf(stderr, "cvislam_mapctl: %s\n", pem.error().message().c_str());
      return 2;
    }
    grpc::SslCredentialsOptions tls;
    tls.pem_root_certs = std::move(pem).value();
    credentials = grpc::SslCredentials(tls);
  }
  auto channel = grpc::CreateCustomChannel(g.server, credentials, channel_args);
  auto stub = v1::MapService::NewStub(channel);

  if (app.got_subcommand("list")) return list(g, *stub);
  if (maps_cmd->parsed()) return maps(g, *stub, mission);
  if (get_cmd->parsed()) {
    get_request.set_mission(mission);
    get_request.set_map_id(map_id);
    get_request.set_observations(observations);
    get_request.set_descriptors(descriptors);
    get_request.set_max_chunk_bytes(chunk_bytes);
    return get(g, *stub, get_request, out);
  }
  if (traj_cmd->parsed()) {
    v1::GetTrajectoryRequest request;
    request.set_mission(mission);
    request.set_agent(agent);
    return trajectory(g, *stub, request, out);
  }
  if (watch_cmd->parsed()) {
    v1::WatchMissionRequest request;
    request.set_mission(mission);
    request.set_from_event(from_event);
    return watch(g, *stub, request, count, seconds);
  }
  if (!mcap_file.empty()) return exportMcap(g, *stub, mission, export_map, mcap_file);
  if (out.empty()) {
    std::fprintf(stderr, "cvislam_mapctl: export needs --out DIR (files) or --mcap FILE\n");
    return 2;
  }
  v1::ExportMapRequest request;
  request.set_mission(mission);
  if (export_map) request.set_map_id(*export_map);
  return exportMap(g, *stub, request, out);
}
