// Test helpers for the link: map deltas written by hand from a small model of the local map, and the server's
// real core (an AgentSession, no gRPC) to deliver batches to.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/messages/conversions.hpp"
#include "agent_rt/messages/messages.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"
#include "server_cloud/core/server_core.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/support/delta_queue.hpp"

namespace cvislam::agent::test {

inline constexpr AgentId kAgent = 3;
inline constexpr std::int64_t kStartNs = 1'600'000'000'000'000'000;
inline constexpr std::int64_t kKeyframeStepNs = 250'000'000;  // 0.25 s between keyframes

// A local map as the tests drive it, and the deltas mapping would write for it.
class DeltaWriter {
 public:
  struct Keyframe {
    std::int64_t t_ns = 0;
    Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
    std::map<std::uint16_t, std::uint32_t> observations;  // keypoint -> point counter
  };
  struct Point {
    std::uint32_t reference = 0;
    Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
  };

  DeltaWriter() : delta_(std::make_unique<MapDeltaMessage>()) {}

  std::map<std::uint32_t, Keyframe> keyframes;  // in the local map now
  std::map<std::uint32_t, Point> points;
  std::uint32_t map_id = 0;
  bool ready = false;
  static constexpr int kKeypoints = 60;

  // Starts the delta of a new keyframe `counter` (0.25 s after the previous), linked by IMU to the previous
  // keyframe when there is one; it observes `observed` (keypoint i -> point counter) and makes `new_points`
  // (keypoint observed.size() + i), each at 3 m in front.
  MapDeltaMessage& addKeyframe(std::uint32_t counter, const std::vector<std::uint32_t>& observed,
                               const std::vector<std::uint32_t>& new_points) {
    begin();
    MapDeltaMessage& d = *delta_;
    Keyframe kf;
    kf.t_ns = kStartNs + static_cast<std::int64_t>(counter) * kKeyframeStepNs;
    kf.p_w = Eigen::Vector3d(0.1 * counter, 0.0, 1.0);
    for (std::size_t i = 0; i < observed.size(); ++i) kf.observations[static_cast<std::uint16_t>(i)] = observed[i];
    for (std::size_t i = 0; i < new_points.size(); ++i) {
      const auto k = static_cast<std::uint16_t>(observed.size() + i);
      kf.observations[k] = new_points[i];
      points[new_points[i]] = Point{counter, kf.p_w + Eigen::Vector3d(0.01 * static_cast<double>(i), 0.0, 3.0)};
      MapEvent e;
      e.type = MapEventType::kPointCreated;
      e.keypoint = k;
      e.keyframe = KeyframeId{kAgent, counter};
      e.point = MapPointId{kAgent, new_points[i]};
      d.events[d.event_count++] = e;
    }
    d.has_keyframe = 1;
    d.keyframe_map_id = map_id;
    d.keyframe = stateOf(counter, kf);
    d.keypoint_count = kKeypoints;
    for (std::uint16_t k = 0; k < kKeypoints; ++k) {
      d.keypoints[k] = KeypointMsg{20.0F + 11.0F * k, 30.0F + 5.0F * (k % 40), 10.0F, 45.0F, 0};
      d.descriptors[k].fill(static_cast<std::uint8_t>(counter * 7 + k));
      d.has_observation[k] = kf.observations.count(k) != 0 ? 1 : 0;
      if (d.has_observation[k] != 0) d.observation[k] = MapPointId{kAgent, kf.observations.at(k)};
    }
    d.has_imu_link = 0;
    d.imu_count = 0;
    if (!keyframes.empty()) {
      const auto previous = std::prev(keyframes.end());
      d.has_imu_link = 1;
      d.imu_from = KeyframeId{kAgent, previous->first};
      // 200 Hz from the previous keyframe's time to this one's, both ends included.
      for (std::int64_t t = previous->second.t_ns; t <= kf.t_ns; t += 5'000'000) {
        d.imu[d.imu_count++] = ImuSampleMsg{t, {0.01, 0.0, 0.0}, {0.0, 0.0, 9.81}};
      }
    }
    keyframes[counter] = kf;
    return d;
  }

  // A delta without a new keyframe (for removals and moves alone).
  MapDeltaMessage& change() {
    begin();
    return *delta_;
  }

  void event(MapEventType type, MapEventReason reason, std::uint32_t keyframe, std::uint32_t point,
             std::uint32_t other = 0, std::uint16_t keypoint = 0) {
    MapDeltaMessage& d = *delta_;
    MapEvent e;
    e.type = type;
    e.reason = reason;
    e.keypoint = keypoint;
    e.keyframe = KeyframeId{kAgent, keyframe};
    e.point = MapPointId{kAgent, point};
    e.other = MapPointId{kAgent, other};
    d.events[d.event_count++] = e;
  }

  // The local map's states and positions into the delta; returns it.
  const MapDeltaMessage& finish() {
    MapDeltaMessage& d = *delta_;
    d.map_id = map_id;
    d.ready = ready ? 1 : 0;
    d.keyframe_count = 0;
    for (const auto& [c, kf] : keyframes) d.keyframes[d.keyframe_count++] = stateOf(c, kf);
    d.point_count = 0;
    d.new_point_count = 0;
    for (const auto& [c, p] : points) {
      const std::array<float, 3> position{static_cast<float>(p.p_w.x()), static_cast<float>(p.p_w.y()),
                                          static_cast<float>(p.p_w.z())};
      d.points[d.point_count++] = DeltaPointMsg{MapPointId{kAgent, c}, position};
      for (std::uint16_t i = 0; i < d.event_count; ++i) {
        if (d.events[i].type == MapEventType::kPointCreated && d.events[i].point.counter == c) {
          NewPointMsg& n = d.new_points[d.new_point_count++];
          n.id = MapPointId{kAgent, c};
          n.reference = KeyframeId{kAgent, p.reference};
          n.p_w = position;
          n.descriptor.fill(static_cast<std::uint8_t>(c));
        }
      }
    }
    return d;
  }

  [[nodiscard]] static KeyframeStateMsg stateOf(std::uint32_t counter, const Keyframe& kf) {
    KeyframeStateMsg m;
    m.id = KeyframeId{kAgent, counter};
    m.t_ns = kf.t_ns;
    m.T_w_s = toMsg(geometry::SE3d(geometry::SO3d(), kf.p_w));
    return m;
  }

 private:
  void begin() {
    MapDeltaMessage& d = *delta_;
    d.sequence = sequence_++;
    d.has_keyframe = 0;
    d.keyframe_before_local_ba = 0;
    d.event_count = 0;
    d.events_lost = 0;
    d.new_point_count = 0;
    d.imu_count = 0;
  }

  std::unique_ptr<MapDeltaMessage> delta_;
  std::uint64_t sequence_ = 0;
};

// The server's core with one agent's stream on it, driven without gRPC.
class ServerSide {
 public:
  explicit ServerSide(const std::string& mission = "link-test", bool stereo = false)
      : mission_(mission), stereo_(stereo) {
    restart();
  }
  // A server with place recognition and the back-end running, which hear of what ingest stored.
  static std::unique_ptr<ServerSide> withWorkers(const std::string& mission = "link-test") {
    auto side = std::make_unique<ServerSide>(mission);
    side->with_workers_ = true;
    side->restart();
    return side;
  }

  // A restarted server: it lost everything unless it keeps a store (useStore), which it then replays.
  void restart() {
    session_.reset();
    server::ServerOptions options;
    options.recognition.delay_keyframes = 0;  // each keyframe queried as soon as recognition hears of it
    core_ = std::make_unique<server::ServerCore>(options);
    if (with_workers_) {
      const Status started = core_->startWorkers();
      ASSERT_TRUE(started.ok()) << started.error().toString();
    }
    if (open_store_) {
      auto store = open_store_();
      ASSERT_TRUE(store.ok()) << store.error().toString();
      auto recovered = core_->attachStore(std::move(store).value());
      recovery_ = recovered.ok() ? Status::Ok() : Status(recovered.error());
    }
  }
  // From now on the server keeps a map store that `open` opens, again at every restart (as a restarted process
  // opens its file again); the server restarts now.
  using StoreOpener = std::function<Result<std::unique_ptr<server::MapStore>>()>;
  void useStore(StoreOpener open) {
    open_store_ = std::move(open);
    restart();
  }
  // What replaying the store at the last restart gave.
  [[nodiscard]] const Status& recovery() const { return recovery_; }

  // A new stream: Hello -> the Welcome's stored sequence (and its resend_from_sequence into *resend_from).
  std::uint64_t connect(std::uint64_t last_acked, std::uint64_t* resend_from = nullptr) {
    session_ = core_->openSession({});
    v1::AgentUplink hello;
    *hello.mutable_hello() = server::test::makeHello(mission_, kAgent, 42, stereo_);
    hello.mutable_hello()->set_last_acked_sequence(last_acked);
    v1::ServerDownlink welcome;
    bool due = false;
    const Status s = session_->handle(hello, hello.ByteSizeLong(), welcome, due);
    EXPECT_TRUE(s.ok()) << s.error().toString();
    EXPECT_TRUE(due);
    if (resend_from != nullptr) *resend_from = welcome.welcome().resend_from_sequence();
    return welcome.welcome().stored_sequence();
  }

  Status deliver(const v1::MapBatch& batch) {
    v1::AgentUplink up;
    *up.mutable_batch() = batch;
    v1::ServerDownlink reply;
    bool due = false;
    return session_->handle(up, up.ByteSizeLong(), reply, due);
  }

  [[nodiscard]] std::uint64_t stored() const {
    return core_->missions().find(mission_)->agent(kAgent)->read()->stored_sequence;
  }

  // Keyframe counter -> its map, of everything the server holds of the agent.
  template <typename F>
  void forEachMap(F&& f) const {
    auto mission = core_->missions().find(mission_);
    if (!mission) return;
    for (const auto& map : mission->stack().maps()) f(*map->read());
  }

  [[nodiscard]] std::size_t keyframes() const {
    std::size_t n = 0;
    forEachMap([&](const server::MapContent& m) { n += m.keyframes().size(); });
    return n;
  }
  [[nodiscard]] std::size_t points() const {
    std::size_t n = 0;
    forEachMap([&](const server::MapContent& m) { n += m.points().size(); });
    return n;
  }
  [[nodiscard]] const server::ServerKeyframe* keyframe(std::uint32_t c) const {
    const server::ServerKeyframe* out = nullptr;
    forEachMap([&](const server::MapContent& m) {
      if (out == nullptr) out = m.keyframe(KeyframeId{kAgent, c});
    });
    return out;
  }
  [[nodiscard]] const server::ServerMapPoint* point(std::uint32_t c) const {
    const server::ServerMapPoint* out = nullptr;
    forEachMap([&](const server::MapContent& m) {
      if (out == nullptr) out = m.point(MapPointId{kAgent, c});
    });
    return out;
  }
  [[nodiscard]] Status consistent() const {
    Status result;
    forEachMap([&](const server::MapContent& m) {
      if (Status s = m.checkConsistency(); !s.ok() && result.ok()) result = s;
    });
    return result;
  }
  [[nodiscard]] server::ServerCore& core() { return *core_; }

 private:
  std::string mission_;
  bool stereo_ = false;
  bool with_workers_ = false;
  std::unique_ptr<server::ServerCore> core_;
  std::unique_ptr<server::AgentSession> session_;
  StoreOpener open_store_;
  Status recovery_;
};

}  // namespace cvislam::agent::test
