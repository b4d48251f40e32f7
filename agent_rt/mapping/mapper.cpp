#include "agent_rt/mapping/mapper.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "agent_rt/mapping/imu_initialisation.hpp"
#include "agent_rt/mapping/mapper_state.hpp"
#include "agent_rt/mapping/monocular_start.hpp"
#include "agent_rt/messages/conversions.hpp"
#include "common/features/best_two.hpp"
#include "common/trace/trace.hpp"

namespace cvislam::agent {

using Eigen::Vector2d;
using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

Status MapperOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "mapping: " + what}; };
  if (max_keyframes < 2 || static_cast<std::size_t>(max_keyframes) > kMaxKeyframes) {
    return bad("max_keyframes must be in [2, " + std::to_string(kMaxKeyframes) + "] (CVISLAM_MAX_KEYFRAMES)");
  }
  if (ba.window > max_keyframes) return bad("the BA window must not exceed max_keyframes");
  if (return_full_window_keyframes < 0) return bad("return_full_window_keyframes must be >= 0");
  if (Status st = retention.validate(); !st.ok()) return st;
  if (triangulation_neighbours < 0) return bad("triangulation_neighbours must be >= 0");
  if (!(fuse_radius_px > 0.0)) return bad("fuse_radius_px must be > 0");
  if (!(fuse_max_depth_ratio >= 0.0)) return bad("fuse_max_depth_ratio must be >= 0");
  if (imu_init_keyframes < 4 || imu_init_max_keyframes < imu_init_keyframes) {
    return bad("imu_init_keyframes must be >= 4 and imu_init_max_keyframes >= imu_init_keyframes");
  }
  if (imu_init_max_keyframes > max_keyframes) return bad("imu_init_max_keyframes must not exceed max_keyframes");
  if (imu_init_min_keyframes < 4) return bad("imu_init_min_keyframes must be >= 4");
  if (!(imu_init_scale_agreement >= 0.0)) return bad("imu_init_scale_agreement must be >= 0");
  if (imu_init_full_window_keyframes < 0) return bad("imu_init_full_window_keyframes must be >= 0");
  if (!(mono_init_search_radius_px > 0.0)) return bad("mono_init_search_radius_px must be > 0");
  if (!(mono_init_ratio > 0.0 && mono_init_ratio <= 1.0)) return bad("mono_init_ratio must be in (0, 1]");
  if (mono_init_max_distance < 0 || mono_init_max_distance > 256) {
    return bad("mono_init_max_distance must be in [0, 256] bits");
  }
  if (static_cast<std::size_t>(max_keyframes + retention.place_keyframes + 1) > kMaxKeyframes) {
    return bad("max_keyframes + place_keyframes must be < " + std::to_string(kMaxKeyframes) +
               " (CVISLAM_MAX_KEYFRAMES: the pool holds the own keyframes and the one being added)");
  }
  if (downlink.max_anchor_keyframes < 0 || static_cast<std::size_t>(max_keyframes + retention.place_keyframes + 1 +
                                                                    downlink.max_anchor_keyframes) > kMaxKeyframes) {
    return bad("downlink.max_anchor_keyframes must be in [0, " + std::to_string(kMaxKeyframes) +
               " - max_keyframes - place_keyframes - 1] (the pool holds the own keyframes, the one being added, and "
               "the anchors)");
  }
  if (downlink.max_anchor_points < 0 || static_cast<std::size_t>(downlink.max_anchor_points) >= kMaxMapPoints) {
    return bad("downlink.max_anchor_points must be in [0, " + std::to_string(kMaxMapPoints) + ")");
  }
  if (!(stereo.min_depth_m > 0.0) || !(stereo.max_depth_m > stereo.min_depth_m)) {
    return bad("stereo depths must satisfy 0 < min_depth_m < max_depth_m");
  }
  if (Status s = orb.validate(); !s.ok()) return s;
  if (Status s = triangulation.validate(); !s.ok()) return s;
  if (Status s = alignment.validate(); !s.ok()) return s;
  return ba.validate();
}

Mapper::Mapper(std::unique_ptr<State> state) : s_(std::move(state)) {}
Mapper::~Mapper() = default;
const LocalMap& Mapper::map() const {
  return s_->map;
}
bool Mapper::imuInitialised() const {
  return s_->imu_initialised;
}

Result<std::unique_ptr<Mapper>> Mapper::create(const MapperOptions& options, const camera::CameraModel& left,
                                               const camera::CameraModel* right, const SE3d& T_s_c,
                                               const SE3d& T_c0_c1) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  auto state = std::make_unique<State>(options, left, right, T_s_c, T_c0_c1);
  if (right != nullptr) {
    auto orb = features::OrbExtractor::create(options.orb.forImageSize(right->width(), right->height()));
    if (!orb) return orb.error();
    state->right_orb.emplace(std::move(orb.value()));
    state->right_keypoints.resize(static_cast<std::size_t>(options.orb.max_features));
    state->right_descriptors.resize(static_cast<std::size_t>(options.orb.max_features));
    state->right_bearings.reserve(static_cast<std::size_t>(options.orb.max_features));
    state->stereo_depth_m.reserve(kMaxKeypointsPerKeyframe);
    const dataset::CameraCalibration& c1 = right->calibration();
    state->options.ba.use_second_camera = options.stereo.use_in_ba;
    state->options.ba.second_intrinsics = {c1.fx, c1.fy, c1.cx, c1.cy};
    state->options.ba.T_c1_c0 = T_c0_c1.inverse();
  }
  state->imu_samples.reserve(kMaxImuSamplesPerKeyframe);
  state->point_index.reserve(kMaxMapPoints * 2);
  return std::unique_ptr<Mapper>(new Mapper(std::move(state)));
}

namespace {

// The nearest keypoint by descriptor among the candidates, accepted by distance and ratio. Distances run from 0
// to 256 (bits); 256 stands for "none" here, so a lone candidate is held to the ratio against 256.
struct BestTwoKeypoints {
  features::BestTwo<int> nearest{256, -1};

  void offer(int distance, int candidate) { nearest.offer(distance, candidate); }
  [[nodiscard]] int index() const { return nearest.candidate; }
  [[nodiscard]] int best() const { return nearest.best; }
  [[nodiscard]] bool accepted(int max_distance, float ratio) const {
    return nearest.candidate >= 0 && nearest.best <= max_distance &&
           static_cast<float>(nearest.best) <= ratio * static_cast<float>(nearest.second);
  }
};

// The epipolar line of bearing b0 in the second camera (relative pose T_c1_c0), and the distance of a bearing b1
// from it in pixels of a camera with focal length f. Made once per b0: a keypoint has hundreds of candidates
// (recomputing the line per candidate was measured at 4 % of the mono agent's CPU).
class EpipolarLine {
 public:
  EpipolarLine(const Vector3d& b0, const SE3d& T_c1_c0, double f)
      : l_(geometry::hatSO3(T_c1_c0.translation()) * (T_c1_c0.so3() * b0)),  // E b0
        norm_(std::hypot(l_.x(), l_.y())),
        f_(f) {}

  [[nodiscard]] double distancePx(const Vector3d& b1) const {
    if (norm_ < 1e-12) return 1e9;
    const Vector3d x1 = b1 / b1.z();
    return std::abs(l_.dot(x1)) / norm_ * f_;
  }

 private:
  Vector3d l_;
  double norm_;
  double f_;
};

// Matches every keypoint of the keyframe in the second camera's image (epipolar band, octave, ratio test,
// rays that meet in front of both cameras) and stores the match on the keypoint for local BA. Returns how
// many keypoints have one; s.stereo_depth_m[k] holds the triangulated depth along keypoint k (0 for none).
int matchStereo(Mapper::State& s, PoolHandle handle, const KeyframeMessage& msg) {
  KeyframeData& kf = *s.map.keyframes().get(handle);
  kf.has_right.fill(false);
  s.stereo_depth_m.assign(kf.keypoint_count, 0.0);
  if (!s.right || !s.right_orb || msg.right_width == 0) return 0;
  const auto pixels = static_cast<std::size_t>(msg.right_width) * msg.right_height;
  const int n_right = s.right_orb->extract(std::span(msg.right_pixels.data(), pixels), msg.right_width,
                                           msg.right_height, s.right_keypoints, s.right_descriptors);
  s.right_bearings.resize(static_cast<std::size_t>(n_right));
  s.right_owner.assign(static_cast<std::size_t>(n_right), -1);
  s.right_owner_distance.assign(static_cast<std::size_t>(n_right), 256);
  for (int j = 0; j < n_right; ++j) {
    s.right_bearings[static_cast<std::size_t>(j)] =
        s.right->unproject(s.right_keypoints[static_cast<std::size_t>(j)].px.cast<double>());
  }
  const SE3d T_c1_c0 = s.T_c0_c1.inverse();
  const StereoOptions& o = s.options.stereo;
  const double f = s.right->calibration().fx;
  int matched = 0;
  for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
    const Vector3d b0 = s.left.unproject(kf.keypoints[k].px.cast<double>());
    const EpipolarLine line(b0, T_c1_c0, f);
    BestTwoKeypoints match;
    for (int j = 0; j < n_right; ++j) {
      const auto& rk = s.right_keypoints[static_cast<std::size_t>(j)];
      if (std::abs(static_cast<int>(rk.octave) - static_cast<int>(kf.keypoints[k].octave)) > 1) continue;
      if (line.distancePx(s.right_bearings[static_cast<std::size_t>(j)]) >
          o.max_epipolar_error_px * s.levelScale(rk.octave)) {
        continue;
      }
      match.offer(features::hammingDistance(kf.descriptors[k], s.right_descriptors[static_cast<std::size_t>(j)]), j);
    }
    if (!match.accepted(o.max_distance, o.ratio)) continue;
    const auto best_j = static_cast<std::size_t>(match.index());
    const Vector3d& b1 = s.right_bearings[best_j];
    auto p = geometry::triangulateMidpoint(SE3d(), b0.normalized(), s.T_c0_c1, b1.normalized());
    if (!p || p->z() < o.min_depth_m) continue;
    const double tolerance = 2.0 * s.levelScale(kf.keypoints[k].octave) / f;
    if (geometry::rayAngle(*p, b0) > tolerance || geometry::rayAngle(T_c1_c0 * *p, b1) > tolerance) continue;
    // One right keypoint serves one left keypoint: the closer in descriptor keeps it.
    const int distance = match.best();
    if (s.right_owner[best_j] >= 0) {
      if (s.right_owner_distance[best_j] <= distance) continue;
      const auto previous = static_cast<std::uint16_t>(s.right_owner[best_j]);
      kf.has_right[previous] = false;
      s.stereo_depth_m[previous] = 0.0;
      --matched;
    }
    const features::Keypoint& rk = s.right_keypoints[best_j];
    s.right_owner[best_j] = k;
    s.right_owner_distance[best_j] = distance;
    kf.has_right[k] = true;
    kf.right_undistorted_px[k] = s.right->undistortPixel(rk.px.cast<double>());
    kf.right_octave[k] = rk.octave;
    s.stereo_depth_m[k] = p->norm();
    ++matched;
  }
  return matched;
}

// New points from stereo depth, for the keypoints with a cam1 match within max_depth_m and no map point yet.
int addStereoPoints(Mapper::State& s, PoolHandle handle) {
  KeyframeData& kf = *s.map.keyframes().get(handle);
  int created = 0;
  for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
    if (kf.has_map_point[k] || !kf.has_right[k] || s.stereo_depth_m[k] > s.options.stereo.max_depth_m) continue;
    const Vector3d b0 = s.left.unproject(kf.keypoints[k].px.cast<double>()).normalized();
    if (s.map.createMapPoint(handle, k, b0, s.stereo_depth_m[k], s.point_ids.next()).ok()) ++created;
  }
  return created;
}

// New points between the keyframe and its previous neighbours, from keypoints neither has linked yet.
int triangulateWithNeighbours(Mapper::State& s, PoolHandle handle, const std::vector<PoolHandle>& order) {
  int created = 0;
  const double f = s.left.calibration().fx;
  int used = 0;
  for (auto it = order.rbegin(); it != order.rend() && used < s.options.triangulation_neighbours; ++it) {
    if (*it == handle) continue;
    ++used;
    KeyframeData& kf = *s.map.keyframes().get(handle);
    KeyframeData& other = *s.map.keyframes().get(*it);
    const SE3d T_w_c0 = s.cameraPose(kf);
    const SE3d T_w_c1 = s.cameraPose(other);
    if ((T_w_c0.translation() - T_w_c1.translation()).norm() < 1e-3) continue;  // no baseline
    const SE3d T_c1_c0 = T_w_c1.inverse() * T_w_c0;
    std::vector<Vector3d> b1(other.keypoint_count);
    for (std::uint16_t j = 0; j < other.keypoint_count; ++j)
      b1[j] = s.left.unproject(other.keypoints[j].px.cast<double>());
    std::vector<std::uint8_t> taken(other.keypoint_count, 0);
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_map_point[k]) continue;
      const Vector3d b0 = s.left.unproject(kf.keypoints[k].px.cast<double>());
      const EpipolarLine line(b0, T_c1_c0, f);
      BestTwoKeypoints match;
      for (std::uint16_t j = 0; j < other.keypoint_count; ++j) {
        if (other.has_map_point[j] || taken[j] != 0) continue;
        if (line.distancePx(b1[j]) > 2.0 * s.levelScale(other.keypoints[j].octave)) continue;
        match.offer(features::hammingDistance(kf.descriptors[k], other.descriptors[j]), j);
      }
      if (!match.accepted(s.options.stereo.max_distance, s.options.stereo.ratio)) continue;
      const int best_j = match.index();
      const std::array<SE3d, 2> T_c_w{T_w_c0.inverse(), T_w_c1.inverse()};
      const std::array<Vector3d, 2> bearings{b0, b1[static_cast<std::size_t>(best_j)]};
      auto p_w = geometry::triangulateLinear(T_c_w, bearings, s.options.triangulation);
      if (!p_w) continue;
      const Vector3d p_c0 = T_c_w[0] * *p_w;
      auto point = s.map.createMapPoint(handle, k, p_c0.normalized(), p_c0.norm(), s.point_ids.next());
      if (!point) continue;
      (void)s.map.addObservation(*it, static_cast<std::uint16_t>(best_j), *point);
      taken[static_cast<std::size_t>(best_j)] = 1;
      ++created;
    }
  }
  return created;
}

// Existing points found again in the keyframe: projected with its pose and matched by descriptor near the
// projection. Counts visibility for culling. When the best keypoint already holds another point at about the
// same depth, the two are one physical point made twice (duplicates by proximity and descriptor): the one
// with fewer observations is merged into the other.
int fusePoints(Mapper::State& s, PoolHandle handle, int* merged) {
  KeyframeData& kf = *s.map.keyframes().get(handle);
  s.grid.build(std::span(kf.keypoints.data(), kf.keypoint_count), s.left.width(), s.left.height());
  const SE3d T_c_w = s.cameraPose(kf).inverse();
  std::vector<std::uint8_t> observed_here(kMaxMapPoints, 0);
  for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
    if (kf.has_map_point[k]) observed_here[kf.map_point[k].index] = 1;
  }
  int fused = 0;
  std::vector<std::pair<PoolHandle, std::uint16_t>> links;
  std::vector<std::pair<PoolHandle, PoolHandle>> duplicates;
  s.map.mapPoints().forEach([&](PoolHandle h, MapPointData& p) {
    if (observed_here[h.index] != 0) {
      ++p.visible;
      ++p.found;
      return;
    }
    const auto p_w = s.map.pointInWorld(h);
    if (!p_w) return;
    const Vector3d p_c = T_c_w * *p_w;
    if (p_c.z() < 0.1) return;
    const auto px = s.left.project(p_c);
    if (!px || px->x() < 0 || px->y() < 0 || px->x() >= s.left.width() || px->y() >= s.left.height()) return;
    ++p.visible;
    // The closest keypoint by descriptor among the free ones, and among those that hold a point.
    int best_free = s.options.fuse_max_distance + 1;
    int best_free_k = -1;
    int best_taken = s.options.fuse_max_distance + 1;
    int best_taken_k = -1;
    s.grid.forEachWithin(*px, s.options.fuse_radius_px * s.levelScale(p.octave), [&](int k) {
      const int d = features::hammingDistance(p.descriptor, kf.descriptors[static_cast<std::size_t>(k)]);
      int& best = kf.has_map_point[static_cast<std::size_t>(k)] ? best_taken : best_free;
      int& best_k = kf.has_map_point[static_cast<std::size_t>(k)] ? best_taken_k : best_free_k;
      if (d < best) {
        best = d;
        best_k = k;
      }
    });
    if (best_taken_k >= 0 && best_taken < best_free) {
      // The keypoint that fits best holds another point: a duplicate if it sits at about the same depth.
      const PoolHandle other = kf.map_point[static_cast<std::size_t>(best_taken_k)];
      const auto other_w = s.map.pointInWorld(other);
      if (other_w && std::abs((T_c_w * *other_w).z() - p_c.z()) <= s.options.fuse_max_depth_ratio * p_c.z()) {
        duplicates.emplace_back(h, other);
        return;
      }
    }
    if (best_free_k >= 0) links.emplace_back(h, static_cast<std::uint16_t>(best_free_k));
  });
  for (const auto& [point, k] : links) {
    if (kf.has_map_point[k]) {
      // Two points wanted the same keypoint: the first keeps it. When one is the server's and the other the
      // agent's, and they sit at about the same depth, they are one physical point (merged below).
      const MapPointData* wanting = s.map.mapPoints().get(point);
      const MapPointData* holding = s.map.mapPoints().get(kf.map_point[k]);
      if (wanting == nullptr || holding == nullptr || wanting->from_server == holding->from_server) continue;
      const auto a_w = s.map.pointInWorld(point);
      const auto b_w = s.map.pointInWorld(kf.map_point[k]);
      if (!a_w || !b_w) continue;
      const double a_z = (T_c_w * *a_w).z();
      if (std::abs((T_c_w * *b_w).z() - a_z) <= s.options.fuse_max_depth_ratio * a_z) {
        duplicates.emplace_back(point, kf.map_point[k]);
      }
      continue;
    }
    if (s.map.addObservation(handle, k, point).ok()) {
      ++fused;
      if (MapPointData* p = s.map.mapPoints().get(point)) {
        ++p->found;
        p->descriptor = kf.descriptors[k];
      }
    }
  }
  for (const auto& [a, b] : duplicates) {
    const MapPointData* pa = s.map.mapPoints().get(a);
    const MapPointData* pb = s.map.mapPoints().get(b);
    if (pa == nullptr || pb == nullptr || a == b) continue;  // gone in an earlier merge
    if (pa->from_server && pb->from_server) continue;        // the server's to merge
    // A server point that duplicates an own one goes into the own one: the anchors' observations then hold the
    // agent's point, and nothing about the server's point goes up (the merge is not reported).
    bool keep_b = pb->observation_count >= pa->observation_count;
    if (pa->from_server != pb->from_server) keep_b = pa->from_server;
    if (s.map.mergeMapPoints(keep_b ? b : a, keep_b ? a : b).ok()) ++*merged;
  }
  return fused;
}

void writeSnapshot(Mapper::State& s, const KeyframeId& newest, MapSnapshotMessage& out) {
  out.map_epoch = s.epoch;
  out.map_id = s.map_id;
  out.epoch_scale = s.epoch_scale;
  out.epoch_transform = toMsg(s.epoch_transform);
  out.imu_initialised = s.imu_initialised ? 1 : 0;
  out.time_correction_ns = std::llround(s.map.timeCorrectionS() * 1e9);
  out.newest_keyframe = newest;
  out.keyframes_taken = s.seen_message ? s.expected_sequence : 0;
  out.keyframe_count = 0;
  out.window_count = 0;
  s.keyframe_slot.assign(kMaxKeyframes, -1);
  s.map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    s.keyframe_slot[h.index] = out.keyframe_count;
    out.keyframe_is_anchor[out.keyframe_count] = kf.anchor ? 1 : 0;
    out.keyframes[out.keyframe_count++] = toStateMsg(kf);
  });
  out.point_count = 0;
  const bool ready = !s.right ? s.mono_initialised : true;
  if (!ready) return;
  s.point_slot.assign(kMaxMapPoints, -1);
  s.map.mapPoints().forEach([&](PoolHandle h, const MapPointData& p) {
    if (p.observation_count < 1) return;
    const auto p_w = s.map.pointInWorld(h);
    if (!p_w || !p_w->allFinite()) return;
    s.point_slot[h.index] = static_cast<std::int32_t>(out.point_count);
    MapPointMsg& m = out.points[out.point_count++];
    m.id = p.id;
    m.p_w = {p_w->x(), p_w->y(), p_w->z()};
    m.descriptor = p.descriptor;
    m.octave = p.octave;
  });

  // Tracking's motion-only BA window: the newest own keyframes and what they observe.
  std::vector<PoolHandle> own;
  for (PoolHandle h : s.keyframesBySequence()) {
    if (!s.map.keyframes().get(h)->anchor) own.push_back(h);
  }
  const std::size_t first = own.size() > kMaxMotionBaKeyframes ? own.size() - kMaxMotionBaKeyframes : 0;
  for (std::size_t i = first; i < own.size(); ++i) {
    const KeyframeData& kf = *s.map.keyframes().get(own[i]);
    WindowKeyframeMsg& w = out.window[out.window_count++];
    w.keyframe = static_cast<std::uint16_t>(s.keyframe_slot[own[i].index]);
    w.observation_count = 0;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (!kf.has_map_point[k]) continue;
      const std::int32_t slot = s.point_slot[kf.map_point[k].index];
      if (slot < 0) continue;
      KeyframeObservationMsg& o = w.observations[w.observation_count++];
      o.u = static_cast<float>(kf.undistorted_px[k].x());
      o.v = static_cast<float>(kf.undistorted_px[k].y());
      o.sigma_px = static_cast<float>(s.options.ba.sigma_px * s.levelScale(kf.keypoints[k].octave));
      o.point = static_cast<std::uint32_t>(slot);
    }
  }
}

// No keyframe ever waits (the default of process()).
const std::function<bool()> kNeverYield;

// A new map begins: the old one is cleared and the frame starts over.
void startNewMap(Mapper::State& s, const KeyframeMessage& msg, MapperReport& report) {
  s.clearMap();
  ++s.map_id;
  s.epoch_scale = 1.0;
  s.epoch_transform = SE3d();
  report.new_map = true;
  // The IMU was initialised: the new map continues the metric, gravity-aligned frame, and a monocular one
  // needs no two-view start (its first points are triangulated from the keyframes' IMU-carried poses).
  if (msg.continues_frame != 0 && s.options.use_imu) {
    s.imu_initialised = true;
    s.mono_initialised = true;
  }
}

// The keyframe as the map holds it, in s.scratch: its state in the map's current frame, its undistorted
// keypoints, and its preintegration from the newest keyframe (`newest`, when there is one).
// The gyro at t_ns, interpolated between the message's samples around it (its last one is at or after the
// keyframe); zero without samples.
Eigen::Vector3d gyroAt(const KeyframeMessage& msg, std::int64_t t_ns) {
  if (msg.imu_count == 0) return Eigen::Vector3d::Zero();
  const std::uint32_t last = std::min<std::uint32_t>(msg.imu_count, kMaxImuSamplesPerKeyframe) - 1;
  std::uint32_t after = 0;
  while (after < last && msg.imu[after].t_ns < t_ns) ++after;
  const Eigen::Vector3d g1 = toVector3(msg.imu[after].gyro);
  if (after == 0 || msg.imu[after].t_ns <= t_ns) return g1;
  const Eigen::Vector3d g0 = toVector3(msg.imu[after - 1].gyro);
  const double span = static_cast<double>(msg.imu[after].t_ns - msg.imu[after - 1].t_ns);
  const double a = static_cast<double>(t_ns - msg.imu[after - 1].t_ns) / span;
  return g0 + a * (g1 - g0);
}

KeyframeData& keyframeFromMessage(Mapper::State& s, const KeyframeMessage& msg, const PoolHandle* newest) {
  KeyframeData& kf = s.scratch;
  kf.id = msg.state.id;
  kf.t_ns = msg.state.t_ns;
  kf.time_correction_ns = msg.time_correction_ns;
  kf.gyro_s = gyroAt(msg, msg.state.t_ns);
  kf.T_w_s = fromMsg(msg.state.T_w_s);
  kf.v_w = toVector3(msg.state.v_w);
  kf.bias = biasFromMsg(msg.state.bias);
  kf.anchor = false;
  kf.keypoint_count = msg.keypoint_count;
  for (std::uint16_t k = 0; k < msg.keypoint_count; ++k) {
    const KeypointMsg& m = msg.keypoints[k];
    kf.keypoints[k] = features::Keypoint{Eigen::Vector2f(m.x, m.y), m.response, m.angle_deg, m.octave};
    kf.descriptors[k] = msg.descriptors[k];
    kf.undistorted_px[k] = s.left.undistortPixel(kf.keypoints[k].px.cast<double>());
  }
  if (msg.map_epoch + 1 == s.epoch && s.epoch > 0) {
    // Tracking made this keyframe before it heard of the last change of frame: move it over.
    const SE3d T = s.epoch_transform;
    kf.T_w_s = SE3d(T.so3() * kf.T_w_s.so3(), s.epoch_scale * (T.so3() * kf.T_w_s.translation()));
    kf.v_w = s.epoch_scale * (T.so3() * kf.v_w);
  }
  kf.has_preintegration = false;
  kf.preintegration_incomplete = false;
  if (newest != nullptr && msg.imu_count > 1 && msg.kind == KeyframeKind::kTracked) {
    const KeyframeData& previous = *s.map.keyframes().get(*newest);
    // With the time offset estimated, from the kept history: the previous keyframe may have been re-timed to
    // before this message's first sample (a negative offset).
    if (s.imu_history.empty()) {
      s.imu_samples.clear();
      for (std::uint32_t i = 0; i < msg.imu_count; ++i) s.imu_samples.push_back(fromMsg(msg.imu[i]));
    }
    const auto& samples = s.imu_history.empty() ? s.imu_samples : s.imu_history;
    kf.preintegration_from = previous.id;
    const bool covered = integrateImuLink(s, previous, samples, kf);
    kf.has_preintegration = covered || linkFromBeforeFirstSample(s, previous, kf);
    kf.preintegration_incomplete = !covered;
  }
  return kf;
}

// The map keeps at most N own keyframes and place_keyframes older ones (keyframe_retention.hpp says which goes),
// and leaves room in the pool. A monocular map waiting for its two-view start keeps its reference.
//
// While the server's covisible map is held (anchors), it is the memory of the places: the server's keyframes
// there, this agent's older ones among them, carry its global BA's states, where the own older keyframes still
// carry the drift the server has taken out, and the two would pull local BA apart (on eight simulated agents with a
// server, the onboard ATE went from 0.7-1.4 cm to 1.0-3.1 cm). Only the newest N stay then.
//
// `own` is the map's own keyframes by sequence; those evicted leave it.
void makeRoomForKeyframe(Mapper::State& s, std::vector<PoolHandle>& own, MapperReport& report) {
  KeyframeRetentionOptions retention = s.options.retention;
  if (s.anchorCount() > 0) retention.place_keyframes = 0;
  const int most = s.options.max_keyframes + retention.place_keyframes;
  while (static_cast<int>(own.size()) >= most || s.map.keyframes().size() >= kMaxKeyframes) {
    if (!s.mono_start.views.empty() && !s.mono_initialised) break;
    const std::optional<PoolHandle> evict = keyframeToEvict(s.map, own, s.options.max_keyframes, retention);
    if (!evict || !s.map.removeKeyframe(*evict, MapEventReason::kEvicted).ok()) break;
    own.erase(std::find(own.begin(), own.end(), *evict));
    ++report.evicted;
  }
}

// Tracking's matches become observations of the new keyframe.
void linkTrackedMatches(Mapper::State& s, PoolHandle handle, const KeyframeMessage& msg, MapperReport& report) {
  s.rebuildPointIndex();
  for (std::uint16_t k = 0; k < msg.keypoint_count; ++k) {
    if (msg.has_match[k] == 0) continue;
    const auto found = s.point_index.find(msg.matched[k]);
    if (found == s.point_index.end()) continue;  // culled since tracking saw it
    if (s.map.addObservation(handle, k, found->second).ok()) {
      ++report.linked;
      // The newest view's descriptor: tracking compares frames with it, and the newest is the closest to
      // what the camera sees next.
      if (MapPointData* p = s.map.mapPoints().get(found->second)) p->descriptor = msg.descriptors[k];
    }
  }
}

// A window that holds fixed one of the agent's own keyframes from well before the local map's newest ones (one
// kept for its place), where the last BA held none that old, has come back over a place mapped long ago: it
// starts the whole-map BAs of MapperOptions::return_full_window_keyframes. "Well before": older than the newest
// max_keyframes by as many again. "None that old": the last BA's oldest fixed keyframe was at least max_keyframes
// newer. A keyframe that was never out of view only ages from one BA to the next, and its window has been held
// to it all along: that is no return.
void noteReturnToPlace(Mapper::State& s, const LocalBundleAdjustmentSummary& ba, MapperReport& report) {
  const auto n = static_cast<std::uint64_t>(s.options.max_keyframes);
  const std::optional<std::uint64_t>& oldest = ba.oldest_fixed_sequence;
  const bool from_long_ago = oldest && ba.newest_sequence >= *oldest + 2 * n;
  const bool newly_in_view = !s.last_oldest_fixed_sequence || (oldest && *s.last_oldest_fixed_sequence >= *oldest + n);
  if (from_long_ago && newly_in_view && s.options.return_full_window_keyframes > 0) {
    s.whole_map_bas_left = s.options.return_full_window_keyframes;
    report.returned_to_place = true;
  }
  s.last_oldest_fixed_sequence = oldest;
}

// Local BA over the window, skipped (at most every other keyframe, never for the keyframe that made the
// monocular map) when tracking has keyframes waiting.
void localBundleAdjustment(Mapper::State& s, const std::function<bool()>& keyframe_waiting, MapperReport& report) {
  const std::function<bool()>& yield =
      s.options.yield_to_waiting_keyframes && keyframe_waiting ? keyframe_waiting : kNeverYield;
  const bool may_skip = yield && !s.ba_skipped_last && !report.mono_initialised_now;
  s.ba_skipped_last = false;
  if (may_skip && yield()) {
    report.ba_skipped = true;
    s.ba_skipped_last = true;
    return;
  }
  LocalBundleAdjustmentOptions ba = s.options.ba;
  ba.use_imu = s.imu_initialised && s.options.use_imu;
  if (s.whole_map_bas_left > 0) {  // after a monocular IMU initialisation, or a return to a place
    ba.window = s.options.max_keyframes;
    --s.whole_map_bas_left;
  }
  const auto t0 = std::chrono::steady_clock::now();
  const trace::Span span("local_ba");
  auto summary = runLocalBundleAdjustment(s.map, ba, yield);
  report.ba_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - t0).count();
  if (summary) {
    noteReturnToPlace(s, *summary, report);
    report.ba_ran = true;
    report.ba = *summary;
  }
}

// The IMU initialisation when due, with a full-window visual-inertial BA when it succeeds.
void tryImuInitialisation(Mapper::State& s, bool stereo, MapperReport& report) {
  const Status st = initialiseImu(s, report);
  if (st.ok()) {
    LocalBundleAdjustmentOptions ba = s.options.ba;
    ba.use_imu = true;
    ba.window = s.options.max_keyframes;
    (void)runLocalBundleAdjustment(s.map, ba);
    return;
  }
  if (st.error().code() == ErrorCode::kNotFound) return;  // not enough keyframes yet
  report.imu_initialisation_failed = true;
  report.note = st.error().message();
  int linked = 0;
  for (PoolHandle h : s.keyframesBySequence()) linked += s.map.keyframes().get(h)->has_preintegration ? 1 : 0;
  if (!stereo && linked + 1 >= s.options.imu_init_max_keyframes) {
    // Monocular: the paper reinitialises when 20 keyframes did not give the IMU.
    s.clearMap();
    ++s.map_id;
    report.map_restarted = true;
  }
}

// Writes the map's changes into `delta` while it lives, and the map as it is then when it ends, whatever path
// leaves the phase. `part`: what it says of the keyframe (MapDeltaWriter::KeyframePart).
class DeltaScope {
 public:
  DeltaScope(Mapper::State& s, MapDeltaMessage* delta, const KeyframeMessage& msg, MapDeltaWriter::KeyframePart part,
             MapperReport& report)
      : s_(s), delta_(delta), msg_(msg), part_(part), report_(report) {
    if (delta_ == nullptr) return;
    s_.delta_writer.start(*delta_);
    s_.map.setEventSink(&s_.delta_writer);
  }
  ~DeltaScope() {
    if (delta_ == nullptr) return;
    s_.map.setEventSink(nullptr);
    s_.delta_writer.finish(s_.map, msg_, {s_.map_id, s_.epoch, s_.frameFinal(), s_.keyframe_map_id}, part_);
    report_.delta_events_lost += delta_->events_lost;
  }
  DeltaScope(const DeltaScope&) = delete;
  DeltaScope& operator=(const DeltaScope&) = delete;

 private:
  Mapper::State& s_;
  MapDeltaMessage* delta_;
  const KeyframeMessage& msg_;
  MapDeltaWriter::KeyframePart part_;
  MapperReport& report_;
};

// The keyframe into the map: its links, fused and new points, culling.
Status insertKeyframe(Mapper::State& s, const KeyframeMessage& msg, MapperReport& report) {
  if (s.seen_message && msg.sequence > s.expected_sequence) report.lost_messages = msg.sequence - s.expected_sequence;
  s.seen_message = true;
  s.expected_sequence = msg.sequence + 1;
  if (msg.keypoint_count > kMaxKeypointsPerKeyframe) {
    return Error{ErrorCode::kDataError, "keyframe message with " + std::to_string(msg.keypoint_count) +
                                            " keypoints, more than the capacity " +
                                            std::to_string(kMaxKeypointsPerKeyframe)};
  }
  if (msg.kind == KeyframeKind::kNewMap) startNewMap(s, msg, report);

  keepImuHistory(s, msg);
  std::vector<PoolHandle> order = s.keyframesBySequence();
  completeImuLinks(s, order);
  const KeyframeData& kf = keyframeFromMessage(s, msg, order.empty() ? nullptr : &order.back());
  makeRoomForKeyframe(s, order, report);
  auto inserted = s.map.insertKeyframe(kf);
  if (!inserted) return inserted.error();
  const PoolHandle handle = *inserted;
  s.keyframe_map_id = s.map_id;
  s.applyPendingCorrections();
  order = s.keyframesBySequence();
  linkTrackedMatches(s, handle, msg, report);

  const bool stereo = s.right.has_value();
  if (stereo) report.stereo_matches = matchStereo(s, handle, msg);
  if (!stereo && !s.mono_initialised) {
    tryMonocularStart(s, handle, report);
  } else {
    report.fused = fusePoints(s, handle, &report.merged);
    if (stereo) report.stereo_points = addStereoPoints(s, handle);
    report.triangulated += triangulateWithNeighbours(s, handle, order);
    report.culled = s.map.cullMapPoints(s.options.cull);
  }
  return Status{};
}

// The map refined around the keyframe: local BA, the IMU initialisation when due, the snapshot for tracking.
void refineAroundKeyframe(Mapper::State& s, MapSnapshotMessage& snapshot, const KeyframeMessage& msg,
                          const std::function<bool()>& keyframe_waiting, MapperReport& report) {
  const bool stereo = s.right.has_value();
  const bool map_ready = stereo || s.mono_initialised;
  if (map_ready && s.map.keyframes().size() >= 2) {
    localBundleAdjustment(s, keyframe_waiting, report);
  } else {
    s.ba_skipped_last = false;
  }
  if (map_ready && s.options.use_imu && !s.imu_initialised) tryImuInitialisation(s, stereo, report);
  writeSnapshot(s, msg.state.id, snapshot);
  report.time_correction_ns = snapshot.time_correction_ns;
}

}  // namespace

Result<MapperReport> Mapper::process(const KeyframeMessage& msg, MapSnapshotMessage& snapshot, MapDeltaMessage* delta,
                                     const std::function<bool()>& keyframe_waiting) {
  MapperReport report;
  {
    const DeltaScope scope(*s_, delta, msg, MapDeltaWriter::KeyframePart::kAfterLocalBa, report);
    if (Status st = insertKeyframe(*s_, msg, report); !st.ok()) return st.error();
    refineAroundKeyframe(*s_, snapshot, msg, keyframe_waiting, report);
  }
  return report;
}

Result<MapperReport> Mapper::insert(const KeyframeMessage& msg, MapDeltaMessage* delta) {
  MapperReport report;
  {
    const DeltaScope scope(*s_, delta, msg, MapDeltaWriter::KeyframePart::kBeforeLocalBa, report);
    if (Status st = insertKeyframe(*s_, msg, report); !st.ok()) return st.error();
  }
  return report;
}

void Mapper::refine(const KeyframeMessage& msg, MapperReport& report, MapSnapshotMessage& snapshot,
                    MapDeltaMessage* delta, const std::function<bool()>& keyframe_waiting) {
  const DeltaScope scope(*s_, delta, msg, MapDeltaWriter::KeyframePart::kStateOnly, report);
  refineAroundKeyframe(*s_, snapshot, msg, keyframe_waiting, report);
}

}  // namespace cvislam::agent
