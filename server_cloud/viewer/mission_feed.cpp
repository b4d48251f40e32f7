#include "server_cloud/viewer/mission_feed.hpp"

#include <algorithm>
#include <cmath>
#include <set>
#include <utility>

#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::server::viewer {

using geometry::SE3d;

struct MissionFeed::CapturedAgent {
  AgentId id = 0;
  bool connected = false;
  std::optional<AgentRecord::LivePose> live;
  std::map<std::uint32_t, AgentRecord::AgentMap> agent_maps;
  std::uint64_t keyframes = 0;
  std::uint64_t up_bytes = 0;
  std::uint64_t down_bytes = 0;
};

struct MissionFeed::Captured {
  struct Keyframe {
    std::uint32_t map = 0;
    std::uint32_t agent_map = 0;
    std::int64_t t_ns = 0;
    SE3d T_m_s;
    std::vector<KeyframeId> links;
  };
  struct Map {
    std::uint64_t signature = 0;
    std::size_t keyframes = 0;
    std::size_t points = 0;
    std::vector<AgentId> agents;
    std::optional<std::vector<Eigen::Vector3f>> cloud;  // when due
  };
  std::map<KeyframeId, Keyframe> keyframes;
  std::map<std::uint32_t, Map> maps;
  std::vector<CapturedAgent> agents;
};

namespace {

using Captured = MissionFeed::Captured;

// The keyframe's IMU predecessor and its strongest older covisible keyframes: each link is drawn once, by the newer
// of its two keyframes.
std::vector<KeyframeId> linksOf(const MapContent& content, const ServerKeyframe& kf, std::size_t covisible_links) {
  std::vector<KeyframeId> links;
  if (kf.imu_from && content.keyframes().count(*kf.imu_from) != 0) links.push_back(*kf.imu_from);
  std::vector<std::pair<int, KeyframeId>> older;
  for (const auto& [other, weight] : content.covisible(kf.id)) {
    if (other < kf.id && (!kf.imu_from || other != *kf.imu_from)) older.emplace_back(weight, other);
  }
  const std::size_t n = std::min(covisible_links, older.size());
  std::partial_sort(
      older.begin(), older.begin() + static_cast<std::ptrdiff_t>(n), older.end(),
      [](const auto& a, const auto& b) { return a.first > b.first || (a.first == b.first && a.second < b.second); });
  for (std::size_t i = 0; i < n; ++i) links.push_back(older[i].second);
  return links;
}

// A fixed subset of about `budget` of the map's points, chosen by id so that the same points stay drawn.
std::vector<Eigen::Vector3f> decimatedCloud(const MapContent& content, std::size_t budget) {
  const std::size_t total = content.points().size();
  const double keep = total <= budget ? 1.0 : static_cast<double>(budget) / static_cast<double>(total);
  constexpr std::uint64_t kBuckets = 1000003;
  const auto threshold = static_cast<std::uint64_t>(keep * kBuckets);
  std::vector<Eigen::Vector3f> cloud;
  cloud.reserve(std::min(total, budget));
  for (const auto& [id, point] : content.points()) {
    if (cloud.size() >= budget) break;
    // A multiplicative hash spreads the (agent, counter) ids over the buckets.
    const std::uint64_t h = ((std::uint64_t{id.agent} << 32U) ^ id.counter) * 0x9E3779B97F4A7C15ULL;
    if (keep < 1.0 && (h >> 20U) % kBuckets >= threshold) continue;
    cloud.emplace_back(point.p_w.cast<float>());
  }
  return cloud;
}

bool moved(const SE3d& a, const SE3d& b, double metres, double degrees) {
  if ((a.translation() - b.translation()).norm() > metres) return true;
  const double angle = a.so3().quaternion().angularDistance(b.so3().quaternion());
  return angle * 180.0 / M_PI > degrees;
}

std::vector<Eigen::Vector3d> segmentsOf(const KeyframeId& id, const std::vector<KeyframeId>& links,
                                        const std::map<KeyframeId, Captured::Keyframe>& keyframes) {
  std::vector<Eigen::Vector3d> segments;
  const Eigen::Vector3d from = keyframes.at(id).T_m_s.translation();
  for (const KeyframeId& other : links) {
    auto it = keyframes.find(other);
    if (it == keyframes.end()) continue;
    segments.push_back(from);
    segments.push_back(it->second.T_m_s.translation());
  }
  return segments;
}

}  // namespace

Status FeedOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "viewer: " + what}; };
  if (max_points_per_map > 5000000) return bad("points per map must be at most 5000000");
  if (covisible_links > 64) return bad("covisible links must be at most 64");
  if (links_every_looks < 1 || links_every_looks > 1000) return bad("links every looks must be in [1, 1000]");
  if (!(moved_m >= 0.0) || !(moved_deg >= 0.0)) return bad("the move thresholds must be >= 0");
  if (!(points_period_s >= 0.0) || !(stats_period_s >= 0.0) || !(trajectory_period_s >= 0.0)) {
    return bad("the periods must be >= 0");
  }
  return Status::Ok();
}

MissionFeed::MissionFeed(std::string mission, FeedOptions options) : mission_(std::move(mission)), options_(options) {
  events_channel_ = channel("/" + mission_ + "/events", kLogSchema);
  stats_channel_ = channel("/" + mission_ + "/stats", kMissionStatsSchema);
  scene_channel_ = channel("/" + mission_ + "/keyframes", kSceneUpdateSchema);
  tf_channel_ = channel("/" + mission_ + "/tf", kFrameTransformSchema);
}

std::string MissionFeed::mapFrame(std::uint32_t map) const {
  return mission_ + "/map" + std::to_string(map);
}

std::string MissionFeed::agentWorldFrame(AgentId agent, std::uint32_t agent_map) const {
  return mission_ + "/agent" + std::to_string(agent) + "/world" + std::to_string(agent_map);
}

std::size_t MissionFeed::channel(const std::string& topic, const char* schema_name) {
  auto it = channel_by_topic_.find(topic);
  if (it != channel_by_topic_.end()) return it->second;
  channels_.push_back({topic, schema_name});
  channel_by_topic_[topic] = channels_.size() - 1;
  return channels_.size() - 1;
}

void MissionFeed::keep(FeedMessage message, std::vector<FeedMessage>& out) {
  newest_[message.channel] = message;
  out.push_back(std::move(message));
}

const std::vector<KeyframeId>& MissionFeed::linksFor(const MapContent& content, const ServerKeyframe& kf) {
  auto it = links_.find(kf.id);
  const bool turn = (looks_ + kf.id.counter + 7U * kf.id.agent) % options_.links_every_looks == 0;
  const auto gone = [&](const KeyframeId& link) { return content.keyframe(link) == nullptr; };
  if (it == links_.end() || turn || std::any_of(it->second.begin(), it->second.end(), gone)) {
    ++link_lookups_;
    it = links_.insert_or_assign(kf.id, linksOf(content, kf, options_.covisible_links)).first;
  }
  return it->second;
}

void MissionFeed::update(const Mission& mission, std::int64_t t_unix_ns, Clock::time_point now,
                         std::vector<FeedMessage>& out) {
  ++looks_;
  Captured captured;
  for (const auto& map : mission.stack().maps()) {
    Captured::Map& m = captured.maps[map->id()];
    const auto last = points_sent_at_.find(map->id());
    const bool cloud_may_go =
        last == points_sent_at_.end() || now - last->second >= std::chrono::duration<double>(options_.points_period_s);
    auto content = map->read();
    m.agents.assign(content->agents().begin(), content->agents().end());
    m.keyframes = content->keyframes().size();
    m.points = content->points().size();
    // What the cloud depends on: how many points, and where the keyframes that carry them are (to the mm).
    std::uint64_t signature = m.points * 1000003ULL + m.keyframes;
    for (const auto& [id, kf] : content->keyframes()) {
      Captured::Keyframe& k = captured.keyframes[id];
      k.map = map->id();
      k.agent_map = kf.agent_map;
      k.t_ns = kf.t_ns;
      k.T_m_s = kf.T_w_s;
      k.links = linksFor(*content, kf);
      const Eigen::Vector3d& p = kf.T_w_s.translation();
      signature +=
          static_cast<std::uint64_t>(std::llround(1000.0 * (std::abs(p.x()) + std::abs(p.y()) + std::abs(p.z()))));
    }
    m.signature = signature;
    const auto sent = points_signature_.find(map->id());
    if (cloud_may_go && (sent == points_signature_.end() || sent->second != signature)) {
      m.cloud = decimatedCloud(*content, options_.max_points_per_map);
    }
  }
  for (const auto& shared : mission.agents()) {
    auto record = shared->read();
    CapturedAgent& a = captured.agents.emplace_back();
    a.id = record->id;
    a.connected = record->connected;
    a.live = record->live_pose;
    a.agent_maps = record->agent_maps;
    a.keyframes = record->serverKeyframes();
    for (const auto& [kind, count] : record->up) {
      if (kind == "message") a.up_bytes = count.bytes;
    }
    for (const auto& [kind, count] : record->down) {
      if (kind == "message") a.down_bytes = count.bytes;
    }
  }

  std::erase_if(links_, [&](const auto& entry) { return captured.keyframes.count(entry.first) == 0; });
  sendEvents(mission, t_unix_ns, out);
  sendKeyframes(captured, t_unix_ns, out);
  for (auto& [map, m] : captured.maps) {
    if (!m.cloud) continue;
    const std::size_t c = channel("/" + mission_ + "/map" + std::to_string(map) + "/points", kPointCloudSchema);
    keep({c, t_unix_ns, pointCloud(t_unix_ns, mapFrame(map), *m.cloud)}, out);
    points_signature_[map] = m.signature;
    points_sent_at_[map] = now;
  }
  sendAgents(captured, t_unix_ns, now, out);
  if (!stats_sent_at_ || now - *stats_sent_at_ >= std::chrono::duration<double>(options_.stats_period_s)) {
    MissionStatsMessage stats;
    for (const auto& a : captured.agents) {
      std::uint32_t map = 0;
      if (!a.agent_maps.empty()) map = a.agent_maps.rbegin()->second.map;
      stats.agents.push_back({a.id, a.connected, map, a.keyframes, a.up_bytes, a.down_bytes});
    }
    for (const auto& [id, m] : captured.maps) stats.maps.push_back({id, m.keyframes, m.points, m.agents});
    keep({stats_channel_, t_unix_ns, missionStats(t_unix_ns, stats)}, out);
    stats_sent_at_ = now;
  }
}

void MissionFeed::sendKeyframes(const Captured& now, std::int64_t t_ns, std::vector<FeedMessage>& out) {
  // Moved, came or changed map: those, and every keyframe linked to one of them (its segments end there).
  std::set<KeyframeId> changed;
  for (const auto& [id, k] : now.keyframes) {
    auto it = drawn_.find(id);
    if (it == drawn_.end() || it->second.entity.map != k.map || it->second.links != k.links ||
        moved(it->second.entity.T_frame_body, k.T_m_s, options_.moved_m, options_.moved_deg)) {
      changed.insert(id);
    }
  }
  std::vector<std::string> deleted;
  for (auto it = drawn_.begin(); it != drawn_.end();) {
    if (now.keyframes.count(it->first) == 0) {
      deleted.push_back(keyframeEntityId(it->first));
      it = drawn_.erase(it);
    } else {
      ++it;
    }
  }
  std::set<KeyframeId> dirty = changed;
  for (const auto& [id, k] : now.keyframes) {
    for (const KeyframeId& other : k.links) {
      if (changed.count(other) != 0) dirty.insert(id);
    }
  }
  if (dirty.empty() && deleted.empty()) return;
  std::vector<KeyframeEntity> entities;
  entities.reserve(dirty.size());
  for (const KeyframeId& id : dirty) {
    const Captured::Keyframe& k = now.keyframes.at(id);
    DrawnKeyframe& d = drawn_[id];
    d.entity = KeyframeEntity{id, k.map, mapFrame(k.map), k.T_m_s, segmentsOf(id, k.links, now.keyframes)};
    d.links = k.links;
    entities.push_back(d.entity);
  }
  out.push_back({scene_channel_, t_ns, sceneUpdate(t_ns, entities, deleted)});
}

void MissionFeed::sendAgents(const Captured& now, std::int64_t t_ns, Clock::time_point at,
                             std::vector<FeedMessage>& out) {
  const auto trajectories = trajectoriesOf(now);
  for (const CapturedAgent& a : now.agents) {
    sendWorldFrames(a, t_ns, out);
    if (auto t = trajectories.find(a.id); t != trajectories.end()) sendTrajectory(a.id, t->second, t_ns, at, out);
    sendLivePose(a, t_ns, out);
  }
}

// Each agent's keyframes by time, in the map that holds its newest keyframe.
std::map<AgentId, MissionFeed::Trajectory> MissionFeed::trajectoriesOf(const Captured& now) {
  std::map<AgentId, std::pair<std::int64_t, std::uint32_t>> newest;  // time and map of each agent's newest
  for (const auto& [id, k] : now.keyframes) {
    auto it = newest.find(id.agent);
    if (it == newest.end() || k.t_ns > it->second.first) newest[id.agent] = {k.t_ns, k.map};
  }
  std::map<AgentId, std::vector<std::pair<std::int64_t, SE3d>>> timed;
  for (const auto& [id, k] : now.keyframes) {
    if (k.map == newest.at(id.agent).second) timed[id.agent].emplace_back(k.t_ns, k.T_m_s);
  }
  std::map<AgentId, Trajectory> out;
  for (auto& [agent, poses] : timed) {
    std::sort(poses.begin(), poses.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
    Trajectory& t = out[agent];
    t.map = newest.at(agent).second;
    for (const auto& [time, T] : poses) t.T_m_s.push_back(T);
  }
  return out;
}

// Where each of the agent's maps is in its server map.
void MissionFeed::sendWorldFrames(const CapturedAgent& a, std::int64_t t_ns, std::vector<FeedMessage>& out) {
  for (const auto& [agent_map, held] : a.agent_maps) {
    const std::string child = agentWorldFrame(a.id, agent_map);
    auto it = frames_sent_.find(child);
    if (it != frames_sent_.end() &&
        !moved(it->second.T_parent_child, held.T_m_w, options_.moved_m, options_.moved_deg)) {
      continue;
    }
    FeedMessage message{tf_channel_, t_ns, frameTransform(t_ns, mapFrame(held.map), child, held.T_m_w)};
    out.push_back(message);
    frames_sent_[child] = {held.T_m_w, std::move(message)};
  }
}

void MissionFeed::sendTrajectory(AgentId agent, const Trajectory& now, std::int64_t t_ns, Clock::time_point at,
                                 std::vector<FeedMessage>& out) {
  // The whole trajectory goes each time (a PosesInFrame replaces the last): at most once a period.
  if (auto last = trajectory_sent_at_.find(agent);
      last != trajectory_sent_at_.end() &&
      at - last->second < std::chrono::duration<double>(options_.trajectory_period_s)) {
    return;
  }
  Trajectory& sent = trajectory_sent_[agent];
  bool changed = sent.map != now.map || sent.T_m_s.size() != now.T_m_s.size();
  for (std::size_t i = 0; !changed && i < now.T_m_s.size(); ++i) {
    changed = moved(sent.T_m_s[i], now.T_m_s[i], options_.moved_m, options_.moved_deg);
  }
  if (!changed) return;
  const std::size_t c = channel("/" + mission_ + "/agent" + std::to_string(agent) + "/trajectory", kPosesInFrameSchema);
  keep({c, t_ns, posesInFrame(t_ns, mapFrame(now.map), now.T_m_s)}, out);
  sent = now;
  trajectory_sent_at_[agent] = at;
}

// The newest tracked pose the agent's batches brought, in its server map's frame; once per pose.
void MissionFeed::sendLivePose(const CapturedAgent& a, std::int64_t t_ns, std::vector<FeedMessage>& out) {
  if (!a.live) return;
  auto held = a.agent_maps.find(a.live->agent_map);
  if (held == a.agent_maps.end()) return;  // that map has not reached the server yet
  auto sent = pose_sent_t_ns_.find(a.id);
  if (sent != pose_sent_t_ns_.end() && sent->second == a.live->t_ns) return;
  pose_sent_t_ns_[a.id] = a.live->t_ns;
  const std::size_t c = channel("/" + mission_ + "/agent" + std::to_string(a.id) + "/pose", kPoseInFrameSchema);
  keep({c, t_ns, poseInFrame(t_ns, mapFrame(held->second.map), held->second.T_m_w * a.live->T_w_s)}, out);
}

void MissionFeed::sendEvents(const Mission& mission, std::int64_t t_ns, std::vector<FeedMessage>& out) {
  static constexpr std::size_t kPageEvents = 4096;
  static constexpr std::size_t kRecentEvents = 100;
  const MissionEventLog::Page page = mission.events().read(next_event_, kPageEvents);
  next_event_ = page.next;
  // Keyframes come and go all the time: one line per agent and cause for this look, not one per keyframe.
  std::map<std::pair<AgentId, std::string>, std::uint32_t> removed;
  std::vector<std::pair<LogLevel, std::string>> lines;
  if (page.skipped > 0) {
    lines.emplace_back(LogLevel::kWarning, std::to_string(page.skipped) + " events missed (the log moved on)");
  }
  for (const MissionEvent& e : page.events) {
    const std::string agent = "agent " + std::to_string(e.agent);
    switch (e.kind) {
      case MissionEvent::Kind::kAgentConnected:
        lines.emplace_back(LogLevel::kInfo, agent + " joined");
        break;
      case MissionEvent::Kind::kAgentDisconnected:
        lines.emplace_back(LogLevel::kInfo, agent + " left");
        break;
      case MissionEvent::Kind::kKeyframeAdded:
        break;  // the scene shows them
      case MissionEvent::Kind::kKeyframeRemoved:
        ++removed[{e.agent, e.cause}];
        break;
      case MissionEvent::Kind::kMapsMerged:
        lines.emplace_back(LogLevel::kInfo,
                           "map " + std::to_string(e.from_map) + " merged into map " + std::to_string(e.map));
        break;
      case MissionEvent::Kind::kMapCorrected:
        lines.emplace_back(LogLevel::kInfo, e.cause + " applied to map " + std::to_string(e.map) + ": " +
                                                std::to_string(e.keyframes) + " keyframes moved");
        break;
    }
  }
  for (const auto& [key, count] : removed) {
    lines.emplace_back(LogLevel::kInfo, "agent " + std::to_string(key.first) + ": " + std::to_string(count) +
                                            (count == 1 ? " keyframe" : " keyframes") + " removed (" + key.second +
                                            ")");
  }
  for (const auto& [level, line] : lines) {
    FeedMessage message{events_channel_, t_ns, logMessage(t_ns, level, line)};
    recent_events_.push_back(message);
    out.push_back(std::move(message));
  }
  if (recent_events_.size() > kRecentEvents) {
    recent_events_.erase(recent_events_.begin(),
                         recent_events_.begin() + static_cast<std::ptrdiff_t>(recent_events_.size() - kRecentEvents));
  }
}

void MissionFeed::fullState(std::vector<FeedMessage>& out) const {
  out.insert(out.end(), recent_events_.begin(), recent_events_.end());
  std::vector<KeyframeEntity> entities;
  entities.reserve(drawn_.size());
  std::int64_t t_ns = 0;
  for (const auto& [id, d] : drawn_) entities.push_back(d.entity);
  for (const auto& [c, m] : newest_) t_ns = std::max(t_ns, m.t_unix_ns);
  if (!entities.empty()) out.push_back({scene_channel_, t_ns, sceneUpdate(t_ns, entities, {})});
  for (const auto& [child, sent] : frames_sent_) out.push_back(sent.message);
  for (const auto& [c, m] : newest_) out.push_back(m);
}

}  // namespace cvislam::server::viewer
