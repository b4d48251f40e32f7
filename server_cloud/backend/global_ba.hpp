// Global bundle adjustment of one server map (CVI-SLAM Eq. 11), and how its result (or any other correction of
// keyframe poses: loop closure, merges) is applied to a map that kept changing while the solve ran.
//
// Problem: every keyframe's pose, and velocity and biases where its agent uses the IMU; every map point seen by
// at least two keyframes (or by both cameras of one), as one world-position block, so that the solver eliminates
// points (schur_solver.hpp, or Ceres' SPARSE_SCHUR). Factors: reprojection (cam0, and cam1 for stereo matches), Cauchy
// loss; IMU preintegration and bias random walk only between consecutive keyframes of one agent (the IMU link the agent
// sent, preintegrated from its raw samples); a prior on the oldest keyframe's pose for the gauge. Two steps, as the
// paper says: points, velocities and biases with the poses held, then everything.
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
#include <set>
#include <string>
#include <unordered_set>
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
  // Step 1 (poses held) settles the points; its first iteration does nearly all of that, and each one costs
  // as much as a third of a full iteration (the evaluation of every reprojection factor).
  int structure_iterations = 1;
  int full_iterations = 15;  // step 2: everything, at most
  // Either step stops once an iteration lowers the cost by less than this fraction. The cost is then within
  // 0.01 % of where more iterations end, which move the keyframes along the solution's flat directions (a slow
  // bend of a long lap) by cm without a gain in cost (bench_global_ba).
  double function_tolerance = 1e-4;
  int threads = 2;
  // Who solves both steps: the server's own Levenberg-Marquardt with the points eliminated in one pass
  // (schur_solver.hpp), or Ceres, kept to compare against and to fall back on.
  enum class Solver { kSchur, kCeres };
  Solver solver = Solver::kSchur;
  // With Ceres: the reduced (keyframe) system of each step factorised (SPARSE_SCHUR), or solved by
  // preconditioned conjugate gradients without forming it (ITERATIVE_SCHUR, SCHUR_JACOBI).
  bool iterative_schur = false;
  double max_solver_time_s = 120.0;  // per step
  // The whole solve's time, both steps and the problem's build: no iteration is started that would end past it
  // (judged by the one before), but each step takes its first. Ceres is given the time left as its own limit,
  // which it checks after each iteration. 0: none.
  double time_budget_s = 0.0;
  double gauge_sigma_m = 1e-4;  // the prior on the oldest keyframe's pose
  double gauge_sigma_rad = 1e-5;
  // With IMU on every agent, hold only the oldest keyframe's position and yaw (the visual-inertial gauge) and
  // leave its roll and pitch to gravity. Off: all six (the paper's prior on one keyframe's pose).
  bool gauge_position_yaw_only = false;

  [[nodiscard]] Status validate() const;
};

// "schur" or "ceres"; anything else is kInvalidArgument naming both.
Result<GlobalBaOptions::Solver> parseGbaSolver(const std::string& name);
const char* toString(GlobalBaOptions::Solver solver);

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
  // In the problem as a constant: a windowed solve's border (keyframes outside the window that see its points,
  // or are IMU-linked to it). Held keyframes get no correction.
  bool held = false;
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

// Part of a map to optimise, with the rest held: the keyframes in `free` and every point they see are
// optimised; the other keyframes that see one of those points or are IMU-linked to a free one are held, except
// those in `left_out`, which stay out of the problem (with their observations).
struct GbaWindow {
  std::unordered_set<KeyframeId> free;
  std::unordered_set<KeyframeId> left_out;
};

// An agent's map by (agent, the agent's map index), as ServerKeyframe::agent_map names it.
using AgentMapKey = std::pair<AgentId, std::uint32_t>;

// The window of a GBA after a merge: every keyframe of `agent_maps` (those of the smaller of the two maps the merge
// joined; the keyframes their agents added since included). None when that is more than `max_free_fraction` of
// the map's keyframes: the whole map costs little more then.
std::optional<GbaWindow> agentMapsWindow(const MapContent& map, const std::set<AgentMapKey>& agent_maps,
                                         double max_free_fraction);

// Copies what the solve needs: the whole map, or `window` of it. kFailedPrecondition names an agent whose sensors
// are unknown.
Result<GbaSnapshot> makeGbaSnapshot(const MapContent& map, const AgentSensorsMap& sensors,
                                    const GbaWindow* window = nullptr);

// Where a solve's time went: building the problem, and the solver's own accounting summed over both steps.
struct GlobalBaProfile {
  double build_s = 0.0;          // the states, the factors and the gauge
  double preprocess_s = 0.0;     // the reduced system's structure and its analysis (Ceres: the program, the ordering)
  double residuals_s = 0.0;      // cost evaluations (the trust region's trial steps included)
  double jacobians_s = 0.0;      // residuals and Jacobians at the accepted points
  double linear_solver_s = 0.0;  // Schur elimination and the reduced system's factorisation
  double other_s = 0.0;          // the rest of the minimiser and the post-processing
};

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
  GlobalBaProfile profile;
  // The cost after each accepted step of either solver step, with the seconds since the solve began (the
  // problem's build included): a GBA's convergence over time.
  struct Step {
    double t_s = 0.0;
    double cost = 0.0;
  };
  std::vector<Step> accepted;
  bool budget_reached = false;  // stopped at time_budget_s before converging; the result is applied all the same
  bool cancelled = false;       // `cancel` was raised: the snapshot holds a partial result, not to be applied
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
// The agent maps the GBA after a loop frees: those of `sides` (the loop's two keyframes, whose points its fusion
// joined), then those with a keyframe that `corrections` (the loop's pose graph) moved by more than `min_m` or
// turned by more than `min_deg`, the most moved first, as long as the free keyframes stay within
// `max_free_fraction` of the map. A pose graph spreads its correction over the whole map; what it barely moved keeps
// the state the last GBA refined, and what it moved least of the rest is refined by the next whole-map GBA. A
// window that frees most of a dense map costs about what the whole map does, so it stops at the fraction.
struct LoopWindow {
  std::set<AgentMapKey> free;
  int map_agent_maps = 0;  // how many agent maps the map holds
};
LoopWindow loopWindowAgentMaps(const MapContent& map, const std::vector<KeyframeCorrection>& corrections,
                               const std::vector<KeyframeId>& sides, double min_m, double min_deg,
                               double max_free_fraction);

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
  std::map<AgentMapKey, geometry::SE3d> frame_change;
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
  // Keyframes a windowed solve held: they stay as they are, where any other keyframe without a correction is
  // taken to have arrived meanwhile and is carried along.
  const std::unordered_set<KeyframeId>* held = nullptr;
  // A rigid move of a whole map part (a merge's correction) leaves every keyframe's state as good as it was:
  // neither flag changes.
  bool keeps_standing = false;
};
// Applies corrections computed on a snapshot to the map as it is now (see the header comment).
AppliedCorrections applyCorrections(MapContent& map, const std::vector<KeyframeCorrection>& keyframes,
                                    const std::vector<PointCorrection>& points, const ApplyOptions& options = {});

// The corrections a solved snapshot implies (none of its held keyframes), and the keyframes it held.
std::vector<KeyframeCorrection> keyframeCorrections(const GbaSnapshot& snapshot);
std::unordered_set<KeyframeId> heldKeyframes(const GbaSnapshot& snapshot);
std::vector<PointCorrection> pointCorrections(const GbaSnapshot& snapshot);

}  // namespace cvislam::server::backend
