// A mission's map stack (CVI-SLAM IV-A): the server maps of one mission, and what the server keeps of each of
// its agents across reconnections.
//
// Locking (no lock is ever held across anything slow, and never across a network call):
//   AgentRecord      one per agent; its stream's session writes it, the monitor reads it.
//   MapStack::maps_  the list of maps; held only to find or add a map.
//   ServerMap        one per map; a batch locks the maps it touches, in id order, for its validation and apply.
// Order: an agent record before the stack, the stack before a map, maps in increasing id. Long work (place
// recognition, global BA) copies what it needs under a map's read lock and works on the copy.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "common/camera/camera_model.hpp"
#include "common/core/ids.hpp"
#include "common/core/percentile.hpp"
#include "common/core/result.hpp"
#include "common/core/synchronized.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"
#include "server_cloud/stack/map_content.hpp"
#include "server_cloud/stack/mission_events.hpp"

namespace cvislam::server {

class ServerMap {
 public:
  explicit ServerMap(MapId id) : id_(id), content_(std::in_place, id) {}
  [[nodiscard]] MapId id() const { return id_; }
  [[nodiscard]] auto write() { return content_.write(); }
  [[nodiscard]] auto read() const { return content_.read(); }

 private:
  const MapId id_;
  Synchronized<MapContent> content_;
};

// Whose world frame a server map's frame is: the agent map it was opened for. Merges move other maps into it and
// leave its frame as it is, so this never changes.
struct MapOrigin {
  AgentId agent = 0;
  std::uint32_t agent_map = 0;
};

class MapStack {
 public:
  // A new, empty map with the next id of this stack (ids are per mission, from 0), opened for `origin`.
  std::shared_ptr<ServerMap> createMap(MapOrigin origin = {});
  // The origin of any map this stack ever made, merged away or not; nullopt for an id it never gave.
  [[nodiscard]] std::optional<MapOrigin> origin(MapId id) const;
  [[nodiscard]] std::shared_ptr<ServerMap> find(MapId id) const;
  // Drops a map from the stack (map fusion moved its content into another); holders of it keep it alive.
  void remove(MapId id);
  [[nodiscard]] std::vector<std::shared_ptr<ServerMap>> maps() const;  // by id

 private:
  struct Maps {
    MapId next_id = 0;
    std::map<MapId, std::shared_ptr<ServerMap>> by_id;
    std::map<MapId, MapOrigin> origins;
  };
  Synchronized<Maps> maps_;
};

enum class SensorMode { kMono, kStereo };

// What an agent's Hello says about its sensors; the server needs it to read keypoints and rebuild the IMU.
struct AgentSensors {
  SensorMode mode = SensorMode::kMono;
  bool uses_imu = true;
  camera::CameraModel cam0;
  std::optional<camera::CameraModel> cam1;
  geometry::SE3d T_s_c0;
  geometry::SE3d T_s_c1;  // stereo only
  imu::ImuNoise imu_noise;
  double imu_rate_hz = 200.0;
};

// The newest `kCapacity` durations of something, for percentiles (a ring: memory stays bounded).
class LatencySamples {
 public:
  static constexpr std::size_t kCapacity = 4096;
  void add(double ms) {
    if (ms_.size() < kCapacity) {
      ms_.push_back(ms);
    } else {
      ms_[next_] = ms;
    }
    next_ = (next_ + 1) % kCapacity;
  }
  [[nodiscard]] std::size_t size() const { return ms_.size(); }
  // The samples kept (the newest kCapacity), not in arrival order once the ring has wrapped.
  [[nodiscard]] const std::vector<double>& samples() const { return ms_; }
  // The fraction-quantile (in [0, 1]) by nearest rank; 0 without samples.
  [[nodiscard]] double percentile(double fraction) const {
    std::vector<double> sorted = ms_;
    std::sort(sorted.begin(), sorted.end());
    return nearestRankPercentile(sorted, fraction);
  }

 private:
  std::vector<double> ms_;
  std::size_t next_ = 0;
};

// Bytes and messages of one kind.
struct TrafficCount {
  std::uint64_t messages = 0;
  std::uint64_t bytes = 0;
  void add(std::uint64_t n, std::uint64_t b) {
    messages += n;
    bytes += b;
  }
};

// What the server keeps of one agent, across its streams.
struct AgentRecord {
  AgentId id = 0;
  // The stream: at most one at a time.
  bool connected = false;
  std::uint64_t session = 0;            // the connected process's random session id
  std::uint32_t connections = 0;        // streams opened; the newest is the one that counts
  std::function<void()> cancel_stream;  // ends the newest stream (safe to call after it ended)
  bool finished = false;
  std::string software;
  std::optional<AgentSensors> sensors;
  std::uint32_t local_map_keyframes = 0;  // the own keyframes its local map keeps (Hello; 0: not said)
  // The newest batch stored; the next must be stored_sequence + 1.
  std::uint64_t stored_sequence = 0;
  // Nonzero when the store turned out to hold another batch under a number the agent sent (an earlier attempt of
  // it committed unseen): from this batch on, what the agent last sent may not be what the server holds, and the
  // next Welcome asks it to send that content again.
  std::uint64_t resend_from = 0;
  std::uint64_t resend_conflicts = 0;   // how often that happened
  std::uint64_t caught_up_batches = 0;  // batches a Hello found in the store beyond what memory held
  // The Hello as last stored (without its last_acked_sequence, which changes every time): a reconnect that says the
  // same is not stored again.
  std::string stored_hello;
  // Reconnections allowed now (a bucket refilled over time), so that an agent that reconnects in a loop neither
  // grows the store nor floods the mission's event log.
  double hello_allowance = -1.0;  // < 0: full
  std::chrono::steady_clock::time_point hello_allowance_at{};
  std::uint64_t hellos_refused = 0;
  // Which server map holds each agent map, keyframe and point of the agent (by counter).
  struct AgentMap {
    MapId map = 0;
    // The agent's world frame in the server map's frame: identity until a merge moves the agent's map into
    // another one. Everything the agent sends is in its world frame and is stored in the map's frame.
    geometry::SE3d T_m_w;
  };
  struct HeldKeyframe {
    MapId map = 0;
    std::uint32_t agent_map = 0;
    std::uint32_t keypoints = 0;
  };
  std::map<std::uint32_t, AgentMap> agent_maps;
  std::unordered_map<std::uint32_t, HeldKeyframe> keyframes;
  std::unordered_map<std::uint32_t, MapId> points;
  // Keyframes whose state the server changed since it last sent them down.
  std::unordered_set<std::uint32_t> corrections;
  // Keyframes the server removed as redundant. They stay in `keyframes`, so that what the agent still sends
  // about them (an update, a removal) is accepted and dropped rather than refused.
  std::unordered_set<std::uint32_t> server_removed_keyframes;
  // Of those, the ones not yet sent down.
  std::set<std::uint32_t> removals_to_send;
  // What the server's maps hold of this agent: its keyframes less those removed as redundant.
  [[nodiscard]] std::size_t serverKeyframes() const {
    return keyframes.size() - std::min(keyframes.size(), server_removed_keyframes.size());
  }
  // The agent's newest tracked pose, as its newest batch carried it: for live viewers, in no map.
  struct LivePose {
    std::int64_t t_ns = 0;
    std::uint32_t agent_map = 0;  // in this agent map's world frame
    geometry::SE3d T_w_s;
    bool metric = false;
  };
  std::optional<LivePose> live_pose;
  // Statistics.
  std::map<std::string, TrafficCount> up;
  std::map<std::string, TrafficCount> down;
  std::uint64_t duplicate_batches = 0;
  std::uint64_t duplicate_objects = 0;
  std::uint64_t imu_links_missing = 0;  // keyframes whose IMU predecessor the server does not hold
  std::uint64_t refused_messages = 0;
  std::string last_error;
  LatencySamples ingest_ms;             // arrival to stored, per batch
  LatencySamples ingest_during_gba_ms;  // those of them with a GBA of the mission running at either end
  // Where each batch's ingest time went, added with ingest_ms so that sample i of each is the same batch: waiting for
  // the agent record's lock and for the maps' locks, and the ingest thread's CPU time. The rest of ingest_ms is
  // time the thread was ready but off a core.
  LatencySamples ingest_record_wait_ms;
  LatencySamples ingest_map_wait_ms;
  LatencySamples ingest_cpu_ms;
};

using SharedAgentRecord = std::shared_ptr<Synchronized<AgentRecord>>;

class Mission {
 public:
  explicit Mission(std::string name) : name_(std::move(name)) {}
  [[nodiscard]] const std::string& name() const { return name_; }
  [[nodiscard]] MapStack& stack() { return stack_; }
  [[nodiscard]] const MapStack& stack() const { return stack_; }

  // The agent's record, made on first use.
  SharedAgentRecord agent(AgentId id);
  // The same for a live Hello: a new agent is refused with RESOURCE_EXHAUSTED when the mission has
  // `max_agents` already (an agent it knows always comes back).
  Result<SharedAgentRecord> admitAgent(AgentId id, std::size_t max_agents);

  // Global BA runs of this mission's maps under way (the back-end counts them; ingest reads it to time batches
  // that met one).
  void gbaStarted() { gba_running_.fetch_add(1, std::memory_order_relaxed); }
  void gbaEnded() { gba_running_.fetch_sub(1, std::memory_order_relaxed); }
  [[nodiscard]] bool gbaRunning() const { return gba_running_.load(std::memory_order_relaxed) > 0; }
  // The agent's record, or nullptr when the agent never connected.
  [[nodiscard]] SharedAgentRecord findAgent(AgentId id) const;
  [[nodiscard]] std::vector<SharedAgentRecord> agents() const;  // by id

  // What happened to the mission's maps, for the map service's WatchMission (it locks itself: append from
  // anywhere, under any other lock).
  [[nodiscard]] MissionEventLog& events() { return events_; }
  [[nodiscard]] const MissionEventLog& events() const { return events_; }

  // Scale-out: the mission moved to another replica. Its sessions and watches end, and refuse what still comes.
  void retire() { retired_.store(true, std::memory_order_release); }
  [[nodiscard]] bool retired() const { return retired_.load(std::memory_order_acquire); }

  // Every agent's sensors as its newest Hello gave them, apart from the agents' records: whoever needs another
  // agent's cameras (the covisible downlink) must not wait while that agent's record is locked for a slow commit.
  void setSensors(AgentId id, const AgentSensors& sensors);
  [[nodiscard]] std::map<AgentId, std::shared_ptr<const AgentSensors>> sensors() const;

 private:
  std::string name_;
  MapStack stack_;
  MissionEventLog events_;
  Synchronized<std::map<AgentId, SharedAgentRecord>> agents_;
  Synchronized<std::map<AgentId, std::shared_ptr<const AgentSensors>>> sensors_;
  std::atomic<int> gba_running_{0};
  std::atomic<bool> retired_{false};
};

// Every mission this server holds, by name.
class MissionRegistry {
 public:
  std::shared_ptr<Mission> getOrCreate(const std::string& name);
  // The same for a live Hello: a new mission is refused with RESOURCE_EXHAUSTED when the server holds
  // `max_missions` already.
  Result<std::shared_ptr<Mission>> open(const std::string& name, std::size_t max_missions);
  // What open would say of the limit now, without making anything (a replica checks it before taking a lease).
  [[nodiscard]] Status checkRoom(const std::string& name, std::size_t max_missions) const;
  [[nodiscard]] std::shared_ptr<Mission> find(const std::string& name) const;
  // Forgets the mission (scale-out: another replica serves it now); returns it, or nullptr when not held.
  std::shared_ptr<Mission> remove(const std::string& name);
  [[nodiscard]] std::vector<std::shared_ptr<Mission>> missions() const;  // by name
  [[nodiscard]] std::size_t size() const;

 private:
  Synchronized<std::map<std::string, std::shared_ptr<Mission>>> missions_;
};

}  // namespace cvislam::server
