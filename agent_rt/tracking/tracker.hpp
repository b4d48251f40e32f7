// The agent's tracking thread, one frame at a time (CVI-SLAM IV-C): IMU prediction, ORB extraction, guided
// projection search against the local map, pose optimisation, a second search, motion-only visual-inertial
// BA, and the keyframe decision. A keyframe is written straight into a message loaned from the keyframe
// channel (iceoryx in the agent) and published to mapping.
//
// The map tracking matches against is the newest MapSnapshotMessage from mapping, which the caller keeps
// alive (in the agent it is an iceoryx chunk) and hands over with adoptSnapshot(). Tracking never waits on
// mapping: until a newer snapshot comes, it keeps the one it has.
//
// After create(), track() does not allocate (all buffers are fixed-size members) except on its error paths,
// which format messages: an IMU gap, a refused pose. test/agent_rt/tracker_allocation_test counts it.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <span>

#include <Eigen/Core>

#include "agent_rt/messages/messages.hpp"
#include "agent_rt/tracking/keyframe_decision.hpp"
#include "agent_rt/tracking/mapping_backlog.hpp"
#include "agent_rt/tracking/pose_optimizer.hpp"
#include "agent_rt/tracking/projection_search.hpp"
#include "common/camera/camera_model.hpp"
#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

struct TrackerOptions {
  AgentId agent = 0;
  features::OrbOptions orb;  // max_features <= kMaxKeypointsPerKeyframe
  ProjectionSearchOptions search;
  double search_radius_px = 15.0;          // first search around the predicted projection, at pyramid level 0
  double refine_radius_px = 4.0;           // second search, after the first pose
  double relocalisation_radius_px = 60.0;  // search radius while relocalising
  double sigma_px = 1.0;                   // keypoint noise at level 0; x scale_factor per level
  PoseOptimizerOptions pose;
  KeyframeDecisionOptions keyframe;
  MappingLagOptions lag;
  int initialisation_max_frames_between = 3;  // keyframe spacing until the IMU is initialised (paper: 3)
  int max_lost_frames = 20;                   // frames of failed relocalisation before a new map
  // How long the IMU alone may carry the position while tracking is lost or waits for a new map (once the IMU is
  // initialised; a gap in the images between two tracked frames does not count). IMU-only velocity drifts with
  // every error in gravity and bias (right after the IMU initialisation: metres per second within seconds, and a
  // new map started at that velocity was lost again at once, map after map). Beyond this the prediction holds
  // the position and takes only the rotation from the gyro, a new map starts at rest, and the search is as wide
  // as while relocalising until a frame is tracked again.
  double max_dead_reckoning_s = 1.0;
  bool use_imu = true;  // prediction and motion-only BA with the IMU, once initialised
  // n: the newest keyframes in motion-only BA with the frame (paper IV-C), 1 to kMaxMotionBaKeyframes
  // (CVISLAM_MAX_MOTION_BA_KEYFRAMES). The oldest of them is held; the others' poses and velocities are
  // optimised with the frame's (see inertial_pose_optimizer.hpp). 1: the newest keyframe alone, held.
  int motion_ba_keyframes = 1;
  imu::ImuNoise noise;

  [[nodiscard]] Status validate() const;
};

enum class TrackingStatus : std::uint8_t {
  kWaitingForMap,  // a new map was requested and mapping has not answered yet
  kTracking,
  kRelocalising,  // the last frame failed; searching wider around the prediction
};
const char* toString(TrackingStatus status);

// What the keyframe channel must provide: a message to write in place, then publish it. In the agent, a
// loaned iceoryx chunk; in tests, any buffer.
class KeyframeSink {
 public:
  virtual ~KeyframeSink() = default;
  virtual KeyframeMessage* loan() = 0;  // nullptr when no chunk is free (the keyframe is then dropped)
  virtual void publish() = 0;           // publishes the loaned message
};

struct FrameInput {
  std::int64_t t_ns = 0;
  std::span<const std::uint8_t> left;   // cam0, row-major 8-bit, width x height
  std::span<const std::uint8_t> right;  // cam1 at the same time, or empty
  int width = 0;
  int height = 0;
  // IMU samples covering [previous frame's t_ns, t_ns]: one at or before the previous frame, one at or after
  // this one. Empty when there is no IMU.
  std::span<const dataset::ImuSample> imu;
  // The correction to the calibrated camera-IMU time offset that t_ns carries (timeCorrectionForNextFrameNs()).
  std::int64_t time_correction_ns = 0;
};

struct StageTimes {
  std::int64_t orb_ns = 0;
  std::int64_t matching_ns = 0;
  std::int64_t pose_ns = 0;
  std::int64_t motion_ba_ns = 0;
  std::int64_t keyframe_ns = 0;
  std::int64_t total_ns = 0;
};

enum class FrameIssue : std::uint8_t { kNone, kImuGap, kFewFeatures, kPoseRefused, kKeyframeDropped };
const char* toString(FrameIssue issue);

struct FrameResult {
  TrackingStatus status = TrackingStatus::kWaitingForMap;
  bool tracked = false;  // the pose below comes from matches against the map
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;             // the IMU biases the frame was predicted with
  bool imu_initialised = false;  // the world frame is gravity-aligned and metric (before: up to scale in mono)
  std::uint32_t map_id = 0;
  std::uint32_t map_epoch = 0;
  KeyframeId reference;  // the newest keyframe when the frame was tracked
  bool has_reference = false;
  geometry::SE3d T_ref_s;  // the frame relative to that keyframe, as tracked
  int keypoints = 0;
  int matches = 0;
  int inliers = 0;
  bool keyframe = false;
  KeyframeReason keyframe_reason = KeyframeReason::kNone;
  bool keyframe_deferred = false;  // the rules asked for a keyframe; mapping was busy (see MappingLagOptions)
  // Keyframes have been held back for MappingLagOptions::yield_request_after_s: the caller should ask mapping to
  // cut its local BA short (the agent does, through MappingYieldRequests).
  bool keyframe_overdue = false;
  int pending_keyframes = 0;  // published and not yet answered by mapping, when the frame was tracked
  // Tracking needs mapping's answer to go on well: a keyframe it needed was held back by a full backlog, or it
  // is lost while keyframes are pending. A caller without a clock (--pace fast) waits for mapping here.
  bool needs_mapping = false;
  FrameIssue issue = FrameIssue::kNone;
  StageTimes times;
};

class Tracker {
 public:
  // `right` may be null (monocular). Buffers for the largest image are allocated here.
  static Result<std::unique_ptr<Tracker>> create(const TrackerOptions& options, const camera::CameraModel& left,
                                                 const camera::CameraModel* right, const geometry::SE3d& T_s_c);
  ~Tracker();
  Tracker(const Tracker&) = delete;
  Tracker& operator=(const Tracker&) = delete;

  // Hands over mapping's newest snapshot, which must stay valid until the next adoptSnapshot(). Moves the
  // tracking state into the snapshot's world frame and onto its refined keyframe states.
  void adoptSnapshot(const MapSnapshotMessage* snapshot);

  FrameResult track(const FrameInput& frame, KeyframeSink& keyframes);

  // The sensor stream started again (a driver restarted) and its next frame, at `t_ns`, may be on a new clock: no
  // IMU or motion links it to the frames before. That frame is searched for widely around the last pose, held; if
  // it is not found, a new map starts at once rather than after max_lost_frames of relocalising against a
  // prediction from the old clock.
  void restartStream(std::int64_t t_ns);

  // The correction to the calibrated camera-IMU time offset that the next frame's time should carry: mapping's
  // estimate from the snapshot, taken at once, since a frame whose time lags its image's is placed by the IMU
  // where the image was not. Only a step back is bounded, to half the last frame interval (before any frame:
  // kMaxTimeCorrectionStepBackNs), so that frame times stay in order.
  std::int64_t timeCorrectionForNextFrameNs();
  static constexpr std::int64_t kMaxTimeCorrectionStepBackNs = 5'000'000;

  [[nodiscard]] TrackingStatus status() const;
  [[nodiscard]] bool imuInitialised() const;
  // The identity of the newest keyframe published and not yet answered by a snapshot (for a caller that
  // waits on mapping); invalid when none.
  [[nodiscard]] bool awaitingKeyframe(KeyframeId* id) const;
  // Keyframes published and not yet answered by a snapshot (those older than lag.answer_timeout_s left out).
  [[nodiscard]] int pendingKeyframes() const;

  struct State;  // the implementation's, in tracker.cpp

 private:
  explicit Tracker(std::unique_ptr<State> state);
  std::unique_ptr<State> s_;
};

}  // namespace cvislam::agent
