#include "server_cloud/ingest/batch_ingest.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::server {

namespace {

using Eigen::Vector3d;
using geometry::SE3d;

Error invalid(const std::string& what) {
  return Error{ErrorCode::kInvalidArgument, what};
}

// Where an object lives while the batch is checked: an existing server map, or the new map of an agent map
// index that this batch opens.
struct MapKey {
  bool is_new = false;
  std::uint32_t value = 0;  // MapId, or the agent map index when is_new
  friend bool operator==(const MapKey&, const MapKey&) = default;
};

struct PlannedKeyframe {
  ServerKeyframe keyframe;
  MapKey map;
};
struct PlannedPoint {
  ServerMapPoint point;
  MapKey map;
  std::uint32_t reference_counter = 0;
};
struct PlannedObservation {
  KeyframeId keyframe;
  std::uint16_t keypoint = 0;
  MapPointId point;
  MapKey map;
};
struct PlannedMerge {
  MapPointId drop;
  MapPointId keep;
  MapKey map;
};
struct PlannedKeyframeUpdate {
  std::uint32_t counter = 0;
  std::uint32_t agent_map = 0;
  wire::KeyframeStateValues state;
  MapKey map;
};
struct PlannedPointUpdate {
  std::uint32_t counter = 0;
  Vector3d p_w;
  MapKey map;
};

// What the batch does, checked and decoded, ready to apply.
struct Plan {
  std::vector<PlannedKeyframe> keyframes;
  std::vector<PlannedPoint> points;
  std::vector<PlannedObservation> observations;
  std::vector<PlannedMerge> merges;
  std::vector<PlannedKeyframeUpdate> keyframe_updates;
  std::vector<PlannedPointUpdate> point_updates;
  std::vector<std::pair<std::uint32_t, MapKey>> removed_points;
  std::vector<std::pair<std::uint32_t, MapKey>> removed_keyframes;
  std::vector<std::uint32_t> new_agent_maps;
};

// A keyframe as the checks see it: held, or new in this batch.
struct KnownKeyframe {
  MapKey map;
  std::uint32_t agent_map = 0;
  std::uint32_t keypoints = 0;
};

class Checker {
 public:
  Checker(AgentRecord& agent, const IngestLimits& limits, IngestReport& report)
      : agent_(agent), sensors_(*agent.sensors), limits_(limits), report_(report) {}

  Result<Plan> check(const v1::MapBatch& batch) {
    for (const v1::Keyframe& k : batch.keyframes()) {
      if (Status s = checkKeyframe(k); !s.ok()) return s.error();
    }
    for (const v1::MapPoint& p : batch.points()) {
      if (Status s = checkPoint(p); !s.ok()) return s.error();
    }
    for (const v1::Observations& o : batch.observations()) {
      if (Status s = checkObservations(o); !s.ok()) return s.error();
    }
    if (Status s = checkMerges(batch.merges()); !s.ok()) return s.error();
    for (const v1::KeyframeState& u : batch.keyframe_updates()) {
      if (Status s = checkKeyframeUpdate(u); !s.ok()) return s.error();
    }
    if (Status s = checkPointUpdates(batch.point_updates()); !s.ok()) return s.error();
    for (std::uint32_t c : batch.removed_points()) {
      auto p = livePoint(c, "removal");
      if (!p) return p.error();
      gone_points_.insert(c);
      plan_.removed_points.emplace_back(c, *p);
    }
    for (std::uint32_t c : batch.removed_keyframes()) {
      auto k = knownKeyframe(c, "removal");
      if (!k) return k.error();
      if (!removed_keyframes_.insert(c).second) return invalid(keyframeName(c) + " removed twice in one batch");
      plan_.removed_keyframes.emplace_back(c, k->map);
    }
    if (batch.has_live_pose()) {
      if (Status s = checkLivePose(batch.live_pose()); !s.ok()) return s.error();
    }
    return std::move(plan_);
  }

  // The pose is in no map, so any agent map goes; its numbers must make a pose.
  static Status checkLivePose(const v1::LivePose& pose) {
    if (pose.p_w_s_size() != 3 || pose.q_w_s_size() != 4) {
      return invalid("live pose: " + std::to_string(pose.p_w_s_size()) + " position and " +
                     std::to_string(pose.q_w_s_size()) + " orientation values (3 and 4 expected)");
    }
    double norm2 = 0.0;
    for (float v : pose.q_w_s()) {
      if (!std::isfinite(v)) return invalid("live pose: a non-finite orientation");
      norm2 += static_cast<double>(v) * static_cast<double>(v);
    }
    for (float v : pose.p_w_s()) {
      if (!std::isfinite(v)) return invalid("live pose: a non-finite position");
    }
    if (std::abs(norm2 - 1.0) > 1e-3) return invalid("live pose: the orientation is not a unit quaternion");
    return Status::Ok();
  }

 private:
  [[nodiscard]] KeyframeId keyframeId(std::uint32_t c) const { return KeyframeId{agent_.id, c}; }
  [[nodiscard]] MapPointId pointId(std::uint32_t c) const { return MapPointId{agent_.id, c}; }
  [[nodiscard]] std::string keyframeName(std::uint32_t c) const { return "keyframe " + keyframeId(c).toString(); }
  [[nodiscard]] std::string pointName(std::uint32_t c) const { return "map point " + pointId(c).toString(); }

  Result<KnownKeyframe> knownKeyframe(std::uint32_t c, const std::string& why) {
    if (removed_keyframes_.count(c) != 0) return invalid(why + ": " + keyframeName(c) + " was removed in this batch");
    if (auto it = new_keyframes_.find(c); it != new_keyframes_.end()) return it->second;
    if (auto it = agent_.keyframes.find(c); it != agent_.keyframes.end()) {
      return KnownKeyframe{MapKey{false, it->second.map}, it->second.agent_map, it->second.keypoints};
    }
    return invalid(why + " refers to " + keyframeName(c) + ", which the server never received");
  }

  // A point that exists at this stage of the batch (held or new, and not merged away or removed before).
  Result<MapKey> livePoint(std::uint32_t c, const std::string& why) {
    if (gone_points_.count(c) != 0) {
      return invalid(why + " refers to " + pointName(c) + ", which an earlier part of this batch removed");
    }
    if (auto it = new_points_.find(c); it != new_points_.end()) return it->second;
    if (auto it = agent_.points.find(c); it != agent_.points.end()) return MapKey{false, it->second};
    return invalid(why + " refers to " + pointName(c) + ", which the server never received");
  }

  Result<MapKey> mapOfAgentMap(std::uint32_t agent_map) {
    if (auto it = agent_.agent_maps.find(agent_map); it != agent_.agent_maps.end()) {
      return MapKey{false, it->second.map};
    }
    if (std::find(plan_.new_agent_maps.begin(), plan_.new_agent_maps.end(), agent_map) == plan_.new_agent_maps.end()) {
      if (agent_.agent_maps.size() + plan_.new_agent_maps.size() >= limits_.max_maps_per_agent) {
        return Error{ErrorCode::kResourceExhausted, "agent " + std::to_string(agent_.id) + " opens more than " +
                                                        std::to_string(limits_.max_maps_per_agent) + " maps"};
      }
      plan_.new_agent_maps.push_back(agent_map);
    }
    return MapKey{true, agent_map};
  }

  Status checkKeyframe(const v1::Keyframe& k) {
    const std::uint32_t c = k.counter();
    const std::string name = keyframeName(c);
    if (new_keyframes_.count(c) != 0) return invalid(name + " is sent in full twice in one batch");
    if (!k.has_state()) return invalid(name + ": no state");
    if (k.state().counter() != c) {
      return invalid(name + ": its state says keyframe " + std::to_string(k.state().counter()));
    }
    auto state = wire::fromProto(k.state(), name);
    if (!state) return state.error();
    if (k.t_ns() <= 0) return invalid(name + ": time " + std::to_string(k.t_ns()) + " ns is not positive");

    // Keypoints, column by column.
    const v1::Keypoints& kp = k.keypoints();
    const int n = kp.xy_size() / 2;
    if (kp.xy_size() % 2 != 0 || static_cast<int>(kp.octave().size()) != n ||
        static_cast<int>(kp.angle().size()) != n || kp.descriptors_size() != 4 * n) {
      return invalid(name + ": keypoint columns disagree (" + std::to_string(kp.xy_size()) + " coordinates, " +
                     std::to_string(kp.octave().size()) + " octaves, " + std::to_string(kp.angle().size()) +
                     " angles, " + std::to_string(kp.descriptors_size()) + " descriptor words)");
    }
    if (n > limits_.max_keypoints_per_keyframe) {
      return invalid(name + ": " + std::to_string(n) + " keypoints, more than the limit " +
                     std::to_string(limits_.max_keypoints_per_keyframe));
    }
    ServerKeyframe kf;
    kf.id = keyframeId(c);
    kf.agent_map = k.agent_map();
    kf.t_ns = k.t_ns();
    kf.awaiting_local_ba = k.before_local_ba();
    kf.T_w_s = state->T_w_s;
    kf.v_w = state->v_w;
    kf.bias = state->bias;
    kf.keypoints.resize(static_cast<std::size_t>(n));
    kf.descriptors.resize(static_cast<std::size_t>(n));
    const double w = sensors_.cam0.width();
    const double h = sensors_.cam0.height();
    for (int i = 0; i < n; ++i) {
      const float x = kp.xy(2 * i);
      const float y = kp.xy(2 * i + 1);
      if (!std::isfinite(x) || !std::isfinite(y) || x < -1.0F || y < -1.0F || static_cast<double>(x) > w + 1.0 ||
          static_cast<double>(y) > h + 1.0) {
        return invalid(name + ": keypoint " + std::to_string(i) + " at (" + std::to_string(x) + ", " +
                       std::to_string(y) + ") is outside the " + std::to_string(static_cast<int>(w)) + "x" +
                       std::to_string(static_cast<int>(h)) + " image");
      }
      const auto octave = static_cast<std::uint8_t>(kp.octave()[static_cast<std::size_t>(i)]);
      if (octave >= 32)
        return invalid(name + ": keypoint " + std::to_string(i) + " has octave " + std::to_string(octave));
      auto& out = kf.keypoints[static_cast<std::size_t>(i)];
      out.px = Eigen::Vector2f(x, y);
      out.octave = octave;
      out.angle_deg = wire::decodeAngle(static_cast<std::uint8_t>(kp.angle()[static_cast<std::size_t>(i)]));
      wire::unpackDescriptor(kp.descriptors().data() + 4 * i, kf.descriptors[static_cast<std::size_t>(i)].data());
    }
    kf.keypoints_undistorted.resize(static_cast<std::size_t>(n));
    for (std::size_t i = 0; i < kf.keypoints.size(); ++i) {
      kf.keypoints_undistorted[i] = sensors_.cam0.undistortPixel(kf.keypoints[i].px.cast<double>()).cast<float>();
    }

    // Stereo matches.
    const v1::StereoMatches& r = k.right();
    const int m = r.keypoint_size();
    if (r.xy_size() != 2 * m || static_cast<int>(r.octave().size()) != m) {
      return invalid(name + ": stereo match columns disagree");
    }
    if (m > 0 && sensors_.mode != SensorMode::kStereo) {
      return invalid(name + ": stereo matches from an agent that said it is monocular");
    }
    std::vector<std::uint8_t> has_right(static_cast<std::size_t>(n), 0);
    for (int i = 0; i < m; ++i) {
      const std::uint32_t index = r.keypoint(i);
      if (index >= static_cast<std::uint32_t>(n)) {
        return invalid(name + ": stereo match for keypoint " + std::to_string(index) + " of " + std::to_string(n));
      }
      if (has_right[index] != 0) return invalid(name + ": two stereo matches for keypoint " + std::to_string(index));
      has_right[index] = 1;
      const float x = r.xy(2 * i);
      const float y = r.xy(2 * i + 1);
      if (!std::isfinite(x) || !std::isfinite(y)) return invalid(name + ": a non-finite stereo match");
      kf.right.push_back({static_cast<std::uint16_t>(index), Eigen::Vector2f(x, y),
                          static_cast<std::uint8_t>(r.octave()[static_cast<std::size_t>(i)])});
    }

    // Raw IMU since the previous keyframe.
    const v1::ImuSamples& imu = k.imu();
    const int samples = imu.dt_ns_size();
    const std::int64_t columns = 3 * static_cast<std::int64_t>(samples);  // 64-bit: no overflow at any message size
    if (imu.gyro_size() != columns || imu.accel_size() != columns) {
      return invalid(name + ": IMU columns disagree (" + std::to_string(samples) + " times, " +
                     std::to_string(imu.gyro_size()) + " gyro and " + std::to_string(imu.accel_size()) +
                     " accelerometer values)");
    }
    if (samples > limits_.max_imu_samples_per_keyframe) {
      return invalid(name + ": " + std::to_string(samples) + " IMU samples, more than the limit " +
                     std::to_string(limits_.max_imu_samples_per_keyframe));
    }
    // Steps of at most 1000 s; only the first may go back (and t_ns > 0), so only a sum going up can overflow.
    constexpr std::int64_t kMaxStepNs = 1'000'000'000'000;
    std::int64_t t = k.t_ns();
    kf.imu.resize(static_cast<std::size_t>(samples));
    for (int i = 0; i < samples; ++i) {
      const std::int64_t dt = imu.dt_ns(i);
      if (dt > kMaxStepNs || dt < -kMaxStepNs || (i > 0 && dt <= 0)) {
        return invalid(name + ": IMU sample " + std::to_string(i) + " does not come after the one before it");
      }
      if (dt > 0 && t > std::numeric_limits<std::int64_t>::max() - dt) {
        return invalid(name + ": IMU sample " + std::to_string(i) + " is later than an int64 time in ns can be");
      }
      t += dt;
      dataset::ImuSample& s = kf.imu[static_cast<std::size_t>(i)];
      s.t_ns = t;
      for (int a = 0; a < 3; ++a) {
        s.gyro_s[a] = imu.gyro(3 * i + a);
        s.accel_s[a] = imu.accel(3 * i + a);
      }
      if (!s.gyro_s.allFinite() || !s.accel_s.allFinite()) return invalid(name + ": a non-finite IMU sample");
    }
    if (k.has_imu_from()) {
      if (k.imu_from() == c) return invalid(name + ": its IMU link starts at itself");
      kf.imu_from = keyframeId(k.imu_from());
    }

    if (agent_.keyframes.count(c) != 0) {
      ++report_.duplicate_objects;  // held already: a resend; dropped (and it opens no map)
      return Status::Ok();
    }
    auto map = mapOfAgentMap(k.agent_map());
    if (!map) return map.error();
    new_keyframes_[c] = KnownKeyframe{*map, k.agent_map(), static_cast<std::uint32_t>(n)};
    plan_.keyframes.push_back({std::move(kf), *map});
    return Status::Ok();
  }

  Status checkPoint(const v1::MapPoint& p) {
    const std::uint32_t c = p.counter();
    const std::string name = pointName(c);
    if (new_points_.count(c) != 0) return invalid(name + " is sent in full twice in one batch");
    if (Status s = wire::checkFinite(p.p_w(), 3, name + " p_w"); !s.ok()) return s;
    if (Status s = wire::checkPosition(Vector3d(p.p_w(0), p.p_w(1), p.p_w(2)), name + " p_w", wire::kMaxPointDistanceM);
        !s.ok()) {
      return s;
    }
    if (p.orb_size() != 4) {
      return invalid(name + ": descriptor of " + std::to_string(p.orb_size()) + " words, expected 4 (32 bytes)");
    }
    if (p.octave() >= 32) return invalid(name + ": octave " + std::to_string(p.octave()));
    auto reference = knownKeyframe(p.reference_keyframe(), name);
    if (!reference) return reference.error();
    if (agent_.points.count(c) != 0) {
      ++report_.duplicate_objects;
      return Status::Ok();
    }
    ServerMapPoint point;
    point.id = pointId(c);
    point.reference = keyframeId(p.reference_keyframe());
    point.p_w = Vector3d(p.p_w(0), p.p_w(1), p.p_w(2));
    wire::unpackDescriptor(p.orb().data(), point.descriptor.data());
    point.octave = static_cast<std::uint8_t>(p.octave());
    new_points_[c] = reference->map;
    point_agent_map_[c] = reference->agent_map;
    plan_.points.push_back({std::move(point), reference->map, p.reference_keyframe()});
    return Status::Ok();
  }

  Status checkObservations(const v1::Observations& o) {
    const std::string name = "observations of " + keyframeName(o.keyframe());
    if (o.keypoint_size() != o.point_size()) {
      return invalid(name + ": " + std::to_string(o.keypoint_size()) + " keypoints but " +
                     std::to_string(o.point_size()) + " points");
    }
    auto kf = knownKeyframe(o.keyframe(), name);
    if (!kf) return kf.error();
    for (int i = 0; i < o.keypoint_size(); ++i) {
      if (o.keypoint(i) >= kf->keypoints) {
        return invalid(name + ": keypoint " + std::to_string(o.keypoint(i)) + " of " + std::to_string(kf->keypoints));
      }
      auto map = livePoint(o.point(i), name);
      if (!map) return map.error();
      if (!(*map == kf->map)) {
        return invalid(name + ": " + pointName(o.point(i)) + " is in another map than the keyframe");
      }
      plan_.observations.push_back(
          {keyframeId(o.keyframe()), static_cast<std::uint16_t>(o.keypoint(i)), pointId(o.point(i)), kf->map});
    }
    return Status::Ok();
  }

  Status checkMerges(const v1::PointMerges& merges) {
    if (merges.drop_size() != merges.keep_size()) return invalid("merges: drop and keep lists differ in length");
    for (int i = 0; i < merges.drop_size(); ++i) {
      const std::uint32_t drop = merges.drop(i);
      const std::uint32_t keep = merges.keep(i);
      if (drop == keep) return invalid("merge of " + pointName(drop) + " into itself");
      auto d = livePoint(drop, "merge");
      if (!d) return d.error();
      auto k = livePoint(keep, "merge");
      if (!k) return k.error();
      if (!(*d == *k)) return invalid("merge of " + pointName(drop) + " into " + pointName(keep) + " across maps");
      gone_points_.insert(drop);
      plan_.merges.push_back({pointId(drop), pointId(keep), *d});
    }
    return Status::Ok();
  }

  Status checkKeyframeUpdate(const v1::KeyframeState& u) {
    const std::string name = "update of " + keyframeName(u.counter());
    auto kf = knownKeyframe(u.counter(), name);
    if (!kf) return kf.error();
    auto state = wire::fromProto(u, name);
    if (!state) return state.error();
    plan_.keyframe_updates.push_back({u.counter(), kf->agent_map, *state, kf->map});
    return Status::Ok();
  }

  Status checkPointUpdates(const v1::PointPositions& u) {
    if (u.p_w_size() != 3 * static_cast<std::int64_t>(u.point_size())) {
      return invalid("point updates: " + std::to_string(u.point_size()) + " points but " +
                     std::to_string(u.p_w_size()) + " coordinates");
    }
    for (int i = 0; i < u.point_size(); ++i) {
      const std::uint32_t c = u.point(i);
      auto map = livePoint(c, "point update");
      if (!map) return map.error();
      const Vector3d p(u.p_w(3 * i), u.p_w(3 * i + 1), u.p_w(3 * i + 2));
      if (Status s = wire::checkPosition(p, "update of " + pointName(c), wire::kMaxPointDistanceM); !s.ok()) return s;
      plan_.point_updates.push_back({c, p, *map});
    }
    return Status::Ok();
  }

 public:
  // The agent map of a point that is new in this batch (for its frame transform).
  [[nodiscard]] std::uint32_t agentMapOfNewPoint(std::uint32_t c) const { return point_agent_map_.at(c); }

 private:
  AgentRecord& agent_;
  const AgentSensors& sensors_;
  const IngestLimits& limits_;
  IngestReport& report_;
  Plan plan_;
  std::unordered_map<std::uint32_t, KnownKeyframe> new_keyframes_;
  std::unordered_map<std::uint32_t, MapKey> new_points_;
  std::unordered_map<std::uint32_t, std::uint32_t> point_agent_map_;
  std::unordered_set<std::uint32_t> gone_points_;
  std::unordered_set<std::uint32_t> removed_keyframes_;
};

// T_m_w applied to a state given in the agent's world frame.
void toMapFrame(const SE3d& T_m_w, wire::KeyframeStateValues& state) {
  state.T_w_s = T_m_w * state.T_w_s;
  state.v_w = T_m_w.so3() * state.v_w;
}

}  // namespace

std::string storedBody(const v1::MapBatch& batch) {
  if (!batch.has_live_pose()) return batch.SerializeAsString();
  v1::MapBatch copy(batch);
  copy.clear_live_pose();
  return copy.SerializeAsString();
}

Result<IngestReport> ingestBatch(const v1::MapBatch& batch, AgentRecord& agent, MapStack& stack,
                                 const IngestLimits& limits, const std::function<Status()>& commit) {
  if (!agent.sensors) return Error{ErrorCode::kFailedPrecondition, "a map batch before the Hello"};
  IngestReport report;
  Checker checker(agent, limits, report);
  auto checked = checker.check(batch);
  if (!checked) return checked.error();
  Plan& plan = *checked;
  if (commit) {
    if (Status s = commit(); !s.ok()) return s.error();
  }

  // Everything is checked: from here on nothing fails. New agent maps get new server maps.
  if (batch.has_live_pose()) {
    const v1::LivePose& p = batch.live_pose();
    const auto d = [](float v) { return static_cast<double>(v); };
    const Eigen::Quaterniond q(d(p.q_w_s(3)), d(p.q_w_s(0)), d(p.q_w_s(1)), d(p.q_w_s(2)));
    const Eigen::Vector3d p_w_s(d(p.p_w_s(0)), d(p.p_w_s(1)), d(p.p_w_s(2)));
    agent.live_pose = AgentRecord::LivePose{p.t_ns(), p.agent_map(), SE3d(q, p_w_s), p.metric()};
  }
  for (std::uint32_t agent_map : plan.new_agent_maps) {
    agent.agent_maps[agent_map] = AgentRecord::AgentMap{stack.createMap(MapOrigin{agent.id, agent_map})->id(), SE3d()};
    ++report.maps_opened;
  }
  const auto resolve = [&](const MapKey& key) -> MapId {
    return key.is_new ? agent.agent_maps.at(key.value).map : key.value;
  };
  const auto frameOf = [&](std::uint32_t agent_map) -> SE3d {
    auto it = agent.agent_maps.find(agent_map);
    return it == agent.agent_maps.end() ? SE3d() : it->second.T_m_w;
  };

  // Lock every map the batch touches, in id order.
  std::map<MapId, std::shared_ptr<ServerMap>> touched;
  const auto touch = [&](const MapKey& key) {
    const MapId id = resolve(key);
    if (touched.count(id) == 0) touched[id] = stack.find(id);
  };
  for (const auto& k : plan.keyframes) touch(k.map);
  for (const auto& p : plan.points) touch(p.map);
  for (const auto& o : plan.observations) touch(o.map);
  for (const auto& m : plan.merges) touch(m.map);
  for (const auto& u : plan.keyframe_updates) touch(u.map);
  for (const auto& u : plan.point_updates) touch(u.map);
  for (const auto& r : plan.removed_points) touch(r.second);
  for (const auto& r : plan.removed_keyframes) touch(r.second);
  std::vector<decltype(std::declval<ServerMap&>().write())> locks;
  std::unordered_map<MapId, MapContent*> content;
  locks.reserve(touched.size());
  const auto locking_from = std::chrono::steady_clock::now();
  for (auto& [id, map] : touched) {
    if (!map) return Error{ErrorCode::kInternal, "server map " + std::to_string(id) + " vanished"};
    locks.push_back(map->write());
    content[id] = &*locks.back();
  }
  report.map_lock_wait_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - locking_from).count();
  const auto mapOf = [&](const MapKey& key) -> MapContent& { return *content.at(resolve(key)); };

  for (auto& planned : plan.keyframes) {
    ServerKeyframe& kf = planned.keyframe;
    wire::KeyframeStateValues state{kf.T_w_s, kf.v_w, kf.bias};
    toMapFrame(frameOf(kf.agent_map), state);
    kf.T_w_s = state.T_w_s;
    kf.v_w = state.v_w;
    const std::uint32_t keypoints = static_cast<std::uint32_t>(kf.keypoints.size());
    const std::uint32_t counter = kf.id.counter;
    const std::uint32_t agent_map = kf.agent_map;
    MapContent& map = mapOf(planned.map);
    // Its IMU link, rebuilt from the raw samples when the predecessor is in the same map.
    if (kf.imu_from) {
      const ServerKeyframe* previous = map.keyframe(*kf.imu_from);
      if (previous != nullptr && agent.sensors->uses_imu) {
        imu::Preintegration preintegration(previous->bias, agent.sensors->imu_noise);
        if (preintegration.integrateInterval(kf.imu, previous->t_ns, kf.t_ns).ok()) {
          kf.preintegration = preintegration;
        }
      }
      if (!kf.preintegration) {
        kf.imu_from.reset();
        ++report.imu_links_missing;
      }
    }
    const bool awaiting = kf.awaiting_local_ba;
    (void)map.addKeyframe(std::move(kf));
    report.added_keyframes.emplace_back(map.id(), KeyframeId{agent.id, counter});
    if (!awaiting) report.keyframes_ready.emplace_back(map.id(), KeyframeId{agent.id, counter});
    agent.keyframes[counter] = AgentRecord::HeldKeyframe{map.id(), agent_map, keypoints};
    ++report.keyframes;
  }
  for (auto& planned : plan.points) {
    const SE3d T_m_w = frameOf(checker.agentMapOfNewPoint(planned.point.id.counter));
    planned.point.p_w = T_m_w * planned.point.p_w;
    const std::uint32_t counter = planned.point.id.counter;
    MapContent& map = mapOf(planned.map);
    (void)map.addPoint(std::move(planned.point));
    agent.points[counter] = map.id();
    ++report.points;
  }
  for (const auto& o : plan.observations) {
    if (mapOf(o.map).addObservation(o.keyframe, o.keypoint, o.point).ok()) {
      ++report.observations;
    } else {
      ++report.observations_refused;
    }
  }
  for (const auto& m : plan.merges) {
    (void)mapOf(m.map).mergePoints(m.drop, m.keep);
    agent.points.erase(m.drop.counter);
    ++report.merges;
  }
  for (auto& u : plan.keyframe_updates) {
    toMapFrame(frameOf(u.agent_map), u.state);
    if (ServerKeyframe* kf = mapOf(u.map).keyframe(KeyframeId{agent.id, u.counter})) {
      kf->T_w_s = u.state.T_w_s;
      kf->v_w = u.state.v_w;
      kf->bias = u.state.bias;
      kf->refined = false;  // the agent's estimate again
      kf->provisional = false;
      if (kf->awaiting_local_ba) {
        kf->awaiting_local_ba = false;
        report.keyframes_ready.emplace_back(mapOf(u.map).id(), kf->id);
      }
      ++report.keyframe_updates;
    }
  }
  for (const auto& u : plan.point_updates) {
    MapContent& map = mapOf(u.map);
    if (ServerMapPoint* p = map.point(MapPointId{agent.id, u.counter})) {
      const ServerKeyframe* reference = map.keyframe(p->reference);
      const SE3d T_m_w = reference != nullptr ? frameOf(reference->agent_map) : SE3d();
      p->p_w = T_m_w * u.p_w;
      ++report.point_updates;
    }
  }
  for (const auto& [c, key] : plan.removed_points) {
    (void)mapOf(key).removePoint(MapPointId{agent.id, c});
    agent.points.erase(c);
    ++report.removed_points;
  }
  for (const auto& [c, key] : plan.removed_keyframes) {
    MapContent& map = mapOf(key);
    std::vector<MapPointId> went;  // points that went with it (no observer left)
    (void)map.removeKeyframe(KeyframeId{agent.id, c}, &went);
    agent.keyframes.erase(c);
    report.removed_keyframe_ids.push_back(KeyframeId{agent.id, c});
    report.removed_keyframe_maps.push_back(map.id());
    for (const MapPointId& p : went) {
      if (p.agent == agent.id) agent.points.erase(p.counter);
    }
    ++report.removed_keyframes;
  }
  return report;
}

}  // namespace cvislam::server
