// One server map (CVI-SLAM IV-A): keyframes and map points of one or more agents in one frame M, their
// observations and the covisibility graph. Unbounded, unlike the agent's local map.
//
// MapContent is plain data plus the operations that keep it consistent (observations on both sides,
// covisibility weights, reference keyframes). It is not thread-safe by itself: ServerMap (map_stack.hpp)
// guards it with a lock, and the only way in is through that lock.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <set>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::server {

using MapId = std::uint32_t;

// A keypoint's match in the second camera (stereo agents).
struct RightObservation {
  std::uint16_t keypoint = 0;
  Eigen::Vector2f px_undistorted = Eigen::Vector2f::Zero();  // cam1 pinhole pixel
  std::uint8_t octave = 0;
};

struct ServerKeyframe {
  KeyframeId id;
  std::uint32_t agent_map = 0;  // the agent's map index it was made in
  std::int64_t t_ns = 0;
  geometry::SE3d T_w_s;  // in the server map's frame M
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
  std::vector<features::Keypoint> keypoints;
  std::vector<features::Descriptor> descriptors;
  // Per keypoint, its cam0 pinhole pixel (undistorted at ingest, outside the map's lock, so that a GBA snapshot
  // under the read lock only copies it). Empty when the keyframe was made otherwise (tests): then it is computed.
  std::vector<Eigen::Vector2f> keypoints_undistorted;
  std::vector<RightObservation> right;
  std::vector<MapPointId> point;                      // per keypoint: the map point it observes, where has_point
  std::vector<std::uint8_t> has_point;                // per keypoint
  std::optional<KeyframeId> imu_from;                 // the previous keyframe of the agent, linked by `imu`
  std::vector<dataset::ImuSample> imu;                // raw samples from imu_from's time to t_ns
  std::optional<imu::Preintegration> preintegration;  // rebuilt on the server from `imu`
  // Its state is the server's (a GBA estimated it), not its agent's onboard estimate: set when a GBA's correction
  // is applied, cleared when a loop's pose graph moves it (until the GBA that follows) or its agent sends an update.
  bool refined = false;
  // Moved by a pose graph (a loop's, or a merge's correction) since: neither its agent's estimate nor a refined
  // one. No agent gets it as an anchor, its own agent included, until a GBA refines it or its agent sends an update.
  bool provisional = false;
  // Its agent sent it before its local BA (v1::Keyframe::before_local_ba): the state is tracking's until the update
  // that follows. No agent gets it as an anchor, and the back-end and place recognition hear of it with that update.
  bool awaiting_local_ba = false;

  [[nodiscard]] int observationCount() const;
};

struct ServerMapPoint {
  struct Observation {
    KeyframeId keyframe;
    std::uint16_t keypoint = 0;
  };
  MapPointId id;
  KeyframeId reference;  // a keyframe that observes it (the one that made it, while it exists)
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
  features::Descriptor descriptor{};
  std::uint8_t octave = 0;
  std::vector<Observation> observations;
};

class MapContent {
 public:
  explicit MapContent(MapId id) : id_(id) {}

  [[nodiscard]] MapId id() const { return id_; }

  // kAlreadyExists when the id is held. A keyframe's observations are added with addObservation().
  Status addKeyframe(ServerKeyframe keyframe);
  // kNotFound when the reference keyframe is not in this map; kAlreadyExists when the id is held.
  Status addPoint(ServerMapPoint point);
  // Links `keypoint` of `keyframe` to `point`, replacing the keypoint's earlier link. A keyframe observes a
  // point at most once: kAlreadyExists when another of its keypoints already does (linking the same keypoint
  // again is a no-op). kNotFound for unknown ids, kInvalidArgument for a keypoint out of range.
  Status addObservation(const KeyframeId& keyframe, std::uint16_t keypoint, const MapPointId& point);
  // `drop` and `keep` are one physical point: every observation of `drop` becomes one of `keep` (a keyframe
  // that observes both keeps its `keep` link) and `drop` goes. The map remembers that `drop` became `keep`:
  // an agent that later observes or merges `drop` reaches `keep` (addObservation and mergePoints resolve ids).
  Status mergePoints(const MapPointId& drop, const MapPointId& keep);
  // The point `id` became through merges: itself when it is held or was never merged away.
  [[nodiscard]] MapPointId resolvePoint(const MapPointId& id) const;
  // Moves every keyframe, point, observation, covisibility link and merge record of `other` into this map, with
  // T_this_other applied to poses, velocities and positions (map fusion). Ids are unique across a mission's
  // maps. `other` is left empty.
  void absorb(MapContent& other, const geometry::SE3d& T_this_other);
  Status removePoint(const MapPointId& id);
  // Removes the keyframe and its observations. Its points move their reference to another observing
  // keyframe, or go when none is left; a keyframe whose IMU link started here loses it. The points that went
  // are appended to `removed_points` when given.
  Status removeKeyframe(const KeyframeId& id, std::vector<MapPointId>* removed_points = nullptr);

  [[nodiscard]] const ServerKeyframe* keyframe(const KeyframeId& id) const;
  [[nodiscard]] ServerKeyframe* keyframe(const KeyframeId& id);
  [[nodiscard]] const ServerMapPoint* point(const MapPointId& id) const;
  [[nodiscard]] ServerMapPoint* point(const MapPointId& id);
  [[nodiscard]] const std::unordered_map<KeyframeId, ServerKeyframe>& keyframes() const { return keyframes_; }
  [[nodiscard]] const std::unordered_map<MapPointId, ServerMapPoint>& points() const { return points_; }
  [[nodiscard]] const std::set<AgentId>& agents() const { return agents_; }

  // Covisibility: the number of map points two keyframes both observe.
  [[nodiscard]] int covisibility(const KeyframeId& a, const KeyframeId& b) const;
  // Every keyframe sharing at least one point with `id`, with the count (empty when none).
  [[nodiscard]] const std::unordered_map<KeyframeId, int>& covisible(const KeyframeId& id) const;
  [[nodiscard]] std::size_t covisibilityEdges() const { return edges_; }

  // Checks every invariant (observations on both sides, covisibility counts, references); for tests.
  [[nodiscard]] Status checkConsistency() const;

 private:
  void link(ServerKeyframe& kf, std::uint16_t keypoint, ServerMapPoint& point);
  void unlink(ServerKeyframe& kf, std::uint16_t keypoint);
  void addCovisibility(const KeyframeId& a, const KeyframeId& b, int delta);

  MapId id_;
  std::unordered_map<KeyframeId, ServerKeyframe> keyframes_;
  std::unordered_map<MapPointId, ServerMapPoint> points_;
  std::unordered_map<KeyframeId, std::unordered_map<KeyframeId, int>> covisibility_;
  std::size_t edges_ = 0;
  std::set<AgentId> agents_;
  std::unordered_map<MapPointId, MapPointId> aliases_;  // merged away -> merged into
};

}  // namespace cvislam::server
