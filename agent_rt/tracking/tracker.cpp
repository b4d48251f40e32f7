#include "agent_rt/tracking/tracker.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <string>

#include "agent_rt/messages/conversions.hpp"
#include "agent_rt/tracking/inertial_pose_optimizer.hpp"
#include "agent_rt/tracking/motion_window.hpp"
#include "agent_rt/tracking/tracker_state.hpp"
#include "common/core/steady_clock.hpp"
#include "common/trace/trace.hpp"

namespace cvislam::agent {

using Eigen::Vector2d;
using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

Status TrackerOptions::validate() const {
  if (Status s = orb.validate(); !s.ok()) return s;
  if (orb.max_features > static_cast<int>(kMaxKeypointsPerKeyframe)) {
    return Error{ErrorCode::kInvalidArgument,
                 "tracker: orb.max_features = " + std::to_string(orb.max_features) + " exceeds the keyframe capacity " +
                     std::to_string(kMaxKeypointsPerKeyframe) + " (raise CVISLAM_MAX_KEYPOINTS_PER_KEYFRAME)"};
  }
  if (!(search_radius_px > 0.0) || !(refine_radius_px > 0.0) || !(relocalisation_radius_px > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "tracker: search radii must be > 0"};
  }
  if (!(sigma_px > 0.0)) return Error{ErrorCode::kInvalidArgument, "tracker: sigma_px must be > 0"};
  if (initialisation_max_frames_between < 1) {
    return Error{
        ErrorCode::kInvalidArgument,
        "tracker: initialisation_max_frames_between (tracking.init_max_frames_between_keyframes) must be >= 1"};
  }
  if (max_lost_frames < 1) return Error{ErrorCode::kInvalidArgument, "tracker: max_lost_frames must be >= 1"};
  if (!(max_dead_reckoning_s > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "tracker: max_dead_reckoning_s must be > 0"};
  }
  if (motion_ba_keyframes < 1 || motion_ba_keyframes > static_cast<int>(kMaxMotionBaKeyframes)) {
    return Error{ErrorCode::kInvalidArgument, "tracker: motion_ba_keyframes = " + std::to_string(motion_ba_keyframes) +
                                                  " must be in [1, " + std::to_string(kMaxMotionBaKeyframes) +
                                                  "] (raise CVISLAM_MAX_MOTION_BA_KEYFRAMES)"};
  }
  if (Status s = search.validate(); !s.ok()) return s;
  if (Status s = pose.validate(); !s.ok()) return s;
  if (Status s = lag.validate(); !s.ok()) return s;
  return keyframe.validate();
}

const char* toString(TrackingStatus status) {
  switch (status) {
    case TrackingStatus::kWaitingForMap:
      return "WAITING_FOR_MAP";
    case TrackingStatus::kTracking:
      return "TRACKING";
    case TrackingStatus::kRelocalising:
      return "RELOCALISING";
  }
  return "?";
}

const char* toString(FrameIssue issue) {
  switch (issue) {
    case FrameIssue::kNone:
      return "none";
    case FrameIssue::kImuGap:
      return "IMU gap";
    case FrameIssue::kFewFeatures:
      return "too few features";
    case FrameIssue::kPoseRefused:
      return "pose refused";
    case FrameIssue::kKeyframeDropped:
      return "keyframe dropped (no free message)";
  }
  return "?";
}

Tracker::Tracker(std::unique_ptr<State> state) : s_(std::move(state)) {}
Tracker::~Tracker() = default;

Result<std::unique_ptr<Tracker>> Tracker::create(const TrackerOptions& options, const camera::CameraModel& left,
                                                 const camera::CameraModel* right, const SE3d& T_s_c) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  if (static_cast<std::size_t>(left.width()) * static_cast<std::size_t>(left.height()) > kMaxImagePixels) {
    return Error{ErrorCode::kInvalidArgument,
                 "tracker: " + std::to_string(left.width()) + "x" + std::to_string(left.height()) +
                     " images exceed CVISLAM_MAX_IMAGE_PIXELS = " + std::to_string(kMaxImagePixels)};
  }
  auto orb = features::OrbExtractor::create(options.orb.forImageSize(left.width(), left.height()));
  if (!orb) return orb.error();
  return std::unique_ptr<Tracker>(
      new Tracker(std::make_unique<State>(options, std::move(orb.value()), left, right, T_s_c)));
}

TrackingStatus Tracker::status() const {
  return s_->status;
}
void Tracker::restartStream(std::int64_t t_ns) {
  State& s = *s_;
  if (!s.started) return;
  s.last_t_ns = t_ns;
  s.v_w = Vector3d::Zero();
  s.imu_ok_since_keyframe = false;
  // Dead reckoning is over: the position is held and the search is wide (predict()), and one failure is enough.
  s.untracked_s = std::numeric_limits<double>::infinity();
  s.lost_frames = std::max(s.lost_frames, s.options.max_lost_frames);
  if (s.status == TrackingStatus::kTracking) s.status = TrackingStatus::kRelocalising;
}

bool Tracker::imuInitialised() const {
  return s_->imu_initialised;
}
bool Tracker::awaitingKeyframe(KeyframeId* id) const {
  if (id != nullptr) *id = s_->awaiting_id;
  return s_->awaiting;
}
int Tracker::pendingKeyframes() const {
  return s_->backlog.pending(steadyNowNs());
}

namespace {

// Projects the snapshot's points with the pose into `projected`; returns how many landed in the image.
int projectPoints(Tracker::State& s, const SE3d& T_w_s, double radius_px, bool skip_matched) {
  const MapSnapshotMessage& map = *s.snapshot;
  const SE3d T_c_w = (T_w_s * s.T_s_c).inverse();
  const double w = s.left.width();
  const double h = s.left.height();
  int count = 0;
  for (std::uint32_t i = 0; i < map.point_count; ++i) {
    if (skip_matched && s.point_matched[i] != 0) continue;
    const MapPointMsg& mp = map.points[i];
    const Vector3d p_c = T_c_w * Vector3d(mp.p_w[0], mp.p_w[1], mp.p_w[2]);
    if (!(p_c.z() > 0.1)) continue;
    const auto px = s.left.project(p_c);
    if (!px || px->x() < 0.0 || px->y() < 0.0 || px->x() >= w || px->y() >= h) continue;
    ProjectedMapPoint& p = s.projected[static_cast<std::size_t>(count)];
    p.px = *px;
    p.descriptor = mp.descriptor;
    p.radius_px = radius_px * s.level_scale[std::min<std::size_t>(mp.octave, s.level_scale.size() - 1)];
    s.projected_source[static_cast<std::size_t>(count)] = i;
    ++count;
  }
  return count;
}

// Adds the matches of one search as pose observations (a keypoint is used once).
void collectMatches(Tracker::State& s, int projected_count) {
  for (int j = 0; j < projected_count; ++j) {
    const int k = s.match_of_point[static_cast<std::size_t>(j)];
    if (k < 0 || s.keypoint_taken[static_cast<std::size_t>(k)] != 0) continue;
    if (s.observation_count >= static_cast<int>(s.observations.size())) break;
    const std::uint32_t point = s.projected_source[static_cast<std::size_t>(j)];
    const MapPointMsg& mp = s.snapshot->points[point];
    const features::Keypoint& kp = s.keypoints[static_cast<std::size_t>(k)];
    PoseObservation& o = s.observations[static_cast<std::size_t>(s.observation_count)];
    o.p_w = Vector3d(mp.p_w[0], mp.p_w[1], mp.p_w[2]);
    o.keypoint_px = s.undistorted[static_cast<std::size_t>(k)];
    o.sigma_px = s.options.sigma_px * s.level_scale[std::min<std::size_t>(kp.octave, s.level_scale.size() - 1)];
    s.observation_point[static_cast<std::size_t>(s.observation_count)] = point;
    s.observation_keypoint[static_cast<std::size_t>(s.observation_count)] = static_cast<std::uint16_t>(k);
    s.keypoint_taken[static_cast<std::size_t>(k)] = 1;
    s.point_matched[point] = 1;
    ++s.observation_count;
  }
}

}  // namespace

namespace {

// One frame's work in progress: its input, its result so far, and what the steps before decided for the ones after.
struct FrameStep {
  const FrameInput& frame;
  KeyframeSink& keyframes;
  FrameResult& result;
  std::int64_t t_start = 0;
  double dt_s = 0.0;          // since the previous frame
  bool imu_frame_ok = false;  // this interval's IMU was integrated
  bool dead_reckoning_too_long = false;
  SE3d T_pred{};
  Vector3d v_pred = Vector3d::Zero();
  MappingPressure mapping{};
  std::size_t keypoints = 0;
  std::int64_t pose_ns = 0;
};

// 1. The IMU since the previous frame: into this frame's preintegration and, while the chain holds, into the
// keyframe's.
void integrateImu(Tracker::State& s, FrameStep& f) {
  const TrackerOptions& o = s.options;
  const FrameInput& frame = f.frame;
  if (s.started) {
    f.dt_s = static_cast<double>(frame.t_ns - s.last_t_ns) * 1e-9;
    s.pre_frame.reset(s.bias);
    if (!frame.imu.empty() && frame.t_ns > s.last_t_ns) {
      if (s.pre_frame.integrateInterval(frame.imu, s.last_t_ns, frame.t_ns).ok()) {
        f.imu_frame_ok = true;
        // From the keyframe's time when mapping has re-timed it past the last frame.
        const std::int64_t from_ns = std::max(s.last_t_ns, s.pre_keyframe_end_ns);
        if (s.imu_ok_since_keyframe && s.has_keyframe && frame.t_ns > from_ns) {
          if (s.pre_keyframe.integrateInterval(frame.imu, from_ns, frame.t_ns).ok()) {
            s.pre_keyframe_end_ns = frame.t_ns;
          } else {
            s.imu_ok_since_keyframe = false;
          }
        }
      } else {
        f.result.issue = FrameIssue::kImuGap;
        s.imu_ok_since_keyframe = false;
      }
    } else if (o.use_imu && frame.t_ns > s.last_t_ns) {
      // No IMU at all for this interval: the keyframe's preintegration would silently skip it.
      f.result.issue = FrameIssue::kImuGap;
      s.imu_ok_since_keyframe = false;
    }
  }
  s.appendImu(frame.imu);
}

// The predicted pose and velocity. With the IMU initialised, lost (or waiting for a new map) for longer than the
// IMU can be trusted with the position (TrackerOptions::max_dead_reckoning_s): the prediction holds the position,
// with or without this frame's IMU, and the search is as wide as while relocalising until a frame is tracked.
void predict(const Tracker::State& s, FrameStep& f) {
  const TrackerOptions& o = s.options;
  f.T_pred = s.T_w_s;
  f.v_pred = s.v_w;
  f.dead_reckoning_too_long = s.imu_initialised && o.use_imu && s.untracked_s > o.max_dead_reckoning_s;
  if (!s.started) return;
  if (f.dead_reckoning_too_long) {
    const SO3d dR = f.imu_frame_ok ? s.pre_frame.correctedDeltaR(s.bias) : SO3d();
    f.T_pred = SE3d(s.T_w_s.so3() * dR, s.T_w_s.translation());
    f.v_pred = Vector3d::Zero();
  } else if (s.imu_initialised && o.use_imu && f.imu_frame_ok) {
    const imu::NavState next = s.pre_frame.predict(imu::NavState{s.T_w_s, s.v_w}, s.bias);
    f.T_pred = next.T_w_s;
    f.v_pred = next.v_w;
  } else {
    const SO3d dR = f.imu_frame_ok ? s.pre_frame.correctedDeltaR(s.bias) : SO3d();
    f.T_pred = SE3d(s.T_w_s.so3() * dR, s.T_w_s.translation() + s.v_w * f.dt_s);
  }
}

// 2. ORB features, and their undistorted positions.
void extractFeatures(Tracker::State& s, FrameStep& f) {
  const TrackerOptions& o = s.options;
  const std::int64_t t_orb = steadyNowNs();
  s.keypoint_count = s.orb.extract(f.frame.left, f.frame.width, f.frame.height,
                                   std::span(s.keypoints.data(), static_cast<std::size_t>(o.orb.max_features)),
                                   std::span(s.descriptors.data(), static_cast<std::size_t>(o.orb.max_features)));
  f.keypoints = static_cast<std::size_t>(s.keypoint_count);
  for (std::size_t k = 0; k < f.keypoints; ++k) {
    s.undistorted[k] = s.left.undistortPixel(s.keypoints[k].px.cast<double>());
  }
  f.result.keypoints = s.keypoint_count;
  const std::int64_t t_orb_end = steadyNowNs();
  f.result.times.orb_ns = t_orb_end - t_orb;
  trace::complete("orb", t_orb, t_orb_end, {{"keypoints", s.keypoint_count}});
}

// The frame's end, on every path: the state moves to the frame's pose and the result says where tracking stands.
void finishFrame(Tracker::State& s, FrameStep& f, const SE3d& T, const Vector3d& v) {
  FrameResult& result = f.result;
  s.T_w_s = T;
  s.v_w = v;
  s.untracked_s = result.tracked || !s.started ? 0.0 : s.untracked_s + f.dt_s;
  if (s.started) {
    s.camera_interval_ns = (f.frame.t_ns - f.frame.time_correction_ns) - (s.last_t_ns - s.last_time_correction_ns);
  }
  s.last_t_ns = f.frame.t_ns;
  s.last_time_correction_ns = f.frame.time_correction_ns;
  s.started = true;
  ++s.frames_since_keyframe;
  result.status = s.status;
  result.T_w_s = T;
  result.v_w = v;
  result.bias = s.bias;
  result.imu_initialised = s.imu_initialised;
  result.map_id = s.new_map_requested ? s.requested_map_id : s.map_id;
  result.map_epoch = s.epoch;
  result.has_reference = s.has_keyframe;
  result.reference = s.keyframe.id;
  result.T_ref_s = s.keyframe.T_w_s.inverse() * T;
  result.times.total_ns = steadyNowNs() - f.t_start;
}

// The keyframe message, written into a loaned chunk: keypoints, descriptors, the tracked matches, the IMU since
// the last keyframe and (stereo) the right image.
void fillKeyframe(const Tracker::State& s, const FrameStep& f, KeyframeKind kind, const SE3d& T, const Vector3d& v,
                  KeyframeMessage& m) {
  m.map_epoch = s.epoch;
  m.kind = kind;
  m.continues_frame = kind == KeyframeKind::kNewMap && s.imu_initialised && s.options.use_imu;
  m.state.t_ns = f.frame.t_ns;
  m.time_correction_ns = f.frame.time_correction_ns;
  m.state.T_w_s = toMsg(T);
  m.state.v_w = toArray(v);
  m.state.bias = toMsg(s.bias);
  m.keypoint_count = static_cast<std::uint16_t>(f.keypoints);
  for (std::size_t k = 0; k < f.keypoints; ++k) {
    const features::Keypoint& kp = s.keypoints[k];
    m.keypoints[k] = KeypointMsg{kp.px.x(), kp.px.y(), kp.response, kp.angle_deg, kp.octave};
    m.descriptors[k] = s.descriptors[k];
    m.has_match[k] = 0;
  }
  if (kind == KeyframeKind::kTracked) {
    for (int i = 0; i < s.observation_count; ++i) {
      if (s.outlier[static_cast<std::size_t>(i)] != 0) continue;
      const std::uint16_t k = s.observation_keypoint[static_cast<std::size_t>(i)];
      m.matched[k] = s.snapshot->points[s.observation_point[static_cast<std::size_t>(i)]].id;
      m.has_match[k] = 1;
    }
  }
  m.imu_count = s.keyframe_imu_count - s.keyframe_imu_first;
  std::memcpy(m.imu.data(), s.keyframe_imu.data() + s.keyframe_imu_first, m.imu_count * sizeof(ImuSampleMsg));
  const FrameInput& frame = f.frame;
  if (!frame.right.empty() && frame.right.size() <= m.right_pixels.size()) {
    m.right_width = static_cast<std::uint16_t>(frame.width);
    m.right_height = static_cast<std::uint16_t>(frame.height);
    std::memcpy(m.right_pixels.data(), frame.right.data(), frame.right.size());
  } else {
    m.right_width = 0;
    m.right_height = 0;
  }
}

// Publishes this frame as a keyframe and makes it tracking's reference; false when no chunk could be loaned.
bool publishKeyframe(Tracker::State& s, FrameStep& f, KeyframeKind kind, const SE3d& T, const Vector3d& v) {
  const std::int64_t t0 = steadyNowNs();
  KeyframeMessage* m = f.keyframes.loan();
  if (m == nullptr) {
    f.result.issue = FrameIssue::kKeyframeDropped;
    return false;
  }
  const bool imu_link = s.imu_ok_since_keyframe && s.has_keyframe && kind == KeyframeKind::kTracked;
  m->sequence = s.backlog.publish(t0);
  m->state.id = s.keyframe_ids.next();
  fillKeyframe(s, f, kind, T, v, *m);
  m->publish_steady_ns = steadyNowNs();
  const KeyframeId id = m->state.id;
  f.keyframes.publish();

  if (imu_link && s.pre_keyframe.dt() > 0.0) s.motion_window.addLink(s.keyframe.id, id, s.pre_keyframe);
  s.published[s.published_next] = Tracker::State::Published{id, T, true};
  s.published_next = (s.published_next + 1) % s.published.size();
  s.has_keyframe = true;
  s.keyframe.id = id;
  s.keyframe.t_ns = f.frame.t_ns;
  s.keyframe.T_w_s = T;
  s.keyframe.v_w = v;
  s.keyframe.bias = s.bias;
  s.frames_since_keyframe = -1;  // finishFrame() counts this frame
  s.pre_keyframe.reset(s.bias);
  s.pre_keyframe_end_ns = f.frame.t_ns;
  s.imu_ok_since_keyframe = true;
  s.restartKeyframeImu(f.frame.t_ns);
  s.awaiting = true;
  s.awaiting_id = id;
  f.result.keyframe = true;
  const std::int64_t t_end = steadyNowNs();
  f.result.times.keyframe_ns = t_end - t0;
  // Where a keyframe's journey to the server and back starts.
  trace::complete("keyframe_write", t0, t_end, {{"keyframe", id.counter}});
  return true;
}

// 3. No map yet: ask for one (stereo: one keyframe; mono: keyframes every few frames until mapping has
// initialised from two views).
void trackWithoutMap(Tracker::State& s, FrameStep& f) {
  const TrackerOptions& o = s.options;
  s.status = TrackingStatus::kWaitingForMap;
  // With the IMU initialised, a new map keeps the world frame: the IMU carries the pose (and, in mono, mapping
  // triangulates the new map's first points from those poses).
  const bool keep_frame = s.imu_initialised && o.use_imu;
  const SE3d T = !s.started ? SE3d() : keep_frame ? f.T_pred : SE3d(f.T_pred.so3(), s.T_w_s.translation());
  const Vector3d v = keep_frame ? f.v_pred : Vector3d::Zero();
  ++s.waiting_frames;
  // Stereo maps answer at once; ask again when the first keyframe gave no map (a black frame, say).
  const bool ask_again = s.new_map_requested && s.right && s.waiting_frames > 2 * o.max_lost_frames && !f.mapping.busy;
  if (!s.new_map_requested || ask_again) {
    if (s.keypoint_count >= o.pose.min_inliers) {
      s.requested_map_id = std::max(s.map_id, s.requested_map_id) + 1;
      s.waiting_frames = 0;
      s.new_map_requested = true;
      s.observation_count = 0;
      publishKeyframe(s, f, KeyframeKind::kNewMap, T, v);
    } else {
      f.result.issue = FrameIssue::kFewFeatures;
    }
  } else if (!s.right && s.frames_since_keyframe + 1 >= o.initialisation_max_frames_between &&
             s.keypoint_count >= o.pose.min_inliers) {
    if (f.mapping.full) {
      f.result.keyframe_deferred = true;
      f.result.keyframe_overdue = s.backlog.heldBack(f.frame.t_ns);
      f.result.needs_mapping = true;
    } else {
      s.observation_count = 0;
      publishKeyframe(s, f, KeyframeKind::kTracked, T, v);
    }
  }
  finishFrame(s, f, T, v);
}

// The frame could not be tracked: relocalising, and after too long a new map.
void trackingLost(Tracker::State& s, FrameStep& f) {
  const TrackerOptions& o = s.options;
  FrameResult& result = f.result;
  result.issue = s.keypoint_count < o.pose.min_inliers ? FrameIssue::kFewFeatures : FrameIssue::kPoseRefused;
  s.status = TrackingStatus::kRelocalising;
  // With keyframes pending, the map tracking searched is behind the camera: the frame is carried by the IMU and
  // does not count towards a new map.
  if (f.mapping.busy) {
    result.needs_mapping = true;
  } else {
    ++s.lost_frames;
  }
  result.matches = s.observation_count;
  result.times.pose_ns = f.pose_ns;
  if (s.lost_frames > o.max_lost_frames && s.keypoint_count >= o.pose.min_inliers) {
    // Relocalisation failed for too long: start a new map here, and say so.
    s.requested_map_id = std::max(s.map_id, s.requested_map_id) + 1;
    s.waiting_frames = 0;
    s.new_map_requested = true;
    s.status = TrackingStatus::kWaitingForMap;
    s.observation_count = 0;
    // A stereo map starts from this one keyframe, so it may keep the frame whatever the IMU carried. A monocular
    // one triangulates its first points between keyframes whose poses the IMU carries: after more dead reckoning
    // than max_dead_reckoning_s that state is wrong (the new map would be, and lost again, map after map), so it
    // starts again from two views and initialises the IMU again.
    const bool keep_frame = s.imu_initialised && o.use_imu && (s.right.has_value() || !f.dead_reckoning_too_long);
    s.imu_initialised = keep_frame;
    publishKeyframe(s, f, KeyframeKind::kNewMap, f.T_pred, keep_frame ? f.v_pred : Vector3d::Zero());
  }
  // Dead reckoning meanwhile: the IMU when initialised, otherwise the rotation alone.
  finishFrame(s, f, f.T_pred, s.imu_initialised ? f.v_pred : Vector3d::Zero());
}

std::span<const PoseObservation> observationsOf(const Tracker::State& s) {
  return {s.observations.data(), static_cast<std::size_t>(s.observation_count)};
}
std::span<std::uint8_t> outliersOf(Tracker::State& s) {
  return {s.outlier.data(), static_cast<std::size_t>(s.observation_count)};
}

// 4. Guided search around the prediction and a first pose; a second, narrower search for the points not
// matched yet around that pose, and the pose again. Empty when the frame cannot be tracked.
std::optional<PoseOptimizerResult> searchAndOptimisePose(Tracker::State& s, FrameStep& f) {
  const TrackerOptions& o = s.options;
  const std::size_t n = f.keypoints;
  const std::int64_t t_matching = steadyNowNs();
  const bool relocalising = s.status == TrackingStatus::kRelocalising || f.dead_reckoning_too_long;
  s.observation_count = 0;
  std::fill_n(s.keypoint_taken.begin(), n, std::uint8_t{0});
  std::fill_n(s.point_matched.begin(), s.snapshot->point_count, std::uint8_t{0});
  s.grid.build(std::span(s.keypoints.data(), n), f.frame.width, f.frame.height);
  const double radius = relocalising ? o.relocalisation_radius_px : o.search_radius_px;
  int projected = projectPoints(s, f.T_pred, radius, false);
  s.matcher.search(std::span(s.projected.data(), static_cast<std::size_t>(projected)), s.grid,
                   std::span(s.descriptors.data(), n), o.search,
                   std::span(s.match_of_point.data(), static_cast<std::size_t>(projected)));
  collectMatches(s, projected);
  std::int64_t t_pose = steadyNowNs();
  f.result.times.matching_ns = t_pose - t_matching;
  trace::complete("matching", t_matching, t_pose, {{"matches", s.observation_count}});

  auto first = optimizePose(observationsOf(s), f.T_pred, s.T_s_c, s.intrinsics, o.pose, outliersOf(s));
  std::int64_t t_pose_end = steadyNowNs();
  f.pose_ns = t_pose_end - t_pose;
  trace::complete("pose_optimisation", t_pose, t_pose_end);
  if (!first) return std::nullopt;

  // Second search: points not matched yet, around their projection with the refined pose.
  const std::int64_t t_second = steadyNowNs();
  for (int i = 0; i < s.observation_count; ++i) {  // outliers give their keypoints and points back
    if (s.outlier[static_cast<std::size_t>(i)] == 0) continue;
    s.keypoint_taken[s.observation_keypoint[static_cast<std::size_t>(i)]] = 0;
  }
  projected = projectPoints(s, first->T_w_s, o.refine_radius_px, true);
  s.matcher.search(std::span(s.projected.data(), static_cast<std::size_t>(projected)), s.grid,
                   std::span(s.descriptors.data(), n), o.search,
                   std::span(s.match_of_point.data(), static_cast<std::size_t>(projected)));
  // Drop the first round's outliers before adding the new matches.
  int kept = 0;
  for (int i = 0; i < s.observation_count; ++i) {
    if (s.outlier[static_cast<std::size_t>(i)] != 0) continue;
    const auto src = static_cast<std::size_t>(i);
    const auto dst = static_cast<std::size_t>(kept++);
    s.observations[dst] = s.observations[src];
    s.observation_point[dst] = s.observation_point[src];
    s.observation_keypoint[dst] = s.observation_keypoint[src];
  }
  s.observation_count = kept;
  collectMatches(s, projected);
  t_pose = steadyNowNs();
  f.result.times.matching_ns += t_pose - t_second;
  trace::complete("matching", t_second, t_pose, {{"matches", s.observation_count}});

  auto second = optimizePose(observationsOf(s), first->T_w_s, s.T_s_c, s.intrinsics, o.pose, outliersOf(s));
  t_pose_end = steadyNowNs();
  f.pose_ns += t_pose_end - t_pose;
  trace::complete("pose_optimisation", t_pose, t_pose_end);
  f.result.times.pose_ns = f.pose_ns;
  if (!second) return std::nullopt;
  return *second;
}

// 5. Motion-only visual-inertial BA: over the window of newest keyframes when their IMU chain holds, else against
// the newest keyframe alone. Refines T and v in place.
void refineWithImu(Tracker::State& s, FrameStep& f, SE3d& T, Vector3d& v) {
  const TrackerOptions& o = s.options;
  if (!(s.imu_initialised && o.use_imu && s.has_keyframe && s.imu_ok_since_keyframe && s.pre_keyframe.dt() > 0.0))
    return;
  const std::int64_t t_ba = steadyNowNs();
  const std::span<MotionWindowKeyframe> window =
      s.motion_window.build(s.snapshot, o.motion_ba_keyframes, s.keyframe, s.pre_keyframe);
  Result<InertialPoseResult> inertial = Error{ErrorCode::kNotFound, "no window"};
  if (window.size() >= 2) {
    auto windowed =
        optimizeMotionWindow(window, observationsOf(s), T, f.v_pred, s.T_s_c, s.intrinsics, o.pose, outliersOf(s));
    if (windowed) {
      InertialPoseResult r;
      r.T_w_s = windowed->T_w_s;
      r.v_w = windowed->v_w;
      r.inliers = windowed->inliers;
      inertial = r;
    }
  }
  if (!inertial) {  // n = 1, a broken chain, or a window that failed: the newest keyframe alone, held
    const InertialAnchor anchor{s.keyframe.T_w_s, s.keyframe.v_w, s.keyframe.bias, &s.pre_keyframe};
    inertial =
        optimizePoseInertial(observationsOf(s), T, f.v_pred, anchor, s.T_s_c, s.intrinsics, o.pose, outliersOf(s));
  }
  if (inertial) {
    T = inertial->T_w_s;
    v = inertial->v_w;
    f.result.inliers = inertial->inliers;
  } else {
    // Keep the visual pose; the outlier flags are recomputed for the keyframe's matches.
    (void)optimizePose(observationsOf(s), T, s.T_s_c, s.intrinsics, o.pose, outliersOf(s));
  }
  const std::int64_t t_ba_end = steadyNowNs();
  f.result.times.motion_ba_ns = t_ba_end - t_ba;
  trace::complete("motion_ba", t_ba, t_ba_end);
}

// 6. The keyframe decision on the tracked frame, and the keyframe when mapping's backlog lets it through.
void considerKeyframe(Tracker::State& s, FrameStep& f, const SE3d& T, const Vector3d& v) {
  const TrackerOptions& o = s.options;
  int covered = 0;
  for (int i = 0; i < s.observation_count; ++i) {
    if (s.outlier[static_cast<std::size_t>(i)] != 0) continue;
    s.coverage_px[static_cast<std::size_t>(covered++)] =
        s.keypoints[s.observation_keypoint[static_cast<std::size_t>(i)]].px;
  }
  TrackingState tracking_state;
  tracking_state.frames_since_keyframe = s.frames_since_keyframe + 1;
  tracking_state.tracked_points = f.result.inliers;
  tracking_state.coverage = gridCoverage(std::span(s.coverage_px.data(), static_cast<std::size_t>(covered)),
                                         f.frame.width, f.frame.height, o.keyframe.grid_columns, o.keyframe.grid_rows);
  if (s.keyframe_coverage <= 0.0) s.keyframe_coverage = tracking_state.coverage;  // first frame on a new map
  tracking_state.keyframe_coverage = s.keyframe_coverage;
  if (s.has_keyframe) tracking_state.interval_s = static_cast<double>(f.frame.t_ns - s.keyframe.t_ns) * 1e-9;
  KeyframeDecisionOptions decision_options = o.keyframe;
  if (!s.imu_initialised && o.use_imu) decision_options.max_frames_between = o.initialisation_max_frames_between;
  if (!o.use_imu) decision_options.max_interval_s = 0.0;  // the cap is for the IMU links' sake
  f.result.keyframe_reason = decideKeyframe(tracking_state, decision_options);
  if (f.result.keyframe_reason == KeyframeReason::kNone) return;
  const KeyframeGate gate = s.backlog.gate(f.mapping, tracking_state.tracked_points);
  if (!gate.publish) {
    f.result.keyframe_deferred = true;
    f.result.keyframe_overdue = s.backlog.heldBack(f.frame.t_ns);
    f.result.needs_mapping = gate.needs_mapping;
  } else if (publishKeyframe(s, f, KeyframeKind::kTracked, T, v)) {
    s.keyframe_coverage = tracking_state.coverage;
  }
}

}  // namespace

FrameResult Tracker::track(const FrameInput& frame, KeyframeSink& keyframes) {
  State& s = *s_;
  FrameResult result;
  FrameStep f{frame, keyframes, result};
  f.t_start = steadyNowNs();
  integrateImu(s, f);
  predict(s, f);
  // Mapping's lag: while keyframes are pending, keyframes only when tracking would otherwise be lost, none beyond
  // the backlog's bound, and no new map for lost frames (see MappingLagOptions).
  f.mapping = s.backlog.pressure(f.t_start);
  result.pending_keyframes = f.mapping.pending;
  extractFeatures(s, f);

  const bool have_map = s.snapshot != nullptr && s.snapshot->map_id == s.map_id && !s.new_map_requested &&
                        s.status != TrackingStatus::kWaitingForMap;
  if (!have_map) {
    trackWithoutMap(s, f);
    return result;
  }

  const std::optional<PoseOptimizerResult> pose = searchAndOptimisePose(s, f);
  if (!pose) {
    trackingLost(s, f);
    return result;
  }
  SE3d T = pose->T_w_s;
  Vector3d v = f.dt_s > 0.0 ? Vector3d((T.translation() - s.T_w_s.translation()) / f.dt_s) : s.v_w;
  result.matches = s.observation_count;
  result.inliers = pose->inliers;
  refineWithImu(s, f, T, v);
  s.status = TrackingStatus::kTracking;
  s.lost_frames = 0;
  considerKeyframe(s, f, T, v);
  result.tracked = true;
  finishFrame(s, f, T, v);
  return result;
}

}  // namespace cvislam::agent
