// The tracker's state: what Tracker's member functions and its helpers share, in tracker.cpp (a frame's tracking)
// and tracker_snapshot.cpp (taking mapping's snapshots). Fixed-size buffers, sized at start; private to the tracker.
#pragma once

#include <array>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <span>

#include "agent_rt/messages/conversions.hpp"
#include "agent_rt/tracking/motion_window.hpp"
#include "agent_rt/tracking/tracker.hpp"

namespace cvislam::agent {

inline constexpr std::size_t kPublishedRing = 64;  // keyframes published and perhaps not yet refined by mapping

struct Tracker::State {
  State(const TrackerOptions& o, features::OrbExtractor&& extractor, const camera::CameraModel& l,
        const camera::CameraModel* r, const geometry::SE3d& extrinsics)
      : options(o), orb(std::move(extractor)), left(l), T_s_c(extrinsics), keyframe_ids(o.agent) {
    if (r != nullptr) right.emplace(*r);
    const auto& c = l.calibration();
    intrinsics = {c.fx, c.fy, c.cx, c.cy};
    pre_frame = imu::Preintegration(imu::ImuBias{}, o.noise);
    pre_keyframe = imu::Preintegration(imu::ImuBias{}, o.noise);
    level_scale[0] = 1.0;
    for (std::size_t i = 1; i < level_scale.size(); ++i)
      level_scale[i] = level_scale[i - 1] * static_cast<double>(o.orb.scale_factor);
  }

  TrackerOptions options;
  features::OrbExtractor orb;
  camera::CameraModel left;
  std::optional<camera::CameraModel> right;
  geometry::SE3d T_s_c;
  factors::PinholeIntrinsics intrinsics;
  std::array<double, 32> level_scale{};

  // Frame buffers.
  int keypoint_count = 0;
  std::array<features::Keypoint, kMaxKeypointsPerKeyframe> keypoints{};
  std::array<features::Descriptor, kMaxKeypointsPerKeyframe> descriptors{};
  std::array<Eigen::Vector2d, kMaxKeypointsPerKeyframe> undistorted{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> keypoint_taken{};
  std::array<MapPointId, kMaxKeypointsPerKeyframe> keypoint_point{};
  KeypointGrid grid;
  ProjectionMatcher matcher;
  std::array<ProjectedMapPoint, kMaxMapPoints> projected{};
  std::array<std::uint32_t, kMaxMapPoints> projected_source{};
  std::array<int, kMaxMapPoints> match_of_point{};
  std::array<std::uint8_t, kMaxMapPoints> point_matched{};
  std::array<PoseObservation, kMaxKeypointsPerKeyframe> observations{};
  std::array<std::uint32_t, kMaxKeypointsPerKeyframe> observation_point{};
  std::array<std::uint16_t, kMaxKeypointsPerKeyframe> observation_keypoint{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> outlier{};
  std::array<Eigen::Vector2f, kMaxKeypointsPerKeyframe> coverage_px{};
  int observation_count = 0;

  // The map.
  const MapSnapshotMessage* snapshot = nullptr;
  TrackingStatus status = TrackingStatus::kWaitingForMap;
  std::uint32_t map_id = 0;            // the map tracked against
  std::uint32_t requested_map_id = 0;  // the new map asked for, while waiting
  bool new_map_requested = false;
  std::uint32_t epoch = 0;
  bool imu_initialised = false;
  std::int64_t time_correction_target_ns = 0;  // mapping's estimate
  std::int64_t time_correction_ns = 0;         // what the frames carry now
  std::int64_t camera_interval_ns = 0;         // between the last two frames, on the camera's clock

  // Frame state.
  bool started = false;
  std::int64_t last_t_ns = 0;
  std::int64_t last_time_correction_ns = 0;  // the one last_t_ns carries
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
  int lost_frames = 0;
  int waiting_frames = 0;  // frames since the new map was asked for
  // Sequence time the frames since the last tracked one spanned, when none of them was tracked (lost, or waiting
  // for a new map); 0 after a tracked frame. A gap in the images between two tracked frames does not count.
  double untracked_s = 0.0;
  imu::Preintegration pre_frame;

  // The newest keyframe published.
  IdCounter<KeyframeId> keyframe_ids;
  bool has_keyframe = false;
  NewestPublishedKeyframe keyframe;
  int frames_since_keyframe = 0;
  double keyframe_coverage = 0.0;
  imu::Preintegration pre_keyframe;  // from keyframe.t_ns to pre_keyframe_end_ns
  std::int64_t pre_keyframe_end_ns = 0;
  bool imu_ok_since_keyframe = true;
  // The IMU since shortly before the newest keyframe: the next keyframe message carries it from
  // keyframe_imu_first (the last sample at or before the keyframe); the samples before that are kept for a
  // keyframe that mapping moves earlier when it re-times keyframes to the camera-IMU time offset.
  std::uint32_t keyframe_imu_count = 0;
  std::uint32_t keyframe_imu_first = 0;
  std::array<ImuSampleMsg, kMaxImuSamplesPerKeyframe> keyframe_imu{};
  std::array<dataset::ImuSample, kMaxImuSamplesPerKeyframe> imu_scratch{};
  std::int64_t last_imu_t_ns = std::numeric_limits<std::int64_t>::min();
  bool awaiting = false;
  KeyframeId awaiting_id;
  MappingBacklog backlog{options.lag};

  struct Published {
    KeyframeId id;
    geometry::SE3d T_w_s;
    bool valid = false;
  };
  std::array<Published, kPublishedRing> published{};
  std::size_t published_next = 0;

  // The IMU between the keyframes tracking published, for motion-only BA over the newest n keyframes.
  MotionWindowBuilder motion_window;

  void appendImu(std::span<const dataset::ImuSample> samples) {
    for (const dataset::ImuSample& s : samples) {
      if (s.t_ns <= last_imu_t_ns) continue;
      last_imu_t_ns = s.t_ns;
      if (keyframe_imu_count >= keyframe_imu.size()) {
        imu_ok_since_keyframe = false;  // more IMU than a keyframe message carries: the link is dropped
        continue;
      }
      keyframe_imu[keyframe_imu_count++] = toMsg(s);
    }
  }

  // The index of the last sample at or before t (0 when there is none).
  [[nodiscard]] std::uint32_t lastImuAtOrBefore(std::int64_t t_ns) const {
    std::uint32_t last = 0;
    for (std::uint32_t i = 0; i < keyframe_imu_count; ++i) {
      if (keyframe_imu[i].t_ns <= t_ns) last = i;
    }
    return last;
  }

  // Keeps the samples the next keyframe interval needs, the last at or before t and those after, and those of
  // the largest time offset before it.
  void restartKeyframeImu(std::int64_t t_ns) {
    const std::uint32_t first = lastImuAtOrBefore(t_ns - kImuKeptBeforeStampNs);
    const std::uint32_t kept = keyframe_imu_count - first;
    std::memmove(keyframe_imu.data(), keyframe_imu.data() + first, kept * sizeof(ImuSampleMsg));
    keyframe_imu_count = kept;
    keyframe_imu_first = lastImuAtOrBefore(t_ns);
  }

  // Tracker::timeCorrectionForNextFrameNs().
  std::int64_t nextTimeCorrectionNs();

  // Mapping moved the newest keyframe's state to `t_ns`: the IMU since it is integrated again from there, up to
  // the last frame.
  void retimeNewestKeyframe(std::int64_t t_ns);

  void applyToTrackedStates(const geometry::SE3d& delta_left);
  // Moves every stored state from the previous epoch into the snapshot's: p' = s R p + t, v' = s R v.
  void changeEpoch(const MapSnapshotMessage& s);
  Published* findPublished(const KeyframeId& id);
  // Takes mapping's newest snapshot: its map, world frame and refined newest keyframe (tracker_snapshot.cpp).
  void adopt(const MapSnapshotMessage* s);
};

}  // namespace cvislam::agent
