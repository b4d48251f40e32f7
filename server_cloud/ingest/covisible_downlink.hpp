// The downlink's map data (CVI-SLAM IV-C.2): for one agent, the K keyframes of its server map most covisible
// with its newest keyframes (other agents' keyframes, and its own older ones that its bounded local map has let
// go), with their map points, expressed in the agent's world frame.
//
// Per stream, a CovisibleSender remembers what the agent holds: a keyframe or point goes in full once, and after
// that only when the server moved it (a pose or position update). The agent holds only the selected keyframes,
// so a keyframe that leaves the selection is forgotten (with the points no held keyframe observes) and goes in
// full again when it is selected again. Each message has a byte budget; new keyframes
// go in rank order, each with the points it brings, and the first that does not fit waits for the next message
// with everything ranked below it. The selection list and the updates always go (they are small), and so does
// the best new keyframe when it alone is over the budget, so that every message makes progress.
//
// Plain C++ over the map content and the protobuf message: the session calls it, tests drive it directly.
#pragma once

#include <cstddef>
#include <cstdint>
#include <map>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/stack/map_content.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::v1 {
class CovisibleMap;
}

namespace cvislam::server {

struct CovisibleOptions {
  bool enabled = true;
  int keyframes = 10;  // K (paper: 10)
  // The agent's newest keyframes whose covisible keyframes compete (their covisibility weights add up).
  int seed_keyframes = 3;
  // The agent's own newest keyframes are in its local map already, and are never sent down: as many as its Hello
  // says its local map keeps, else this many (the agent's default N).
  int own_recent_excluded = 20;
  // Another agent's keyframe is sent only while its state is the server's refined one (ServerKeyframe::refined),
  // never that agent's raw onboard estimate: two agents that held each other's onboard keyframes fixed would
  // pull each other's drift in (co-drift). The agent's own older keyframes are always eligible.
  bool foreign_refined_only = true;
  // Per message; 2 messages per second at 150 kB is the downlink goal of 0.30 MB/s.
  std::size_t budget_bytes = 150000;
  // A keyframe or point sent before is sent again when the server moved it by more than this.
  double update_translation_m = 0.002;
  double update_rotation_deg = 0.05;

  [[nodiscard]] Status validate() const;
};

// The cameras of the mission's agents, taken before the map's lock (records are locked before maps).
struct CovisibleCamera {
  double fx = 1.0;
  double fy = 1.0;
  double cx = 0.0;
  double cy = 0.0;
  geometry::SE3d T_s_c;
};
using CovisibleCameras = std::map<AgentId, CovisibleCamera>;
CovisibleCameras covisibleCameras(const Mission& mission);

// The K keyframes of `content` most covisible with `seeds` (the agent's newest keyframes, newest first), best
// first, with their summed covisibility; the seeds and the agent's own newest `own_recent_excluded` keyframes
// (counters above seeds[0].counter - own_recent_excluded) are left out, and so are other agents' keyframes that
// are not refined when `foreign_refined_only`.
std::vector<std::pair<KeyframeId, int>> selectCovisible(const MapContent& content, const std::vector<KeyframeId>& seeds,
                                                        const CovisibleOptions& options);

// What one fill() put in the message (wire::covisibleParts() counts its bytes).
struct CovisibleReport {
  int selected = 0;
  int keyframes = 0;  // sent in full
  int points = 0;
  int keyframe_updates = 0;
  int point_updates = 0;
  int deferred = 0;  // selected keyframes left for a later message by the budget
  [[nodiscard]] bool carriesData() const { return keyframes + points + keyframe_updates + point_updates > 0; }
};

class CovisibleSender {
 public:
  explicit CovisibleSender(const CovisibleOptions& options) : options_(options) {}

  // Fills `out` for the agent whose newest keyframes are `seeds` (newest first, all in `content`), in its agent
  // map `agent_map`, whose world frame is T_w_m from the content's frame. `out` is left empty when the
  // selection is empty and unchanged and nothing moved. `local_map_keyframes` > 0 overrides
  // options.own_recent_excluded (what the agent's Hello said).
  CovisibleReport fill(const MapContent& content, const std::vector<KeyframeId>& seeds, std::uint32_t agent_map,
                       const geometry::SE3d& T_w_m, const CovisibleCameras& cameras, v1::CovisibleMap& out,
                       std::uint32_t local_map_keyframes = 0);

  [[nodiscard]] std::size_t keyframesSent() const { return keyframes_sent_.size(); }
  [[nodiscard]] std::size_t pointsSent() const { return points_sent_.size(); }

 private:
  // Forgets the sent keyframes that left the selection, and the points no keyframe still held observes.
  void releaseUnselected(const MapContent& content, const std::vector<KeyframeId>& selection);
  // Updates of what was sent before and is selected now: keyframe poses, then the positions of their points.
  void addUpdates(const MapContent& content, const std::vector<KeyframeId>& selection, const geometry::SE3d& T_w_m,
                  const CovisibleCameras& cameras, v1::CovisibleMap& out, CovisibleReport& report);
  // New keyframes, best first, each with the points it brings, within the budget.
  void addNewKeyframes(const MapContent& content, const std::vector<KeyframeId>& selection, const geometry::SE3d& T_w_m,
                       const CovisibleCameras& cameras, v1::CovisibleMap& out, CovisibleReport& report);

  CovisibleOptions options_;
  bool started_ = false;
  std::uint32_t agent_map_ = 0;
  std::vector<KeyframeId> last_selection_;
  std::unordered_map<KeyframeId, geometry::SE3d> keyframes_sent_;  // T_w_c as sent
  std::unordered_map<MapPointId, Eigen::Vector3d> points_sent_;    // p_w as sent
};

}  // namespace cvislam::server
