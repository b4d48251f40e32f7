#include "server_cloud/maps/map_reader.hpp"

#include <algorithm>
#include <map>
#include <set>
#include <utility>

#include "cvislam/v1/map_service.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::server::maps {

namespace {

std::shared_ptr<Mission> findMission(const MissionRegistry& missions, const std::string& name, Status& status) {
  if (name.empty()) {
    status = Error{ErrorCode::kInvalidArgument, "the request names no mission (ListMissions lists them)"};
    return nullptr;
  }
  auto mission = missions.find(name);
  if (!mission) {
    // No list of what the server holds: a caller learns only of the missions its token opens (ListMissions).
    status = Error{ErrorCode::kNotFound,
                   "no mission '" + name + "' on this server (ListMissions lists the missions your token opens)"};
  }
  return mission;
}

void setVec3(const Eigen::Vector3d& v, v1::Vec3* out) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

void fillInfo(const MapSnapshot& s, v1::MapInfo& info) {
  info.set_map_id(s.map_id);
  for (AgentId a : s.agents) info.add_agents(a);
  info.set_keyframes(s.keyframes.size());
  info.set_points(s.points.size());
  info.set_observations(s.observations);
  info.set_covisibility_edges(s.covisibility_edges);
  std::uint64_t refined = 0;
  for (const auto& kf : s.keyframes) refined += kf.refined ? 1 : 0;
  info.set_refined_keyframes(refined);
  info.set_origin_agent(s.origin.agent);
  info.set_origin_agent_map(s.origin.agent_map);
}

void toMessage(const MapSnapshot::Keyframe& kf, v1::MapKeyframe& out) {
  out.mutable_id()->set_agent(kf.id.agent);
  out.mutable_id()->set_counter(kf.id.counter);
  out.set_agent_map(kf.agent_map);
  out.set_t_ns(kf.t_ns);
  wire::toProto(kf.T_m_s, out.mutable_t_m_s());
  setVec3(kf.v_m, out.mutable_v_m());
  setVec3(kf.bias.gyro, out.mutable_bias_gyro());
  setVec3(kf.bias.accel, out.mutable_bias_accel());
  out.set_refined(kf.refined);
  out.set_keypoints(kf.keypoints);
  out.set_observed_points(kf.observed_points);
  for (const auto& o : kf.observations) {
    v1::MapObservation& m = *out.add_observations();
    m.set_keypoint(o.keypoint);
    m.set_u(o.px.x());
    m.set_v(o.px.y());
    m.mutable_point()->set_agent(o.point.agent);
    m.mutable_point()->set_counter(o.point.counter);
  }
}

void toMessage(const MapSnapshot::Point& p, bool descriptor, v1::MapPointState& out) {
  out.mutable_id()->set_agent(p.id.agent);
  out.mutable_id()->set_counter(p.id.counter);
  setVec3(p.p_m, out.mutable_p_m());
  out.mutable_reference()->set_agent(p.reference.agent);
  out.mutable_reference()->set_counter(p.reference.counter);
  out.set_observations(p.observations);
  if (descriptor) out.set_orb_descriptor(p.descriptor.data(), p.descriptor.size());
}

MapSnapshot copyMap(const Mission& mission, const ServerMap& map, const SnapshotOptions& options) {
  MapSnapshot s;
  s.mission = mission.name();
  s.map_id = map.id();
  s.origin = mission.stack().origin(map.id()).value_or(MapOrigin{});
  s.descriptors = options.descriptors;
  {
    auto content = map.read();
    s.agents.assign(content->agents().begin(), content->agents().end());
    s.covisibility_edges = content->covisibilityEdges();
    s.keyframes.reserve(content->keyframes().size());
    for (const auto& [id, kf] : content->keyframes()) {
      MapSnapshot::Keyframe& k = s.keyframes.emplace_back();
      k.id = id;
      k.agent_map = kf.agent_map;
      k.t_ns = kf.t_ns;
      k.T_m_s = kf.T_w_s;
      k.v_m = kf.v_w;
      k.bias = kf.bias;
      k.refined = kf.refined;
      k.keypoints = static_cast<std::uint32_t>(kf.keypoints.size());
      for (std::size_t i = 0; i < kf.has_point.size(); ++i) {
        if (kf.has_point[i] == 0U) continue;
        ++k.observed_points;
        if (options.observations)
          k.observations.push_back({static_cast<std::uint16_t>(i), kf.keypoints[i].px, kf.point[i]});
      }
      s.observations += k.observed_points;
    }
    s.points.reserve(content->points().size());
    for (const auto& [id, p] : content->points()) {
      MapSnapshot::Point& q = s.points.emplace_back();
      q.id = id;
      q.p_m = p.p_w;
      q.reference = p.reference;
      q.observations = static_cast<std::uint32_t>(p.observations.size());
      if (options.descriptors) q.descriptor = p.descriptor;
    }
  }
  std::sort(s.keyframes.begin(), s.keyframes.end(), [](const auto& a, const auto& b) { return a.id < b.id; });
  std::sort(s.points.begin(), s.points.end(), [](const auto& a, const auto& b) { return a.id < b.id; });
  return s;
}

}  // namespace

void listMissions(const MissionRegistry& missions, v1::ListMissionsResponse& out) {
  out.Clear();
  for (const auto& mission : missions.missions()) {
    v1::MissionInfo& info = *out.add_missions();
    info.set_name(mission->name());
    std::uint32_t connected = 0;
    for (const auto& shared : mission->agents()) {
      auto record = shared->read();
      info.add_agents(record->id);
      connected += record->connected ? 1 : 0;
    }
    info.set_connected_agents(connected);
    const auto stack = mission->stack().maps();
    info.set_maps(static_cast<std::uint32_t>(stack.size()));
    std::uint64_t keyframes = 0;
    std::uint64_t points = 0;
    for (const auto& map : stack) {
      auto content = map->read();
      keyframes += content->keyframes().size();
      points += content->points().size();
    }
    info.set_keyframes(keyframes);
    info.set_points(points);
  }
}

Status listMaps(const MissionRegistry& missions, const std::string& name, v1::ListMapsResponse& out) {
  out.Clear();
  Status status;
  auto mission = findMission(missions, name, status);
  if (!mission) return status;
  out.set_mission(name);
  for (const auto& map : mission->stack().maps()) {
    const MapOrigin origin = mission->stack().origin(map->id()).value_or(MapOrigin{});
    v1::MapInfo& info = *out.add_maps();
    auto content = map->read();
    info.set_map_id(map->id());
    for (AgentId a : content->agents()) info.add_agents(a);
    info.set_keyframes(content->keyframes().size());
    info.set_points(content->points().size());
    std::uint64_t observations = 0;
    std::uint64_t refined = 0;
    for (const auto& [id, kf] : content->keyframes()) {
      observations += static_cast<std::uint64_t>(std::count(kf.has_point.begin(), kf.has_point.end(), 1));
      refined += kf.refined ? 1 : 0;
    }
    info.set_observations(observations);
    info.set_refined_keyframes(refined);
    info.set_covisibility_edges(content->covisibilityEdges());
    info.set_origin_agent(origin.agent);
    info.set_origin_agent_map(origin.agent_map);
  }
  return {};
}

Status getTrajectory(const MissionRegistry& missions, const std::string& name, AgentId agent,
                     v1::GetTrajectoryResponse& out) {
  out.Clear();
  Status status;
  auto mission = findMission(missions, name, status);
  if (!mission) return status;
  struct Row {
    KeyframeId id;
    MapId map = 0;
    std::int64_t t_ns = 0;
    geometry::SE3d T_m_s;
    bool refined = false;
  };
  std::vector<Row> rows;
  for (const auto& map : mission->stack().maps()) {
    auto content = map->read();
    if (content->agents().count(agent) == 0) continue;
    for (const auto& [id, kf] : content->keyframes()) {
      if (id.agent == agent) rows.push_back({id, map->id(), kf.t_ns, kf.T_w_s, kf.refined});
    }
  }
  if (rows.empty()) {
    return Error{ErrorCode::kNotFound, "mission '" + name + "' holds no keyframe of agent " + std::to_string(agent)};
  }
  std::sort(rows.begin(), rows.end(),
            [](const Row& a, const Row& b) { return a.t_ns != b.t_ns ? a.t_ns < b.t_ns : a.id < b.id; });
  out.set_mission(name);
  out.set_agent(agent);
  out.mutable_poses()->Reserve(static_cast<int>(rows.size()));
  for (const Row& r : rows) {
    v1::TrajectoryPose& p = *out.add_poses();
    p.mutable_id()->set_agent(r.id.agent);
    p.mutable_id()->set_counter(r.id.counter);
    p.set_map_id(r.map);
    p.set_t_ns(r.t_ns);
    wire::toProto(r.T_m_s, p.mutable_t_m_s());
    p.set_refined(r.refined);
  }
  return {};
}

Result<MapSnapshot> snapshotMap(const MissionRegistry& missions, const std::string& name, MapId map_id,
                                const SnapshotOptions& options) {
  Status status;
  auto mission = findMission(missions, name, status);
  if (!mission) return status.error();
  auto map = mission->stack().find(map_id);
  if (!map) {
    std::string held;
    for (const auto& m : mission->stack().maps()) held += (held.empty() ? "" : ", ") + std::to_string(m->id());
    std::string why = mission->stack().origin(map_id) ? " (merged into another map)" : "";
    return Error{ErrorCode::kNotFound, "mission '" + name + "' has no map " + std::to_string(map_id) + why +
                                           "; its maps: " + (held.empty() ? std::string("none yet") : held)};
  }
  return copyMap(*mission, *map, options);
}

Result<std::vector<MapSnapshot>> snapshotMission(const MissionRegistry& missions, const std::string& name,
                                                 const SnapshotOptions& options) {
  Status status;
  auto mission = findMission(missions, name, status);
  if (!mission) return status.error();
  std::vector<MapSnapshot> out;
  for (const auto& map : mission->stack().maps()) out.push_back(copyMap(*mission, *map, options));
  return out;
}

Result<MapChunker> MapChunker::create(MapSnapshot snapshot, std::size_t max_chunk_bytes) {
  if (max_chunk_bytes == 0) max_chunk_bytes = kDefaultChunkBytes;
  if (max_chunk_bytes < kMinChunkBytes || max_chunk_bytes > kMaxChunkBytes) {
    return Error{ErrorCode::kInvalidArgument, "max_chunk_bytes " + std::to_string(max_chunk_bytes) + " is outside " +
                                                  std::to_string(kMinChunkBytes) + " to " +
                                                  std::to_string(kMaxChunkBytes) +
                                                  " bytes (0 takes the default, 1 MiB)"};
  }
  return MapChunker(std::move(snapshot), max_chunk_bytes);
}

bool MapChunker::next(v1::MapChunk& chunk) {
  if (done_) return false;
  chunk.Clear();
  chunk.set_index(index_);
  if (index_ == 0) fillInfo(snapshot_, *chunk.mutable_map());
  ++index_;
  std::size_t bytes = chunk.ByteSizeLong() + 2;  // + the `last` flag
  // A repeated message field costs its tag, its length's varint and the message.
  const auto field_bytes = [](std::size_t n) { return n + 1 + (n < 128 ? 1 : n < 16384 ? 2 : n < 2097152 ? 3 : 5); };
  bool any = false;
  while (next_keyframe_ < snapshot_.keyframes.size()) {
    v1::MapKeyframe item;
    toMessage(snapshot_.keyframes[next_keyframe_], item);
    const std::size_t n = field_bytes(item.ByteSizeLong());
    if (any && bytes + n > max_bytes_) return true;
    *chunk.add_keyframes() = std::move(item);
    bytes += n;
    any = true;
    ++next_keyframe_;
  }
  while (next_point_ < snapshot_.points.size()) {
    v1::MapPointState item;
    toMessage(snapshot_.points[next_point_], snapshot_.descriptors, item);
    const std::size_t n = field_bytes(item.ByteSizeLong());
    if (any && bytes + n > max_bytes_) return true;
    *chunk.add_points() = std::move(item);
    bytes += n;
    any = true;
    ++next_point_;
  }
  chunk.set_last(true);
  done_ = true;
  return true;
}

}  // namespace cvislam::server::maps
