// Mapper's state, shared by its translation units (mapper.cpp: the keyframe pipeline; mapper_downlink.cpp:
// what the server sends down). Internal to agent_rt/mapping.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <limits>
#include <optional>
#include <unordered_map>
#include <utility>
#include <vector>

#include "agent_rt/mapping/map_delta_writer.hpp"
#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/tracking/projection_search.hpp"

namespace cvislam::agent {

struct Mapper::State {
  State(const MapperOptions& o, const camera::CameraModel& l, const camera::CameraModel* r,
        const geometry::SE3d& extrinsics, const geometry::SE3d& stereo_extrinsics)
      : options(o), left(l), T_s_c(extrinsics), T_c0_c1(stereo_extrinsics), map(extrinsics), point_ids(o.agent) {
    if (r != nullptr) right.emplace(*r);
    level_scale[0] = 1.0;
    for (std::size_t i = 1; i < level_scale.size(); ++i)
      level_scale[i] = level_scale[i - 1] * static_cast<double>(o.orb.scale_factor);
  }

  MapperOptions options;
  camera::CameraModel left;
  std::optional<camera::CameraModel> right;
  std::optional<features::OrbExtractor> right_orb;
  geometry::SE3d T_s_c;
  geometry::SE3d T_c0_c1;
  LocalMap map;
  IdCounter<MapPointId> point_ids;
  std::array<double, 32> level_scale{};

  std::uint32_t map_id = 0;
  std::uint32_t epoch = 0;
  double epoch_scale = 1.0;
  geometry::SE3d epoch_transform;
  bool imu_initialised = false;
  bool mono_initialised = false;
  // Monocular: the scales of the last two initialisation attempts before imu_init_keyframes, newest last; NaN
  // where there was none.
  std::array<double, 2> early_scales{kNoScale, kNoScale};
  static constexpr double kNoScale = std::numeric_limits<double>::quiet_NaN();
  void forgetEarlyScales() { early_scales.fill(kNoScale); }
  std::optional<std::uint64_t> last_oldest_fixed_sequence;  // of the last local BA (noteReturnToPlace)
  // Local BAs still to take the whole local map, not the window: after a monocular IMU initialisation
  // (MapperOptions::imu_init_full_window_keyframes) or a return to a place (return_full_window_keyframes).
  int whole_map_bas_left = 0;
  bool ba_skipped_last = false;  // the previous keyframe's local BA was skipped (the next one is not)
  // A monocular map waiting for its two-view start: the reference keyframe, then every keyframe since, oldest
  // first (after the ones kept from an earlier reference); per keyframe the keypoint each of the reference's
  // keypoints was found at (-1: not found there), and the camera's rotation from the first view by the gyro.
  struct MonocularStart {
    std::vector<PoolHandle> views;
    std::vector<std::vector<std::int32_t>> followed;  // [view][reference keypoint]
    std::vector<geometry::SO3d> R_c_c0;
    // The reference's index in `views`: the views before it are kept from an earlier reference, with the tracks
    // they share with this one.
    std::size_t reference = 0;
    void clear() {
      views.clear();
      followed.clear();
      R_c_c0.clear();
      reference = 0;
    }
  } mono_start;
  std::uint64_t expected_sequence = 0;
  bool seen_message = false;
  std::uint32_t keyframe_map_id = 0;  // the map the keyframe being processed was inserted into
  // The newest downlink message applied, (stream, sequence).
  std::uint32_t downlink_stream = 0;
  std::uint64_t downlink_sequence = 0;
  bool downlink_seen = false;
  std::unordered_map<MapPointId, std::uint32_t> message_point;  // point -> index in the message (scratch)
  // The server's states of own keyframes that were in the local BA window when they came: applied when the
  // keyframe leaves the window, so that the keyframes held fixed around the window agree with one another.
  std::unordered_map<KeyframeId, KeyframeStateMsg> pending_corrections;
  // What the server sends is in the agent's world frame as the server holds it (T_m_w, fixed when the agent
  // map joined the server's map); that differs from the agent's frame now by whatever the server moved since
  // (a merge's error, global BA). Re-estimated from the newest own keyframe the server corrected, so that the
  // present stays where it is and only the server's view of the past (drift) moves: local = T * server.
  geometry::SE3d T_local_server;

  // Downlink (mapper_downlink.cpp): a server state in the local frame; one keyframe taking the server's state
  // (returns the step: translation [m], rotation [deg]); the pending corrections of keyframes now outside the
  // local BA window.
  [[nodiscard]] KeyframeStateMsg toLocal(const KeyframeStateMsg& c) const;
  std::pair<double, double> correct(KeyframeData& kf, const KeyframeStateMsg& c);
  void applyPendingCorrections();

  MapDeltaWriter delta_writer;  // the link's delta, when one is asked for

  // Scratch (mapping may allocate, but reuses).
  KeyframeData scratch;
  std::vector<dataset::ImuSample> imu_samples;
  std::vector<dataset::ImuSample> imu_history;  // keepImuHistory's, oldest first
  std::unordered_map<MapPointId, PoolHandle> point_index;
  std::vector<features::Keypoint> right_keypoints;
  std::vector<features::Descriptor> right_descriptors;
  std::vector<Eigen::Vector3d> right_bearings;
  std::vector<int> right_owner;  // per right keypoint: the left keypoint matched to it, or -1
  std::vector<int> right_owner_distance;
  std::vector<double> stereo_depth_m;       // per keypoint of the newest keyframe, 0 without a cam1 match
  std::vector<std::int32_t> keyframe_slot;  // snapshot index by keyframe pool index, -1 for none
  std::vector<std::int32_t> point_slot;     // snapshot index by map point pool index, -1 for none
  KeypointGrid grid;

  void rebuildPointIndex() {
    point_index.clear();
    map.mapPoints().forEach([&](PoolHandle h, const MapPointData& p) { point_index[p.id] = h; });
  }

  void clearMap() {
    std::vector<PoolHandle> all;
    map.keyframes().forEach([&](PoolHandle h, const KeyframeData&) { all.push_back(h); });
    for (PoolHandle h : all) (void)map.removeKeyframe(h);
    std::vector<PoolHandle> points;
    map.mapPoints().forEach([&](PoolHandle h, const MapPointData&) { points.push_back(h); });
    for (PoolHandle h : points) (void)map.removeMapPoint(h);
    imu_initialised = false;
    forgetEarlyScales();
    mono_initialised = false;
    mono_start.clear();
    last_oldest_fixed_sequence.reset();
    whole_map_bas_left = 0;
    pending_corrections.clear();
    T_local_server = geometry::SE3d();
  }

  // The server's keyframes held in the local map.
  [[nodiscard]] int anchorCount() const {
    int n = 0;
    map.keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { n += kf.anchor ? 1 : 0; });
    return n;
  }

  // Own keyframes by sequence, oldest first (anchors are not among them).
  [[nodiscard]] std::vector<PoolHandle> keyframesBySequence() const {
    std::vector<std::pair<std::uint64_t, PoolHandle>> order;
    map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
      if (!kf.anchor) order.emplace_back(kf.sequence, h);
    });
    std::sort(order.begin(), order.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
    std::vector<PoolHandle> out;
    out.reserve(order.size());
    for (const auto& [sequence, h] : order) out.push_back(h);
    return out;
  }

  [[nodiscard]] geometry::SE3d cameraPose(const KeyframeData& kf) const { return kf.T_w_s * T_s_c; }

  // The map's world frame is final: metric and gravity-aligned (the IMU is initialised; without the IMU: the map
  // has started). Until then nothing of it goes to the server, and nothing from the server comes in.
  [[nodiscard]] bool frameFinal() const {
    const bool started = right.has_value() || mono_initialised;
    return options.use_imu ? imu_initialised : started;
  }

  [[nodiscard]] double levelScale(std::uint8_t octave) const {
    return level_scale[std::min<std::size_t>(octave, level_scale.size() - 1)];
  }
};

}  // namespace cvislam::agent
