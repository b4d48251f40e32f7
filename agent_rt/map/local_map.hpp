// The agent's local map: keyframes and map points in fixed-capacity pools (capacities from CMake), owned by
// the mapping thread. Observations live in the keyframes (keypoint -> map point); a map point is stored as
// a bearing and inverse depth in the camera of its reference keyframe, as the reprojection factor wants it.
//
// Capacity policy: insertKeyframe() and createMapPoint() report kCapacityExceeded instead of growing. The
// mapping thread then evicts an own keyframe (removeKeyframe(), which one: mapping/keyframe_retention.hpp) and
// culls map points (cullMapPoints()). Removing a keyframe moves the reference of each of its map points to another
// observing keyframe, or removes the point when none is left.
//
// Anchors (keyframes that came down from the server, KeyframeData::anchor) and the server's points
// (MapPointData::from_server) are the server's already: the event sink hears nothing about them, neither their
// arrival nor their removal nor an observation of a server point, so the link never sends them back up.
#pragma once

#include <array>
#include <cstdint>
#include <memory>

#include <Eigen/Core>

#include "agent_rt/map/capacities.hpp"
#include "agent_rt/map/fixed_pool.hpp"
#include "agent_rt/map/map_events.hpp"
#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

inline constexpr std::uint16_t kNoKeypoint = 0xFFFF;

struct KeyframeData {
  KeyframeId id;
  std::uint64_t sequence = 0;  // insertion order of the agent's own keyframes, set by insertKeyframe(); 0 for anchors
  std::int64_t t_ns = 0;  // on the IMU's clock: the camera's stamp plus the calibrated offset plus time_correction_ns
  // The estimated camera-IMU time offset's correction the frame's time carried when tracking made the keyframe, and
  // the body's angular rate (the raw gyro) at t_ns: local BA shifts the pose by the rest of the offset
  // (time_offset_point_factor.hpp).
  std::int64_t time_correction_ns = 0;
  Eigen::Vector3d gyro_s = Eigen::Vector3d::Zero();
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
  bool anchor = false;  // held fixed in local BA (covisible keyframes, keyframes from the server)
  // The IMU from keyframe `preintegration_from` of this agent to this one, when there is one. Local BA joins
  // the two only when that keyframe is the previous one in the map (by sequence); after a keyframe in
  // between was removed, the link is simply not used.
  bool has_preintegration = false;
  KeyframeId preintegration_from;
  imu::Preintegration preintegration;
  // The link from `preintegration_from` was wanted but the samples did not cover its interval when it was built: it
  // is missing, or stands on IMU that was not measured (held back before the first sample, or extrapolated past the
  // newest for a keyframe re-timed forward by the time offset). Integrated again once the kept IMU covers it.
  bool preintegration_incomplete = false;
  std::uint16_t keypoint_count = 0;
  std::array<features::Keypoint, kMaxKeypointsPerKeyframe> keypoints{};
  std::array<features::Descriptor, kMaxKeypointsPerKeyframe> descriptors{};
  std::array<Eigen::Vector2d, kMaxKeypointsPerKeyframe> undistorted_px{};
  std::array<PoolHandle, kMaxKeypointsPerKeyframe> map_point{};  // valid only where has_map_point
  std::array<bool, kMaxKeypointsPerKeyframe> has_map_point{};
  // Stereo: the keypoint's match in the second camera (cam1), undistorted to cam1's pinhole, and its pyramid
  // level. It belongs to the keypoint, so whatever map point the keypoint links to (now or by a later fusion)
  // gets it as a second observation in local BA.
  std::array<bool, kMaxKeypointsPerKeyframe> has_right{};
  std::array<Eigen::Vector2d, kMaxKeypointsPerKeyframe> right_undistorted_px{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> right_octave{};
};

struct MapPointData {
  MapPointId id;
  PoolHandle reference;  // keyframe whose camera holds the bearing and inverse depth
  Eigen::Vector3d bearing_c = Eigen::Vector3d::UnitZ();
  double inverse_depth = 1.0;  // [1/m]
  features::Descriptor descriptor{};
  std::uint8_t octave = 0;                // pyramid level of the keypoint that made it: search radius and pixel noise
  std::uint64_t created_at_sequence = 0;  // the newest keyframe's sequence when the point was made
  std::uint32_t visible = 0;              // frames in whose view the point projected
  std::uint32_t found = 0;                // frames in which it was matched
  std::uint16_t observation_count = 0;    // keyframes observing it
  std::uint16_t most_observations = 0;    // the most keyframes that observed it at one time (eviction lowers the count)
  // Came down from the server with an anchor keyframe: never culled, and never reported to the event sink
  // (the server has it already), nor is any observation of it.
  bool from_server = false;
};

struct CullOptions {
  double min_found_ratio = 0.25;  // found / visible, once visible at least min_visible times
  std::uint32_t min_visible = 10;
  std::uint64_t keyframes_to_prove = 2;  // after this many newer keyframes a point needs...
  std::uint16_t min_observations = 2;    // ...at least this many observing keyframes
};

class LocalMap {
 public:
  using KeyframePool = FixedPool<KeyframeData, kMaxKeyframes>;
  using MapPointPool = FixedPool<MapPointData, kMaxMapPoints>;

  explicit LocalMap(const geometry::SE3d& T_s_c);

  // Every structural change from now on is reported to `sink` (nullptr: none), in the order it happens.
  void setEventSink(MapEventSink* sink) { events_ = sink; }

  // Copies the keyframe in (map point links are cleared). kCapacityExceeded when the pool is full.
  Result<PoolHandle> insertKeyframe(const KeyframeData& keyframe);
  // Removes the keyframe and its observations; its map points move to another observing keyframe, or go.
  // `reason` is what the event sink hears (kRemoved: taken out; kEvicted: left the bounded map).
  Status removeKeyframe(PoolHandle keyframe, MapEventReason reason = MapEventReason::kRemoved);
  // Removes the oldest keyframe that is not an anchor; kNotFound if there is none.
  Status evictOldestKeyframe();

  // A new map point observed by `keypoint` of `reference`, at `depth_m` along that keypoint's bearing.
  Result<PoolHandle> createMapPoint(PoolHandle reference, std::uint16_t keypoint, const Eigen::Vector3d& bearing_c,
                                    double depth_m, MapPointId id);
  Status addObservation(PoolHandle keyframe, std::uint16_t keypoint, PoolHandle map_point);
  // Removes the point and every observation of it.
  Status removeMapPoint(PoolHandle map_point, MapEventReason reason = MapEventReason::kRemoved);
  // `drop` and `keep` are one physical point (a duplicate): every keyframe that observed `drop` observes
  // `keep` at that keypoint instead (one that observes `keep` already just loses the `drop` link), `drop`'s
  // visibility counts are added to `keep`'s, and `drop` goes. Returns how many observations moved to `keep`.
  Result<int> mergeMapPoints(PoolHandle keep, PoolHandle drop);

  // Removes points that tracking rarely finds, and young points that too few keyframes observe. Returns how
  // many were removed.
  int cullMapPoints(const CullOptions& options);

  [[nodiscard]] Result<Eigen::Vector3d> pointInWorld(PoolHandle map_point) const;

  [[nodiscard]] const KeyframePool& keyframes() const { return *keyframes_; }
  [[nodiscard]] KeyframePool& keyframes() { return *keyframes_; }
  [[nodiscard]] const MapPointPool& mapPoints() const { return *map_points_; }
  [[nodiscard]] MapPointPool& mapPoints() { return *map_points_; }
  [[nodiscard]] const geometry::SE3d& extrinsics() const { return T_s_c_; }  // T_s_c
  // The camera-IMU time offset, as the correction [s] to the calibrated one that local BA estimates: a property
  // of the rig, so it outlives the maps the agent starts.
  [[nodiscard]] double timeCorrectionS() const { return time_correction_s_; }
  void setTimeCorrectionS(double correction_s) { time_correction_s_ = correction_s; }

 private:
  // Unlinks one observation and counts it off its map point.
  void detach(PoolHandle keyframe, std::uint16_t keypoint);
  void report(const MapEvent& event) {
    if (events_ != nullptr) events_->record(event);
  }

  geometry::SE3d T_s_c_;
  double time_correction_s_ = 0.0;
  std::unique_ptr<KeyframePool> keyframes_;  // megabytes: on the heap, allocated once here
  std::unique_ptr<MapPointPool> map_points_;
  std::uint64_t next_sequence_ = 0;
  MapEventSink* events_ = nullptr;
};

}  // namespace cvislam::agent
