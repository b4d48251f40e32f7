// What a viewer sees of one mission, as foxglove.* messages (foxglove_messages.hpp) on the mission's channels:
// every agent's live pose and keyframe trajectory, the keyframes with their links, each map's points, the agents'
// world frames, the mission's events and its figures. The feed looks at the mission when asked (update()) and
// says only what changed since it last looked; fullState() is the whole scene for a client that comes later.
// Plain C++ over the map stack: the live endpoint and the MCAP recorder consume it, tests drive it directly.
//
// Locking: each map's read lock and each agent's record lock are held only to copy what the feed draws (poses,
// links, a decimated set of points); building the messages happens after.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/viewer/foxglove_messages.hpp"

namespace cvislam::server {
class MapContent;
class Mission;
struct ServerKeyframe;
}  // namespace cvislam::server

namespace cvislam::server::viewer {

struct FeedOptions {
  std::size_t max_points_per_map = 20000;  // a fixed subset of the map's points, by id, beyond that
  std::size_t covisible_links = 3;         // lines from each keyframe to its strongest older covisible keyframes
  // A keyframe's links are looked up again on every this many looks, the keyframes staggered over them, and at once
  // when it is new or one of its links went. The lookup walks the keyframe's covisibility under its map's read lock,
  // which ingest's writes wait behind: every keyframe's on every look (five a second) held the lock for tens of ms
  // on an eight-agent map under load, and was most of ingest's slowest batches. A link that changed strength shows
  // within this many looks.
  std::size_t links_every_looks = 10;
  // A keyframe (and a trajectory, a world frame) is sent again when it moved or turned more than this: less is
  // not seen in a viewer, and each local BA nudges a dozen keyframes by about a millimetre.
  double moved_m = 0.005;
  double moved_deg = 0.5;
  double points_period_s = 1.0;      // a map's point cloud goes at most this often (when the map changed)
  double trajectory_period_s = 1.0;  // an agent's trajectory likewise (the keyframes' cubes go at once)
  double stats_period_s = 1.0;

  [[nodiscard]] Status validate() const;
};

struct FeedChannel {
  std::string topic;
  std::string schema_name;
};

struct FeedMessage {
  std::size_t channel = 0;  // index into MissionFeed::channels()
  std::int64_t t_unix_ns = 0;
  std::string payload;  // JSON
};

class MissionFeed {
 public:
  using Clock = std::chrono::steady_clock;

  MissionFeed(std::string mission, FeedOptions options);

  // Looks at the mission now and appends to `out` what changed since the last call (everything, the first time).
  // New agents and maps add channels (see channels()).
  void update(const Mission& mission, std::int64_t t_unix_ns, Clock::time_point now, std::vector<FeedMessage>& out);
  // The scene as the feed last saw it, in full: one scene update with every keyframe, the newest message of every
  // other channel, and the newest events.
  void fullState(std::vector<FeedMessage>& out) const;

  // Every channel so far, in the order they came: an index never changes meaning.
  [[nodiscard]] const std::vector<FeedChannel>& channels() const { return channels_; }
  [[nodiscard]] const std::string& mission() const { return mission_; }
  // How many keyframes' links the feed has looked up so far (FeedOptions::links_every_looks).
  [[nodiscard]] std::uint64_t linkLookups() const { return link_lookups_; }
  // Frame ids of the mission's maps and of its agents' world frames.
  [[nodiscard]] std::string mapFrame(std::uint32_t map) const;
  [[nodiscard]] std::string agentWorldFrame(AgentId agent, std::uint32_t agent_map) const;

  // What one look copies of the mission, and of each agent (defined in the .cpp).
  struct Captured;
  struct CapturedAgent;

 private:
  struct DrawnKeyframe {
    KeyframeEntity entity;
    std::vector<KeyframeId> links;  // the keyframes its segments go to
  };

  struct Trajectory {
    std::uint32_t map = 0;
    std::vector<geometry::SE3d> T_m_s;  // oldest first
  };

  std::size_t channel(const std::string& topic, const char* schema_name);
  void sendKeyframes(const Captured& now, std::int64_t t_ns, std::vector<FeedMessage>& out);
  void sendAgents(const Captured& now, std::int64_t t_ns, Clock::time_point at, std::vector<FeedMessage>& out);
  static std::map<AgentId, Trajectory> trajectoriesOf(const Captured& now);
  void sendWorldFrames(const CapturedAgent& agent, std::int64_t t_ns, std::vector<FeedMessage>& out);
  void sendTrajectory(AgentId agent, const Trajectory& now, std::int64_t t_ns, Clock::time_point at,
                      std::vector<FeedMessage>& out);
  void sendLivePose(const CapturedAgent& agent, std::int64_t t_ns, std::vector<FeedMessage>& out);
  void sendEvents(const Mission& mission, std::int64_t t_ns, std::vector<FeedMessage>& out);
  const std::vector<KeyframeId>& linksFor(const MapContent& content, const ServerKeyframe& kf);
  void keep(FeedMessage message, std::vector<FeedMessage>& out);  // sends it and keeps it as its channel's newest

  std::string mission_;
  FeedOptions options_;
  std::vector<FeedChannel> channels_;
  std::map<std::string, std::size_t> channel_by_topic_;
  std::map<KeyframeId, DrawnKeyframe> drawn_;
  std::unordered_map<KeyframeId, std::vector<KeyframeId>> links_;  // as last looked up
  std::uint64_t looks_ = 0;
  std::uint64_t link_lookups_ = 0;
  std::map<std::uint32_t, std::uint64_t> points_signature_;  // per map: what its last cloud was made of
  std::map<std::uint32_t, Clock::time_point> points_sent_at_;
  std::map<AgentId, std::int64_t> pose_sent_t_ns_;
  struct SentFrame {
    geometry::SE3d T_parent_child;
    FeedMessage message;
  };
  std::map<std::string, SentFrame> frames_sent_;  // child frame -> its newest transform
  std::map<AgentId, Trajectory> trajectory_sent_;
  std::map<AgentId, Clock::time_point> trajectory_sent_at_;
  std::map<std::size_t, FeedMessage> newest_;  // per channel (not the scene's, nor the events')
  std::vector<FeedMessage> recent_events_;
  std::uint64_t next_event_ = 1;
  std::optional<Clock::time_point> stats_sent_at_;
  std::size_t scene_channel_ = 0;
  std::size_t events_channel_ = 0;
  std::size_t stats_channel_ = 0;
  std::size_t tf_channel_ = 0;
};

}  // namespace cvislam::server::viewer
