// Global bundle adjustment of one server map (CVI-SLAM Eq. 11), and how its result (or any other correction of
// keyframe poses: loop closure, merges) is applied to a map that kept changing while the solve ran.
//
// Problem: every keyframe's pose, and velocity and biases where its agent uses the IMU; every map point seen by
// at least two keyframes (or by both cameras of one), as one world-position block, so that SPARSE_SCHUR
// eliminates points. Factors: reprojection (cam0, and cam1 for stereo matches), Cauchy loss; IMU
// preintegration and bias random walk only between consecutive keyframes of one agent (the IMU link the
// agent sent, preintegrated from its raw samples); a prior on the oldest keyframe's pose for the gauge.
// Two steps, as the paper says: points, velocities and biases with the poses held, then everything.
//
// The solve runs on a snapshot (GbaSnapshot), taken under the map's read lock, so ingest never waits for it.
// applyCorrections() writes the result back under the write lock: optimised keyframes take the change the solve
// made (T_after T_before^-1 applied to their current state, so an agent's update that arrived meanwhile is
// kept); keyframes that arrived meanwhile take the change of their agent's nearest optimised keyframe; points
// take their own change, or their reference keyframe's.
#pragma once

#include <atomic>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/factors/pinhole_intrinsics.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"
#include "server_cloud/stack/map_content.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::server::backend {

struct GlobalBaOptions {
  double sigma_px = 1.0;              // keypoint noise at pyramid level 0
  double pyramid_scale_factor = 1.2;  // noise grows by this per octave
  double cauchy_scale = 1.0;          // on whitened residuals
  int structure_iterations = 5;       // step 1: poses held
  int full_iterations = 15;           // step 2: everything
  int threads = 2;
  double max_solver_time_s = 120.0;  // per step
  double gauge_sigma_m = 1e-4;       // the prior on the oldest keyframe's pose
  double gauge_sigma_rad = 1e-5;
  // With IMU on every agent, hold only the oldest keyframe's position and yaw (the visual-inertial gauge) and
  // leave its roll and pitch to gravity. Off: all six (the paper's prior on one keyframe's pose).
  bool gauge_position_yaw_only = false;

  [[nodiscard]] Status validate() const;
};

// What the solve needs of an agent.
struct GbaAgent {
  factors::PinholeIntrinsics cam0;
  geometry::SE3d T_c0_s;
  std::optional<factors::PinholeIntrinsics> cam1;  // stereo
  geometry::SE3d T_c1_s;
  bool uses_imu = false;
  imu::ImuNoise noise;
};

struct GbaObservation {
  std::uint32_t point = 0;  // index into GbaSnapshot::points
  Eigen::Vector2d px_undistorted = Eigen::Vector2d::Zero();
  std::uint8_t octave = 0;
  bool second_camera = false;
};

struct GbaKeyframe {
  KeyframeId id;
  std::uint32_t agent_map = 0;
  std::int64_t t_ns = 0;
  geometry::SE3d T_w_s;  // optimised in place; T_w_s_before keeps the start
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
  geometry::SE3d T_w_s_before;
  int imu_from = -1;  // index of the IMU-linked previous keyframe, or -1
  std::optional<imu::Preintegration> preintegration;
  std::vector<GbaObservation> observations;
};

struct GbaPoint {
  MapPointId id;
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();  // optimised in place
  Eigen::Vector3d p_w_before = Eigen::Vector3d::Zero();
};

struct GbaSnapshot {
  MapId map = 0;
  std::vector<GbaKeyframe> keyframes;  // by (agent, counter)
  std::vector<GbaPoint> points;
  std::map<AgentId, GbaAgent> agents;
};

// The camera and IMU calibration of every agent of a mission (from their Hello).
using AgentSensorsMap = std::map<AgentId, AgentSensors>;

// Copies what the solve needs. kFailedPrecondition names an agent whose sensors are unknown.
Result<GbaSnapshot> makeGbaSnapshot(const MapContent& map, const AgentSensorsMap& sensors);

struct GlobalBaSummary {
  int keyframes = 0;
  int points = 0;
  int reprojection_factors = 0;
  int imu_factors = 0;
  int structure_iterations = 0;
  int full_iterations = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
  double structure_s = 0.0;
  double full_s = 0.0;
  bool cancelled = false;  // `cancel` was raised: the snapshot holds a partial result, not to be applied
};

// Optimises the snapshot in place. `cancel`, when given, is polled after every iteration.
Result<GlobalBaSummary> runGlobalBa(GbaSnapshot& snapshot, const GlobalBaOptions& options,
                                    const std::atomic<bool>* cancel = nullptr);

// One keyframe's change: its pose before and after an optimisation; velocity and biases when it estimated them.
struct KeyframeCorrection {
  KeyframeId id;
  geometry::SE3d T_w_s_before;
  geometry::SE3d T_w_s_after;
  std::optional<std::pair<Eigen::Vector3d, imu::ImuBias>> velocity_bias_after;
};
struct PointCorrection {
  MapPointId id;
  Eigen::Vector3d p_w_before;
  Eigen::Vector3d p_w_after;
};

struct AppliedCorrections {
  int keyframes_optimised = 0;
  int keyframes_propagated = 0;  // arrived after the snapshot
  int points_optimised = 0;
  int points_propagated = 0;
  std::vector<KeyframeId> changed;  // every keyframe whose state changed (for the downlink)
  // Per (agent, agent map): the change of its newest keyframes in this map (windowChange), for the agent map's
  // T_m_w, so that what the agent sends next lands where the corrected map expects it.
  std::map<std::pair<AgentId, std::uint32_t>, geometry::SE3d> frame_change;
};

// One corrected keyframe's change and its position before it.
struct TimedChange {
  geometry::SE3d delta;
  Eigen::Vector3d p_before;
};

// The change of an agent map's frame from the changes of its `window` newest corrected keyframes (by time, in
// `series`, which is not empty): the mean rotation, and the translation that fits their positions given it.
// A window of 1 is the newest keyframe's own change.
geometry::SE3d windowChange(const std::map<std::int64_t, TimedChange>& series, int window);

struct ApplyOptions {
  // The corrected keyframes' state is then the server's refined one (ServerKeyframe::refined, which the downlink
  // requires of another agent's keyframes): true for a GBA. A loop's pose graph moves keyframes without their
  // points' evidence and clears the flag, so that its crude states wait for the GBA that follows it.
  bool marks_refined = true;
  int frame_window = 1;  // how many of an agent map's newest corrected keyframes its frame follows (windowChange)
};
// Applies corrections computed on a snapshot to the map as it is now (see the header comment).
AppliedCorrections applyCorrections(MapContent& map, const std::vector<KeyframeCorrection>& keyframes,
                                    const std::vector<PointCorrection>& points, const ApplyOptions& options = {});

// The corrections a solved snapshot implies.
std::vector<KeyframeCorrection> keyframeCorrections(const GbaSnapshot& snapshot);
std::vector<PointCorrection> pointCorrections(const GbaSnapshot& snapshot);

}  // namespace cvislam::server::backend
