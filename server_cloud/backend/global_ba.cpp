#include "server_cloud/backend/global_ba.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>
#include <optional>
#include <unordered_map>
#include <utility>

#include <ceres/ceres.h>

#include "common/core/steady_clock.hpp"
#include "common/factors/imu_factor.hpp"
#include "common/factors/manifolds.hpp"
#include "common/factors/prior_factor.hpp"
#include "common/factors/world_point_factor.hpp"
#include "server_cloud/backend/schur_solver.hpp"

namespace cvislam::server::backend {

namespace {

using geometry::SE3d;

factors::PinholeIntrinsics pinholeOf(const camera::CameraModel& model) {
  const auto& c = model.calibration();
  return {c.fx, c.fy, c.cx, c.cy};
}

class CancelCallback final : public ceres::IterationCallback {
 public:
  explicit CancelCallback(const std::atomic<bool>* cancel) : cancel_(cancel) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& /*summary*/) override {
    return cancel_ != nullptr && cancel_->load(std::memory_order_relaxed) ? ceres::SOLVER_ABORT
                                                                          : ceres::SOLVER_CONTINUE;
  }

 private:
  const std::atomic<bool>* cancel_;
};

}  // namespace

Status GlobalBaOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "global_ba." + what}; };
  if (!(sigma_px > 0.0)) return bad("sigma_px must be positive");
  if (!(pyramid_scale_factor >= 1.0)) return bad("pyramid_scale_factor must be >= 1");
  if (!(cauchy_scale > 0.0)) return bad("cauchy_scale must be positive");
  if (structure_iterations < 0 || full_iterations < 1) {
    return bad("iterations: structure_iterations >= 0 and full_iterations >= 1");
  }
  if (threads < 1) return bad("threads must be >= 1");
  if (!(function_tolerance > 0.0 && function_tolerance < 1.0)) return bad("function_tolerance must be in (0, 1)");
  if (!(max_solver_time_s > 0.0)) return bad("max_solver_time_s must be positive");
  if (!(time_budget_s >= 0.0)) return bad("time_budget_s must be 0 (none) or positive");
  if (!(gauge_sigma_m > 0.0) || !(gauge_sigma_rad > 0.0)) return bad("gauge sigmas must be positive");
  return Status::Ok();
}

namespace {

// The keyframes a windowed solve needs: the window's, and those that see its points or are IMU-linked to it
// (held), with the points the window sees.
std::vector<const ServerKeyframe*> windowKeyframes(const MapContent& map, const GbaWindow& window,
                                                   std::unordered_set<MapPointId>& window_points) {
  std::vector<const ServerKeyframe*> out;
  std::unordered_set<KeyframeId> border;
  const auto consider = [&](const KeyframeId& id) {
    if (window.free.count(id) == 0 && window.left_out.count(id) == 0) border.insert(id);
  };
  for (const KeyframeId& id : window.free) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (kf == nullptr) continue;
    out.push_back(kf);
    for (std::size_t k = 0; k < kf->keypoints.size(); ++k) {
      if (kf->has_point[k] != 0) window_points.insert(kf->point[k]);
    }
    if (kf->imu_from) consider(*kf->imu_from);
  }
  for (const MapPointId& id : window_points) {
    if (const ServerMapPoint* p = map.point(id)) {
      for (const ServerMapPoint::Observation& o : p->observations) consider(o.keyframe);
    }
  }
  for (const auto& [id, kf] : map.keyframes()) {
    if (kf.imu_from && window.free.count(*kf.imu_from) != 0) consider(id);
  }
  for (const KeyframeId& id : border) {
    if (const ServerKeyframe* kf = map.keyframe(id)) out.push_back(kf);
  }
  return out;
}

}  // namespace

std::optional<GbaWindow> agentMapsWindow(const MapContent& map, const std::set<AgentMapKey>& agent_maps,
                                         double max_free_fraction) {
  GbaWindow window;
  for (const auto& [id, kf] : map.keyframes()) {
    if (agent_maps.count({id.agent, kf.agent_map}) != 0) window.free.insert(id);
  }
  if (static_cast<double>(window.free.size()) > max_free_fraction * static_cast<double>(map.keyframes().size())) {
    return std::nullopt;
  }
  return window;
}

LoopWindow loopWindowAgentMaps(const MapContent& map, const std::vector<KeyframeCorrection>& corrections,
                               const std::vector<KeyframeId>& sides, double min_m, double min_deg,
                               double max_free_fraction) {
  std::map<AgentMapKey, std::size_t> keyframes;
  for (const auto& [id, kf] : map.keyframes()) ++keyframes[{id.agent, kf.agent_map}];
  // Each agent map's largest move, in units of the bounds (above 1: over one of them).
  std::map<AgentMapKey, double> moved;
  for (const KeyframeCorrection& c : corrections) {
    const ServerKeyframe* kf = map.keyframe(c.id);
    if (kf == nullptr) continue;
    const geometry::SE3d delta = c.T_w_s_before.inverse() * c.T_w_s_after;
    const double m = min_m > 0.0 ? delta.translation().norm() / min_m : 0.0;
    const double deg = min_deg > 0.0 ? delta.so3().log().norm() * 180.0 / M_PI / min_deg : 0.0;
    double& largest = moved[{c.id.agent, kf->agent_map}];
    largest = std::max({largest, m, deg});
  }
  LoopWindow window;
  window.map_agent_maps = static_cast<int>(keyframes.size());
  std::set<AgentMapKey>& free = window.free;
  std::size_t free_keyframes = 0;
  for (const KeyframeId& id : sides) {
    const ServerKeyframe* kf = map.keyframe(id);
    if (kf == nullptr || !free.insert({id.agent, kf->agent_map}).second) continue;
    free_keyframes += keyframes[{id.agent, kf->agent_map}];
  }
  std::vector<std::pair<double, AgentMapKey>> ranked;
  for (const auto& [key, largest] : moved) {
    if (largest > 1.0 && free.count(key) == 0) ranked.emplace_back(largest, key);
  }
  std::sort(ranked.begin(), ranked.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
  const double limit = max_free_fraction * static_cast<double>(map.keyframes().size());
  for (const auto& [largest, key] : ranked) {
    if (static_cast<double>(free_keyframes + keyframes[key]) > limit) break;
    free.insert(key);
    free_keyframes += keyframes[key];
  }
  return window;
}

Result<GbaSnapshot> makeGbaSnapshot(const MapContent& map, const AgentSensorsMap& sensors, const GbaWindow* window) {
  GbaSnapshot snapshot;
  snapshot.map = map.id();
  std::map<AgentId, const AgentSensors*> used;
  for (AgentId agent : map.agents()) {
    const auto it = sensors.find(agent);
    if (it == sensors.end()) {
      return Error{ErrorCode::kFailedPrecondition,
                   "global BA of map " + std::to_string(map.id()) + ": no sensors of agent " + std::to_string(agent)};
    }
    const AgentSensors& s = it->second;
    GbaAgent a;
    a.cam0 = pinholeOf(s.cam0);
    a.T_c0_s = s.T_s_c0.inverse();
    if (s.cam1) {
      a.cam1 = pinholeOf(*s.cam1);
      a.T_c1_s = s.T_s_c1.inverse();
    }
    a.uses_imu = s.uses_imu;
    a.noise = s.imu_noise;
    snapshot.agents.emplace(agent, a);
    used.emplace(agent, &s);
  }

  // Keyframes in a stable order; points indexed on first sight.
  std::vector<const ServerKeyframe*> keyframes;
  std::unordered_set<MapPointId> window_points;
  if (window != nullptr) {
    keyframes = windowKeyframes(map, *window, window_points);
  } else {
    keyframes.reserve(map.keyframes().size());
    for (const auto& [id, kf] : map.keyframes()) keyframes.push_back(&kf);
  }
  std::sort(keyframes.begin(), keyframes.end(),
            [](const ServerKeyframe* a, const ServerKeyframe* b) { return a->id < b->id; });
  std::unordered_map<KeyframeId, int> keyframe_index;
  for (std::size_t i = 0; i < keyframes.size(); ++i) keyframe_index.emplace(keyframes[i]->id, static_cast<int>(i));

  std::unordered_map<MapPointId, std::uint32_t> point_index;
  std::vector<int> point_keyframes;  // observing keyframes per point
  std::vector<std::uint8_t> point_stereo;
  snapshot.keyframes.resize(keyframes.size());
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    const ServerKeyframe& kf = *keyframes[i];
    const AgentSensors& s = *used.at(kf.id.agent);
    GbaKeyframe& out = snapshot.keyframes[i];
    out.id = kf.id;
    out.agent_map = kf.agent_map;
    out.t_ns = kf.t_ns;
    out.T_w_s = kf.T_w_s;
    out.T_w_s_before = kf.T_w_s;
    out.v_w = kf.v_w;
    out.bias = kf.bias;
    out.held = window != nullptr && window->free.count(kf.id) == 0;
    if (kf.imu_from && kf.preintegration && s.uses_imu) {
      const auto it = keyframe_index.find(*kf.imu_from);
      if (it != keyframe_index.end()) {
        out.imu_from = it->second;
        out.preintegration = kf.preintegration;
      }
    }
    std::vector<int> right_of(kf.keypoints.size(), -1);
    for (std::size_t r = 0; r < kf.right.size(); ++r) right_of[kf.right[r].keypoint] = static_cast<int>(r);
    for (std::size_t k = 0; k < kf.keypoints.size(); ++k) {
      if (kf.has_point[k] == 0) continue;
      if (out.held && window_points.count(kf.point[k]) == 0) continue;  // a point the window does not see
      const auto [it, added] = point_index.emplace(kf.point[k], static_cast<std::uint32_t>(point_index.size()));
      if (added) {
        point_keyframes.push_back(0);
        point_stereo.push_back(0);
      }
      ++point_keyframes[it->second];
      GbaObservation o;
      o.point = it->second;
      o.px_undistorted = kf.keypoints_undistorted.size() == kf.keypoints.size()
                             ? kf.keypoints_undistorted[k].cast<double>()
                             : s.cam0.undistortPixel(kf.keypoints[k].px.cast<double>());
      o.octave = kf.keypoints[k].octave;
      out.observations.push_back(o);
      if (right_of[k] >= 0 && s.cam1) {
        const RightObservation& r = kf.right[static_cast<std::size_t>(right_of[k])];
        out.observations.push_back({it->second, r.px_undistorted.cast<double>(), r.octave, true});
        point_stereo[it->second] = 1;
      }
    }
  }

  // Points that two keyframes (or both cameras of one) see; the rest only follow their reference keyframe.
  std::vector<std::int64_t> remap(point_index.size(), -1);
  snapshot.points.reserve(point_index.size());
  std::vector<MapPointId> ids(point_index.size());
  for (const auto& [id, index] : point_index) ids[index] = id;
  for (std::size_t p = 0; p < ids.size(); ++p) {
    if (point_keyframes[p] < 2 && point_stereo[p] == 0) continue;
    const ServerMapPoint* point = map.point(ids[p]);
    if (point == nullptr) continue;
    remap[p] = static_cast<std::int64_t>(snapshot.points.size());
    snapshot.points.push_back({point->id, point->p_w, point->p_w});
  }
  for (GbaKeyframe& kf : snapshot.keyframes) {
    std::erase_if(kf.observations, [&](const GbaObservation& o) { return remap[o.point] < 0; });
    for (GbaObservation& o : kf.observations) o.point = static_cast<std::uint32_t>(remap[o.point]);
  }
  return snapshot;
}

namespace {

// The optimised states, copied out of the snapshot so that a cancelled or failed solve leaves it untouched.
struct GbaStates {
  explicit GbaStates(const GbaSnapshot& snapshot)
      : poses(snapshot.keyframes.size()),
        velocities(snapshot.keyframes.size()),
        biases(snapshot.keyframes.size()),
        has_imu_state(snapshot.keyframes.size(), 0),
        points(snapshot.points.size()) {
    for (std::size_t i = 0; i < snapshot.keyframes.size(); ++i) {
      const GbaKeyframe& kf = snapshot.keyframes[i];
      poses[i] = factors::poseToBlock(kf.T_w_s);
      velocities[i] = kf.v_w;
      biases[i] << kf.bias.gyro, kf.bias.accel;
    }
    for (std::size_t p = 0; p < points.size(); ++p) points[p] = snapshot.points[p].p_w;
  }

  void writeBack(GbaSnapshot& snapshot) const {
    for (std::size_t i = 0; i < snapshot.keyframes.size(); ++i) {
      GbaKeyframe& kf = snapshot.keyframes[i];
      kf.T_w_s = factors::poseFromBlock(poses[i].data());
      if (has_imu_state[i] != 0) {
        kf.v_w = velocities[i];
        kf.bias.gyro = biases[i].head<3>();
        kf.bias.accel = biases[i].tail<3>();
      }
    }
    for (std::size_t p = 0; p < points.size(); ++p) snapshot.points[p].p_w = points[p];
  }

  std::vector<factors::PoseBlock> poses;
  std::vector<Eigen::Vector3d> velocities;
  std::vector<Eigen::Matrix<double, 6, 1>> biases;
  std::vector<std::uint8_t> has_imu_state;  // velocity and bias are in the problem (the keyframe has an IMU link)
  std::vector<Eigen::Vector3d> points;
};

// What the problem holds, whichever solver takes it.
struct GbaFactorPlan {
  struct Reprojection {
    std::unique_ptr<factors::WorldPointReprojectionFactor> cost;
    std::size_t keyframe = 0;
    std::uint32_t point = 0;
  };
  std::vector<Reprojection> reprojections;
  std::vector<std::uint8_t> point_used;
  std::vector<std::pair<std::size_t, std::size_t>> imu_links;                // (previous, next) keyframe
  std::optional<std::pair<std::size_t, Eigen::Matrix<double, 6, 6>>> gauge;  // keyframe, sqrt information
};

// Every observation whose point is in front of its camera at the start; a point no factor uses is held.
void planReprojections(const GbaSnapshot& snapshot, const GlobalBaOptions& options, const GbaStates& states,
                       GbaFactorPlan& plan) {
  plan.point_used.assign(states.points.size(), 0);
  for (std::size_t i = 0; i < snapshot.keyframes.size(); ++i) {
    const GbaKeyframe& kf = snapshot.keyframes[i];
    const GbaAgent& agent = snapshot.agents.at(kf.id.agent);
    for (const GbaObservation& o : kf.observations) {
      const double sigma = options.sigma_px * std::pow(options.pyramid_scale_factor, o.octave);
      auto cost = o.second_camera ? std::make_unique<factors::WorldPointReprojectionFactor>(
                                        o.px_undistorted, *agent.cam1, sigma, agent.T_c1_s)
                                  : std::make_unique<factors::WorldPointReprojectionFactor>(
                                        o.px_undistorted, agent.cam0, sigma, agent.T_c0_s);
      // A point behind the camera at the start (a bad association) cannot be evaluated: leave it out.
      Eigen::Vector2d residual;
      if (!cost->evaluateTangent(states.poses[i].data(), states.points[o.point].data(), residual, nullptr, nullptr)) {
        continue;
      }
      plan.reprojections.push_back({std::move(cost), i, o.point});
      plan.point_used[o.point] = 1;
    }
  }
}

// IMU and bias random-walk factors along each agent's preintegration links; marks the keyframes whose velocity
// and biases the problem then holds.
void planImuLinks(const GbaSnapshot& snapshot, GbaStates& states, GbaFactorPlan& plan) {
  for (std::size_t j = 0; j < snapshot.keyframes.size(); ++j) {
    const GbaKeyframe& kf = snapshot.keyframes[j];
    if (kf.imu_from < 0 || !kf.preintegration) continue;
    const auto i = static_cast<std::size_t>(kf.imu_from);
    if (kf.held && snapshot.keyframes[i].held) continue;  // constrains nothing the solve moves
    states.has_imu_state[i] = 1;
    states.has_imu_state[j] = 1;
    plan.imu_links.emplace_back(i, j);
  }
}

// The gauge: a prior on the oldest keyframe's pose. With every agent inertial, gravity fixes roll and pitch,
// so only position and yaw are held. Held keyframes fix the gauge of a windowed solve instead.
void planGauge(const GbaSnapshot& snapshot, const GlobalBaOptions& options, GbaFactorPlan& plan) {
  const bool windowed =
      std::any_of(snapshot.keyframes.begin(), snapshot.keyframes.end(), [](const GbaKeyframe& kf) { return kf.held; });
  if (windowed) return;
  std::size_t oldest = 0;
  for (std::size_t i = 1; i < snapshot.keyframes.size(); ++i) {
    if (snapshot.keyframes[i].t_ns < snapshot.keyframes[oldest].t_ns) oldest = i;
  }
  Eigen::Matrix<double, 6, 6> gauge_sqrt_information = Eigen::Matrix<double, 6, 6>::Zero();
  gauge_sqrt_information.topLeftCorner<3, 3>() = Eigen::Matrix3d::Identity() / options.gauge_sigma_m;
  const bool all_imu = std::all_of(snapshot.agents.begin(), snapshot.agents.end(),
                                   [](const auto& entry) { return entry.second.uses_imu; });
  if (options.gauge_position_yaw_only && all_imu) {
    // The rotation residual is Log(R0^T R), in the keyframe's frame; its yaw about the world's z is
    // z^T R0 times it. Roll and pitch rows stay zero.
    gauge_sqrt_information.block<1, 3>(3, 3) =
        (snapshot.keyframes[oldest].T_w_s.so3().matrix().transpose() * Eigen::Vector3d::UnitZ()).transpose() /
        options.gauge_sigma_rad;
  } else {
    gauge_sqrt_information.bottomRightCorner<3, 3>() = Eigen::Matrix3d::Identity() / options.gauge_sigma_rad;
  }
  plan.gauge.emplace(oldest, gauge_sqrt_information);
}

std::unique_ptr<factors::ImuFactor> imuFactor(const GbaSnapshot& snapshot, std::size_t j) {
  return std::make_unique<factors::ImuFactor>(*snapshot.keyframes[j].preintegration);
}

std::unique_ptr<factors::BiasRandomWalkFactor> biasFactor(const GbaSnapshot& snapshot, std::size_t j) {
  const GbaKeyframe& kf = snapshot.keyframes[j];
  return std::make_unique<factors::BiasRandomWalkFactor>(snapshot.agents.at(kf.id.agent).noise,
                                                         kf.preintegration->dt());
}

void addPlanToCeres(const GbaSnapshot& snapshot, const GlobalBaOptions& options, GbaFactorPlan& plan, GbaStates& states,
                    ceres::Problem& problem) {
  auto* pose_manifold = new factors::PoseManifold();  // the problem takes ownership
  for (factors::PoseBlock& pose : states.poses) {
    problem.AddParameterBlock(pose.data(), factors::kPoseSize, pose_manifold);
  }
  for (Eigen::Vector3d& p : states.points) problem.AddParameterBlock(p.data(), factors::kPointSize);
  for (GbaFactorPlan::Reprojection& r : plan.reprojections) {
    problem.AddResidualBlock(r.cost.release(), new ceres::CauchyLoss(options.cauchy_scale),
                             states.poses[r.keyframe].data(), states.points[r.point].data());
  }
  for (std::size_t p = 0; p < states.points.size(); ++p) {
    if (plan.point_used[p] == 0) problem.SetParameterBlockConstant(states.points[p].data());
  }
  for (std::size_t k = 0; k < snapshot.keyframes.size(); ++k) {
    if (states.has_imu_state[k] == 0) continue;
    problem.AddParameterBlock(states.velocities[k].data(), factors::kVelocitySize);
    problem.AddParameterBlock(states.biases[k].data(), factors::kBiasSize);
    if (snapshot.keyframes[k].held) {
      problem.SetParameterBlockConstant(states.velocities[k].data());
      problem.SetParameterBlockConstant(states.biases[k].data());
    }
  }
  for (const auto& [i, j] : plan.imu_links) {
    problem.AddResidualBlock(imuFactor(snapshot, j).release(), nullptr, states.poses[i].data(),
                             states.velocities[i].data(), states.biases[i].data(), states.poses[j].data(),
                             states.velocities[j].data());
    problem.AddResidualBlock(biasFactor(snapshot, j).release(), nullptr, states.biases[i].data(),
                             states.biases[j].data());
  }
  if (plan.gauge) {
    const auto& [oldest, sqrt_information] = *plan.gauge;
    problem.AddResidualBlock(new factors::PosePriorFactor(snapshot.keyframes[oldest].T_w_s, sqrt_information), nullptr,
                             states.poses[oldest].data());
  }
}

// The Schur solver's blocks of one keyframe: pose, and velocity and biases where the problem has them.
struct SchurKeyframeBlocks {
  int pose = -1;
  int velocity = -1;
  int bias = -1;
};

std::vector<SchurKeyframeBlocks> addPlanToSchur(const GbaSnapshot& snapshot, const GlobalBaOptions& options,
                                                GbaFactorPlan& plan, GbaStates& states, SchurProblem& problem) {
  // Each keyframe's blocks next to each other, so that the reduced system is banded along each agent's path.
  std::vector<SchurKeyframeBlocks> blocks(snapshot.keyframes.size());
  for (std::size_t k = 0; k < snapshot.keyframes.size(); ++k) {
    blocks[k].pose = problem.addPose(states.poses[k].data());
    if (states.has_imu_state[k] != 0) {
      blocks[k].velocity = problem.addVector(states.velocities[k].data(), factors::kVelocitySize);
      blocks[k].bias = problem.addVector(states.biases[k].data(), factors::kBiasSize);
      problem.setKeyframeBlockHeld(blocks[k].velocity, snapshot.keyframes[k].held);
      problem.setKeyframeBlockHeld(blocks[k].bias, snapshot.keyframes[k].held);
    }
  }
  for (std::size_t p = 0; p < states.points.size(); ++p) {
    problem.setPointHeld(problem.addPoint(states.points[p].data()), plan.point_used[p] == 0);
  }
  for (GbaFactorPlan::Reprojection& r : plan.reprojections) {
    problem.addReprojection(std::move(r.cost), blocks[r.keyframe].pose, static_cast<int>(r.point),
                            options.cauchy_scale);
  }
  for (const auto& [i, j] : plan.imu_links) {
    problem.addKeyframeFactor(imuFactor(snapshot, j),
                              {blocks[i].pose, blocks[i].velocity, blocks[i].bias, blocks[j].pose, blocks[j].velocity});
    problem.addKeyframeFactor(biasFactor(snapshot, j), {blocks[i].bias, blocks[j].bias});
  }
  if (plan.gauge) {
    const auto& [oldest, sqrt_information] = *plan.gauge;
    problem.addKeyframeFactor(
        std::make_unique<factors::PosePriorFactor>(snapshot.keyframes[oldest].T_w_s, sqrt_information),
        {blocks[oldest].pose});
  }
  return blocks;
}

// One Ceres stage of the solve: at most `iterations` (0: none), with the blocks held as the caller set them.
// Cancellation is reported in the summary, not as an error.
Status solveCeresStage(ceres::Problem& problem, ceres::Solver::Options& solver, const GlobalBaOptions& options,
                       GbaStates& states, int iterations, std::chrono::steady_clock::time_point started, int& done,
                       double& seconds, GlobalBaSummary& summary) {
  if (iterations == 0) return Status::Ok();
  const double offset_s = secondsSince(started);
  solver.max_num_iterations = iterations;
  solver.max_solver_time_in_seconds = options.max_solver_time_s;
  const double budget_left_s = options.time_budget_s - offset_s;
  if (options.time_budget_s > 0.0 && budget_left_s <= 0.0) {
    solver.max_num_iterations = 1;  // spent: the step's first iteration, as the Schur solver takes it
  } else if (options.time_budget_s > 0.0) {
    solver.max_solver_time_in_seconds = std::min(options.max_solver_time_s, budget_left_s);
  }
  // Points first (Schur-eliminated), then the keyframe states; Ceres prunes the held blocks from the ordering
  // it is given, so each solve gets its own.
  auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
  for (Eigen::Vector3d& p : states.points) ordering->AddElementToGroup(p.data(), 0);
  for (std::size_t i = 0; i < states.poses.size(); ++i) {
    ordering->AddElementToGroup(states.poses[i].data(), 1);
    if (states.has_imu_state[i] != 0) {
      ordering->AddElementToGroup(states.velocities[i].data(), 1);
      ordering->AddElementToGroup(states.biases[i].data(), 1);
    }
  }
  solver.linear_solver_ordering = ordering;
  ceres::Solver::Summary s;
  const auto start = std::chrono::steady_clock::now();
  ceres::Solve(solver, &problem, &s);
  seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (s.termination_type == ceres::USER_FAILURE) {
    summary.cancelled = true;
    return Status::Ok();
  }
  if (!s.IsSolutionUsable()) return Error{ErrorCode::kDegenerate, "global BA failed: " + s.message};
  if (options.time_budget_s > 0.0 && s.termination_type == ceres::NO_CONVERGENCE &&
      static_cast<int>(s.iterations.size()) - 1 < iterations) {
    summary.budget_reached = true;
  }
  done = static_cast<int>(s.iterations.size()) - 1;
  for (std::size_t i = 1; i < s.iterations.size(); ++i) {
    if (s.iterations[i].step_is_successful) {
      summary.accepted.push_back({offset_s + s.iterations[i].cumulative_time_in_seconds, s.iterations[i].cost});
    }
  }
  GlobalBaProfile& profile = summary.profile;
  profile.preprocess_s += s.preprocessor_time_in_seconds;
  profile.residuals_s += s.residual_evaluation_time_in_seconds;
  profile.jacobians_s += s.jacobian_evaluation_time_in_seconds;
  profile.linear_solver_s += s.linear_solver_time_in_seconds;
  profile.other_s += s.total_time_in_seconds - s.preprocessor_time_in_seconds - s.residual_evaluation_time_in_seconds -
                     s.jacobian_evaluation_time_in_seconds - s.linear_solver_time_in_seconds;
  if (summary.initial_cost == 0.0) summary.initial_cost = s.initial_cost;
  summary.final_cost = s.final_cost;
  return Status::Ok();
}

Status solveWithCeres(const GbaSnapshot& snapshot, const GlobalBaOptions& options, GbaFactorPlan& plan,
                      GbaStates& states, const std::atomic<bool>* cancel, std::chrono::steady_clock::time_point started,
                      GlobalBaSummary& summary) {
  const auto build_start = std::chrono::steady_clock::now();
  ceres::Problem::Options problem_options;
  problem_options.manifold_ownership = ceres::TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  addPlanToCeres(snapshot, options, plan, states, problem);
  summary.profile.build_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();

  CancelCallback callback(cancel);
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_SCHUR;
  if (options.iterative_schur) {
    solver.linear_solver_type = ceres::ITERATIVE_SCHUR;
    solver.preconditioner_type = ceres::SCHUR_JACOBI;
  }
  solver.num_threads = options.threads;
  solver.function_tolerance = options.function_tolerance;
  solver.callbacks.push_back(&callback);
  solver.update_state_every_iteration = false;

  // Step 1: structure, velocities and biases with the poses held.
  for (factors::PoseBlock& pose : states.poses) problem.SetParameterBlockConstant(pose.data());
  if (Status s = solveCeresStage(problem, solver, options, states, options.structure_iterations, started,
                                 summary.structure_iterations, summary.structure_s, summary);
      !s.ok() || summary.cancelled) {
    return s;
  }
  // Step 2: everything.
  for (std::size_t i = 0; i < states.poses.size(); ++i) {
    if (!snapshot.keyframes[i].held) problem.SetParameterBlockVariable(states.poses[i].data());
  }
  return solveCeresStage(problem, solver, options, states, options.full_iterations, started, summary.full_iterations,
                         summary.full_s, summary);
}

// One stage of the Schur solver; its accounting goes where Ceres' would.
void solveSchurStage(SchurProblem& problem, const GlobalBaOptions& options, int iterations,
                     const std::atomic<bool>* cancel, std::chrono::steady_clock::time_point started, int& done,
                     double& seconds, GlobalBaSummary& summary) {
  const double offset_s = secondsSince(started);
  if (iterations == 0) return;
  SchurSolverOptions solver;
  solver.max_iterations = iterations;
  solver.function_tolerance = options.function_tolerance;
  solver.max_time_s = options.max_solver_time_s;
  if (options.time_budget_s > 0.0) {
    solver.deadline = started + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                    std::chrono::duration<double>(options.time_budget_s));
  }
  solver.threads = options.threads;
  solver.cancel = cancel;
  const auto start = std::chrono::steady_clock::now();
  const SchurSolverSummary s = problem.solve(solver);
  seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  summary.cancelled = s.cancelled;
  summary.budget_reached = summary.budget_reached || s.deadline_reached;
  done = s.iterations;
  for (const SchurSolverSummary::Step& step : s.accepted) summary.accepted.push_back({offset_s + step.t_s, step.cost});
  GlobalBaProfile& profile = summary.profile;
  profile.preprocess_s += s.setup_s;
  profile.residuals_s += s.evaluate_s;
  profile.jacobians_s += s.linearize_s;
  profile.linear_solver_s += s.linear_solver_s;
  profile.other_s += seconds - s.setup_s - s.evaluate_s - s.linearize_s - s.linear_solver_s;
  if (summary.initial_cost == 0.0) summary.initial_cost = s.initial_cost;
  summary.final_cost = s.final_cost;
}

void solveWithSchur(const GbaSnapshot& snapshot, const GlobalBaOptions& options, GbaFactorPlan& plan, GbaStates& states,
                    const std::atomic<bool>* cancel, std::chrono::steady_clock::time_point started,
                    GlobalBaSummary& summary) {
  const auto build_start = std::chrono::steady_clock::now();
  SchurProblem problem;
  const std::vector<SchurKeyframeBlocks> blocks = addPlanToSchur(snapshot, options, plan, states, problem);
  summary.profile.build_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();
  // Step 1: structure, velocities and biases with the poses held.
  for (const SchurKeyframeBlocks& b : blocks) problem.setKeyframeBlockHeld(b.pose, true);
  solveSchurStage(problem, options, options.structure_iterations, cancel, started, summary.structure_iterations,
                  summary.structure_s, summary);
  if (summary.cancelled) return;
  // Step 2: everything.
  for (std::size_t k = 0; k < blocks.size(); ++k) {
    problem.setKeyframeBlockHeld(blocks[k].pose, snapshot.keyframes[k].held);
  }
  solveSchurStage(problem, options, options.full_iterations, cancel, started, summary.full_iterations, summary.full_s,
                  summary);
}

}  // namespace

Result<GlobalBaOptions::Solver> parseGbaSolver(const std::string& name) {
  if (name == "schur") return GlobalBaOptions::Solver::kSchur;
  if (name == "ceres") return GlobalBaOptions::Solver::kCeres;
  return Error{ErrorCode::kInvalidArgument, "unknown GBA solver '" + name + "' (schur or ceres)"};
}

const char* toString(GlobalBaOptions::Solver solver) {
  return solver == GlobalBaOptions::Solver::kCeres ? "ceres" : "schur";
}

Result<GlobalBaSummary> runGlobalBa(GbaSnapshot& snapshot, const GlobalBaOptions& options,
                                    const std::atomic<bool>* cancel) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  GlobalBaSummary summary;
  summary.keyframes = static_cast<int>(snapshot.keyframes.size());
  summary.points = static_cast<int>(snapshot.points.size());
  if (snapshot.keyframes.size() < 2) return summary;

  const auto build_start = std::chrono::steady_clock::now();
  GbaStates states(snapshot);
  GbaFactorPlan plan;
  planReprojections(snapshot, options, states, plan);
  planImuLinks(snapshot, states, plan);
  planGauge(snapshot, options, plan);
  summary.reprojection_factors = static_cast<int>(plan.reprojections.size());
  summary.imu_factors = static_cast<int>(plan.imu_links.size());
  summary.profile.build_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();

  if (options.solver == GlobalBaOptions::Solver::kCeres) {
    if (Status s = solveWithCeres(snapshot, options, plan, states, cancel, build_start, summary); !s.ok()) {
      return s.error();
    }
  } else {
    solveWithSchur(snapshot, options, plan, states, cancel, build_start, summary);
  }
  if (summary.cancelled) return summary;
  states.writeBack(snapshot);
  return summary;
}

std::vector<KeyframeCorrection> keyframeCorrections(const GbaSnapshot& snapshot) {
  std::vector<bool> has_imu(snapshot.keyframes.size(), false);
  for (std::size_t j = 0; j < snapshot.keyframes.size(); ++j) {
    const int i = snapshot.keyframes[j].imu_from;
    if (i >= 0 && snapshot.keyframes[j].preintegration) {
      has_imu[j] = true;
      has_imu[static_cast<std::size_t>(i)] = true;
    }
  }
  std::vector<KeyframeCorrection> out;
  out.reserve(snapshot.keyframes.size());
  for (std::size_t i = 0; i < snapshot.keyframes.size(); ++i) {
    const GbaKeyframe& kf = snapshot.keyframes[i];
    if (kf.held) continue;
    KeyframeCorrection c{kf.id, kf.T_w_s_before, kf.T_w_s, std::nullopt};
    if (has_imu[i]) c.velocity_bias_after = std::make_pair(kf.v_w, kf.bias);
    out.push_back(std::move(c));
  }
  return out;
}

std::unordered_set<KeyframeId> heldKeyframes(const GbaSnapshot& snapshot) {
  std::unordered_set<KeyframeId> out;
  for (const GbaKeyframe& kf : snapshot.keyframes) {
    if (kf.held) out.insert(kf.id);
  }
  return out;
}

std::vector<PointCorrection> pointCorrections(const GbaSnapshot& snapshot) {
  std::vector<PointCorrection> out;
  out.reserve(snapshot.points.size());
  for (const GbaPoint& p : snapshot.points) out.push_back({p.id, p.p_w_before, p.p_w});
  return out;
}

SE3d windowChange(const std::map<std::int64_t, TimedChange>& series, int window) {
  // Rotation: the normalised mean of the changes' quaternions (sign-aligned; they differ by little).
  // Translation: given that rotation, the one that moves the window's keyframe positions where their own
  // changes move them, in the least-squares sense.
  auto it = series.end();
  Eigen::Vector4d q_sum = Eigen::Vector4d::Zero();
  Eigen::Vector3d before_sum = Eigen::Vector3d::Zero();
  Eigen::Vector3d after_sum = Eigen::Vector3d::Zero();
  int n = 0;
  const Eigen::Quaterniond q_ref = std::prev(series.end())->second.delta.so3().quaternion();
  while (it != series.begin() && n < std::max(window, 1)) {
    --it;
    const Eigen::Quaterniond& q = it->second.delta.so3().quaternion();
    q_sum += (q.coeffs().dot(q_ref.coeffs()) < 0.0 ? -1.0 : 1.0) * q.coeffs();
    before_sum += it->second.p_before;
    after_sum += it->second.delta * it->second.p_before;
    ++n;
  }
  const Eigen::Quaterniond q_mean(Eigen::Vector4d(q_sum.normalized()));
  const geometry::SO3d R(q_mean);
  return SE3d(R, (after_sum - (R * before_sum)) / static_cast<double>(n));
}

AppliedCorrections applyCorrections(MapContent& map, const std::vector<KeyframeCorrection>& keyframes,
                                    const std::vector<PointCorrection>& points, const ApplyOptions& options) {
  AppliedCorrections applied;
  // The change of every corrected keyframe, and per agent map its corrected keyframes by time.
  std::unordered_map<KeyframeId, SE3d> change;
  std::map<AgentMapKey, std::map<std::int64_t, TimedChange>> by_time;
  for (const KeyframeCorrection& c : keyframes) {
    ServerKeyframe* kf = map.keyframe(c.id);
    if (kf == nullptr) continue;  // removed meanwhile
    const SE3d delta = c.T_w_s_after * c.T_w_s_before.inverse();
    change.emplace(c.id, delta);
    by_time[{kf->id.agent, kf->agent_map}].emplace(kf->t_ns, TimedChange{delta, kf->T_w_s.translation()});
    kf->T_w_s = delta * kf->T_w_s;
    if (!options.keeps_standing) {
      kf->refined = options.marks_refined;
      kf->provisional = !options.marks_refined;
    }
    if (c.velocity_bias_after) {
      // The solve estimated velocity and biases: they replace the held ones (an agent update meanwhile is lost).
      kf->v_w = c.velocity_bias_after->first;
      kf->bias = c.velocity_bias_after->second;
    } else {
      kf->v_w = delta.so3() * kf->v_w;
    }
    ++applied.keyframes_optimised;
    applied.changed.push_back(c.id);
  }
  // Per agent map, the change of its frame: that of its newest corrected keyframes, so that one keyframe's
  // own correction (the newest is the least constrained) does not turn the whole frame.
  for (const auto& [key, series] : by_time) {
    if (!series.empty()) applied.frame_change[key] = windowChange(series, options.frame_window);
  }
  // Keyframes that arrived meanwhile: newer than every corrected keyframe of their agent map, the frame's change
  // (they were made in that frame); else their nearest corrected keyframe in time (earlier first).
  for (const auto& [id, kf_const] : map.keyframes()) {
    if (change.count(id) != 0 || (options.held != nullptr && options.held->count(id) != 0)) continue;
    const auto series = by_time.find({id.agent, kf_const.agent_map});
    if (series == by_time.end() || series->second.empty()) continue;
    auto it = series->second.upper_bound(kf_const.t_ns);
    const bool newest = it == series->second.end();
    if (it != series->second.begin()) --it;
    const SE3d delta = newest ? applied.frame_change.at(series->first) : it->second.delta;
    ServerKeyframe* kf = map.keyframe(id);
    kf->T_w_s = delta * kf->T_w_s;
    kf->v_w = delta.so3() * kf->v_w;
    if (!options.marks_refined && !options.keeps_standing) kf->provisional = true;
    change.emplace(id, delta);
    ++applied.keyframes_propagated;
    applied.changed.push_back(id);
  }
  // Points: their own change, else their reference keyframe's.
  std::unordered_map<MapPointId, const PointCorrection*> corrected;
  for (const PointCorrection& c : points) corrected.emplace(c.id, &c);
  std::vector<MapPointId> ids;
  ids.reserve(map.points().size());
  for (const auto& [id, p] : map.points()) ids.push_back(id);
  for (const MapPointId& id : ids) {
    ServerMapPoint* p = map.point(id);
    if (const auto it = corrected.find(id); it != corrected.end()) {
      p->p_w = it->second->p_w_after + (p->p_w - it->second->p_w_before);
      ++applied.points_optimised;
      continue;
    }
    const auto it = change.find(p->reference);
    if (it == change.end()) continue;
    p->p_w = it->second * p->p_w;
    ++applied.points_propagated;
  }
  return applied;
}

}  // namespace cvislam::server::backend
