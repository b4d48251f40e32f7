// The agent's mapping thread, one keyframe at a time (CVI-SLAM IV-C): insert the keyframe into the
// fixed-capacity local map (bounded to N own keyframes), link the map points tracking matched, fuse existing
// points into it by projection and descriptor, make new points (stereo depth from the second camera;
// triangulation against the previous keyframes), cull points that are seldom found, run local BA over the
// newest M keyframes, initialise the IMU once enough keyframes are there, and write the refined local map
// into a snapshot message for tracking.
//
// Monocular maps start from two views (essential matrix, two_view_initialiser); stereo maps from the first
// keyframe alone.
//
// Runs in the mapping thread; it may allocate (Ceres does), tracking never waits for it.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>

#include "agent_rt/map/local_map.hpp"
#include "agent_rt/mapping/keyframe_retention.hpp"
#include "agent_rt/mapping/local_bundle_adjustment.hpp"
#include "agent_rt/messages/messages.hpp"
#include "common/camera/camera_model.hpp"
#include "common/core/result.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/triangulation.hpp"
#include "common/imu/visual_inertial_alignment.hpp"

namespace cvislam::agent {

struct StereoOptions {
  double max_epipolar_error_px = 2.0;  // distance of a right keypoint from the epipolar curve, in cam1 pixels
  int max_distance = 50;               // Hamming bits
  float ratio = 0.8F;                  // best / second best
  double min_depth_m = 0.2;
  // Farther points get their depth from triangulation over time: stereo depth beyond ~45 baselines (EuRoC:
  // 11 cm) is too uncertain to seed a point with. 40 m here cost 1-3 cm of ATE on the simulated flights.
  double max_depth_m = 5.0;
  // Every keypoint's cam1 match (at any depth) as a second observation in local BA: keeps the map's depth
  // and scale tied to the baseline, not only the IMU.
  bool use_in_ba = true;
};

// What the server sends down (CVI-SLAM IV-C.2, IV-D): its K keyframes most covisible with the agent's
// position enter the local map as anchors, held fixed in local BA (Eq. 10), with their points, which tracking
// matches like any other; the server's refined states of the agent's own keyframes replace the local ones.
struct DownlinkOptions {
  bool use_anchors = true;
  int max_anchor_keyframes = 32;  // anchors held at once (the server's K is 10); the pool holds N own beside them
  int max_anchor_points = 3000;   // the server's points held at once, so that the agent's own keep room
  // Corrections are applied to own keyframes outside the local BA window (one in the window takes its
  // correction when it leaves the window): held fixed there, they pull the window onto the server's map over the
  // next local BAs, so tracking never sees the step at once. Off by default: on the simulated missions they
  // helped the drifting MH_05 replay but made overlap2 and the live steps worse than anchors alone (docs/agent.md).
  bool apply_corrections = false;
};

struct MapperOptions {
  AgentId agent = 0;
  int max_keyframes = 20;              // N: the agent's own keyframes kept in the local map
  KeyframeRetentionOptions retention;  // which of them leaves when the map is full
  LocalBundleAdjustmentOptions ba;     // window = M
  CullOptions cull;
  features::OrbOptions orb;  // for the second camera's image (stereo)
  StereoOptions stereo;
  geometry::TriangulationOptions triangulation;
  int triangulation_neighbours = 2;   // previous keyframes searched for new points
  double fuse_radius_px = 4.0;        // at level 0
  int fuse_max_distance = 40;         // Hamming bits
  double fuse_max_depth_ratio = 0.2;  // duplicates: depths in the keyframe's camera within this share
  bool use_imu = true;
  int imu_init_keyframes = 15;      // keyframes at which the IMU initialisation is made (paper: 15)
  int imu_init_max_keyframes = 20;  // monocular: still failing then, the map is started again
  // Monocular: from this many keyframes on, the alignment is tried at every keyframe, and the initialisation is made
  // as soon as its scale has settled: the last three attempts' scales within imu_init_scale_agreement of each other
  // (relative). At imu_init_keyframes it is made whatever they were. Motion that shows the scale clearly gives the
  // metric map sooner; motion that does not is not initialised on a scale that still moves.
  int imu_init_min_keyframes = 10;
  double imu_init_scale_agreement = 0.0075;
  // Monocular: the next keyframes' local BAs after the IMU initialisation take every own keyframe, not the
  // window. The scale estimated from the first seconds then goes on being estimated with all the motion since,
  // rather than being held by the keyframes a window keeps fixed. (ORB-SLAM3 refines scale and gravity over the
  // whole map a few seconds after the initialisation; here the map is the local one.)
  int imu_init_full_window_keyframes = 10;
  // Coming back over a place mapped long ago (a keyframe kept for its place, KeyframeRetentionOptions), the window
  // meets the drift since, with that keyframe held fixed. The next this-many keyframes' local BAs take every own
  // keyframe, not the window, so that the correction spreads over the whole local map instead of bending the
  // window: on the simulated `loop`, the window's scale came out up to 4 % short for a few seconds. 0: never.
  int return_full_window_keyframes = 20;
  imu::VisualInertialAlignmentOptions alignment;
  int mono_init_min_matches = 80;
  double mono_init_min_parallax_deg = 1.0;  // median, rotation compensated
  // Following the reference's keypoints to the next keyframes (monocular_start.hpp): the window around the
  // position the gyro predicts, at level 0, the largest descriptor distance, and Lowe's ratio within the window.
  double mono_init_search_radius_px = 100.0;
  int mono_init_max_distance = 50;
  double mono_init_ratio = 0.9;
  DownlinkOptions downlink;
  // Mapping behind tracking (ORB-SLAM's local mapping does the same): when the next keyframe is already waiting
  // (or tracking has asked, its keyframe overdue: the agent's YieldRequests), this keyframe's local BA is skipped
  // (never two in a row, nor the one of the keyframe that makes the monocular map), and a running one stops after
  // its current iteration (after one iteration at least). The next keyframe's BA refines the same window, so the
  // map stays consistent; tracking gets the keyframe's points sooner. At `--pace sync` tracking waits for every
  // answer, so nothing ever waits, tracking never asks, and nothing changes.
  bool yield_to_waiting_keyframes = true;

  [[nodiscard]] Status validate() const;
};

struct MapperReport {
  bool new_map = false;
  bool imu_initialised_now = false;
  bool imu_initialisation_failed = false;
  bool map_restarted = false;  // monocular IMU initialisation failed up to the limit
  bool mono_initialised_now = false;
  int linked = 0;          // tracking's matches linked
  int fused = 0;           // existing points found again by projection
  int merged = 0;          // duplicate points merged into another
  int stereo_matches = 0;  // keypoints of the keyframe with a cam1 match
  int stereo_points = 0;
  int triangulated = 0;
  int culled = 0;
  int evicted = 0;
  bool ba_ran = false;
  bool ba_skipped = false;         // the next keyframe was waiting, or tracking asked (yield_to_waiting_keyframes)
  bool returned_to_place = false;  // this BA's window came back over a place mapped long ago (whole-map BAs next)
  LocalBundleAdjustmentSummary ba;
  std::int64_t ba_ns = 0;
  std::uint64_t lost_messages = 0;      // keyframe messages missing before this one
  std::uint32_t delta_events_lost = 0;  // structural changes beyond the delta's capacity
  std::int64_t time_correction_ns = 0;  // the estimated correction to the calibrated camera-IMU time offset, after
  std::string note;                     // why an initialisation did not succeed, for the log
};

// What one downlink message did to the local map.
struct DownlinkReport {
  bool stale = false;   // a message of an older stream or sequence than one applied already: ignored
  std::string skipped;  // why the covisible map was not used (another agent map, the map not ready), or empty
  int anchors_added = 0;
  int anchors_released = 0;  // left the server's selection
  int anchors_held = 0;      // after this message
  int anchor_poses_updated = 0;
  int anchors_over_capacity = 0;  // selected and sent, but the pool's share for anchors is full
  int points_added = 0;
  int points_linked = 0;  // the server's point was one the local map holds already (own, or sent before)
  int points_updated = 0;
  int points_over_capacity = 0;  // left out: max_anchor_points reached, or the pool is full
  int unknown_references = 0;    // observations of points neither in the message nor in the map, updates of
                                 // keyframes or points no longer held: skipped
  int corrections_applied = 0;
  int corrections_deferred = 0;  // in the local BA window: applied when the keyframe leaves it
  int corrections_skipped = 0;   // no longer in the local map
  double largest_correction_m = 0.0;
  double largest_correction_deg = 0.0;
  // How far the server's frame, as it expresses the agent's world, moved against the agent's own frame since the
  // last correction (re-estimated from the newest corrected own keyframe) [m].
  double frame_change_m = 0.0;
};

class Mapper {
 public:
  // `right` and T_c0_c1 only for stereo.
  static Result<std::unique_ptr<Mapper>> create(const MapperOptions& options, const camera::CameraModel& left,
                                                const camera::CameraModel* right, const geometry::SE3d& T_s_c,
                                                const geometry::SE3d& T_c0_c1);
  ~Mapper();
  Mapper(const Mapper&) = delete;
  Mapper& operator=(const Mapper&) = delete;

  // Processes one keyframe and writes the resulting local map into `snapshot` and, when given, what changed
  // into `delta` (for the link to the server). `keyframe_waiting`, when given, says whether the next keyframe
  // has arrived or tracking has asked mapping to yield (see MapperOptions::yield_to_waiting_keyframes).
  Result<MapperReport> process(const KeyframeMessage& keyframe, MapSnapshotMessage& snapshot,
                               MapDeltaMessage* delta = nullptr, const std::function<bool()>& keyframe_waiting = {});
  // The same in two phases, each writing a delta of its own, so that the keyframe can leave for the server before
  // its local BA: insert() puts the keyframe into the map (links, fused and new points, culling) and writes it in
  // full into `delta`; refine() runs the local BA and the IMU initialisation, writes the snapshot and, into
  // `delta`, the refined states and positions. refine() follows a successful insert() of the same keyframe.
  Result<MapperReport> insert(const KeyframeMessage& keyframe, MapDeltaMessage* delta);
  void refine(const KeyframeMessage& keyframe, MapperReport& report, MapSnapshotMessage& snapshot,
              MapDeltaMessage* delta, const std::function<bool()>& keyframe_waiting = {});

  // Applies one downlink message (link -> mapping) between keyframes. Messages of a stream apply in sequence;
  // one older than the newest applied is ignored (stale), one that repeats what the map holds changes nothing.
  Result<DownlinkReport> applyDownlink(const AnchorMessage& message);

  [[nodiscard]] const LocalMap& map() const;
  [[nodiscard]] bool imuInitialised() const;

  struct State;  // the implementation's, in mapper.cpp

 private:
  explicit Mapper(std::unique_ptr<State> state);
  std::unique_ptr<State> s_;
};

}  // namespace cvislam::agent
