#include "agent_rt/mapping/local_bundle_adjustment.hpp"

#include <algorithm>
#include <cmath>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include <ceres/ceres.h>

#include "common/factors/imu_factor.hpp"
#include "common/factors/inverse_depth_point_factor.hpp"
#include "common/factors/manifolds.hpp"
#include "common/factors/prior_factor.hpp"
#include "common/factors/state_layout.hpp"
#include "common/factors/time_offset_point_factor.hpp"

namespace cvislam::agent {

using Eigen::Vector3d;

Status LocalBundleAdjustmentOptions::validate() const {
  const auto bad = [](const std::string& what) {
    return Error{ErrorCode::kInvalidArgument, "local BA options: " + what};
  };
  if (window < 1) return bad("window must be >= 1");
  if (min_covisible < 1) return bad("min_covisible must be >= 1");
  if (max_iterations < 1) return bad("max_iterations must be >= 1");
  if (!(cauchy_scale > 0.0) || !(sigma_px > 0.0)) return bad("cauchy_scale and sigma_px must be > 0");
  if (!(pyramid_scale_factor >= 1.0)) return bad("pyramid_scale_factor must be >= 1");
  if (!(intrinsics.fx > 0.0) || !(intrinsics.fy > 0.0)) return bad("intrinsics fx, fy must be > 0");
  if (use_second_camera && (!(second_intrinsics.fx > 0.0) || !(second_intrinsics.fy > 0.0))) {
    return bad("second camera intrinsics fx, fy must be > 0");
  }
  if (use_second_camera && !(max_second_camera_error_sigma > 0.0)) {
    return bad("max_second_camera_error_sigma must be > 0");
  }
  if (!(time_offset_prior_sigma_s > 0.0) || !(max_time_offset_s > 0.0)) {
    return bad("time_offset_prior_sigma_s and max_time_offset_s must be > 0");
  }
  return noise.validate();
}

namespace {

std::uint64_t handleKey(PoolHandle h) {
  return (static_cast<std::uint64_t>(h.index) << 32U) | h.generation;
}

struct KeyframeState {
  PoolHandle handle;
  factors::PoseBlock pose;
  Vector3d velocity;
  Eigen::Matrix<double, 6, 1> bias;
  bool in_window = false;
  factors::KeyframeMotion motion;  // over its time shift; zero for an anchor (the server's: not on our clock)
};

// A point as one Ceres block, (a, b, rho) in its reference camera (inverse_depth_point_factor.hpp), so that
// SPARSE_SCHUR can eliminate it; the map keeps its bearing and inverse distance, converted at both ends.
struct PointState {
  PoolHandle handle;
  Vector3d point;
};

// Lower bound of rho = 1/z: in front of the reference camera, and finite.
constexpr double kMinInverseDepth = 1e-8;

// Ends the solve after the current iteration when the caller's predicate says so. Asked from the first
// iteration on (not after the initial evaluation: at least one step is taken) and not after the last one.
class StopWhenAsked final : public ceres::IterationCallback {
 public:
  StopWhenAsked(const std::function<bool()>& stop, int max_iterations) : stop_(stop), max_iterations_(max_iterations) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& summary) override {
    if (summary.iteration < 1 || summary.iteration >= max_iterations_ || !stop_()) return ceres::SOLVER_CONTINUE;
    stopped_ = true;
    return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
  }
  [[nodiscard]] bool stopped() const { return stopped_; }

 private:
  const std::function<bool()>& stop_;  // the caller's, which outlives the solve
  int max_iterations_ = 0;
  bool stopped_ = false;
};

// The problem's states: the window's keyframes (optimised), the keyframes that share its points (fixed), and
// the points the window observes, each with its index by pool handle.
class BaStates {
 public:
  explicit BaStates(LocalMap& map) : map_(map) {}

  // Adds a keyframe once (later calls return its index); `in_window` is kept from the first call.
  std::size_t addKeyframe(PoolHandle h, bool in_window) {
    const auto [it, inserted] = keyframe_index_.emplace(handleKey(h), keyframes.size());
    if (inserted) {
      const KeyframeData& kf = *map_.keyframes().get(h);
      KeyframeState s;
      s.handle = h;
      s.pose = factors::poseToBlock(kf.T_w_s);
      s.velocity = kf.v_w;
      s.bias << kf.bias.gyro, kf.bias.accel;
      s.in_window = in_window;
      if (!kf.anchor) {
        s.motion = {kf.v_w, kf.gyro_s - kf.bias.gyro, static_cast<double>(kf.time_correction_ns) * 1e-9};
      }
      keyframes.push_back(s);
    }
    return it->second;
  }
  [[nodiscard]] bool hasKeyframe(PoolHandle h) const { return keyframe_index_.count(handleKey(h)) != 0; }
  KeyframeState& keyframe(PoolHandle h) { return keyframes[keyframe_index_.at(handleKey(h))]; }

  // Adds the point once.
  void addPoint(PoolHandle h, const Vector3d& point) {
    if (point_index_.emplace(handleKey(h), points.size()).second) points.push_back({h, point});
  }
  [[nodiscard]] bool seen(PoolHandle h) const {
    return point_index_.count(handleKey(h)) != 0 || left_out.count(handleKey(h)) != 0;
  }
  [[nodiscard]] bool hasPoint(PoolHandle h) const { return point_index_.count(handleKey(h)) != 0; }
  PointState* point(PoolHandle h) {
    const auto it = point_index_.find(handleKey(h));
    return it == point_index_.end() ? nullptr : &points[it->second];
  }

  std::vector<KeyframeState> keyframes;
  std::vector<PointState> points;
  std::unordered_set<std::uint64_t> left_out;  // points without a valid inverse-depth point or reference

 private:
  LocalMap& map_;
  std::unordered_map<std::uint64_t, std::size_t> keyframe_index_;
  std::unordered_map<std::uint64_t, std::size_t> point_index_;
};

// The window: the newest `window` non-anchor keyframes, oldest first.
std::vector<PoolHandle> selectWindow(const LocalMap& map, int window) {
  std::vector<std::pair<std::uint64_t, PoolHandle>> by_sequence;
  map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (!kf.anchor) by_sequence.emplace_back(kf.sequence, h);
  });
  std::sort(by_sequence.begin(), by_sequence.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  const std::size_t first =
      by_sequence.size() > static_cast<std::size_t>(window) ? by_sequence.size() - static_cast<std::size_t>(window) : 0;
  std::vector<PoolHandle> handles;
  for (std::size_t i = first; i < by_sequence.size(); ++i) handles.push_back(by_sequence[i].second);
  return handles;
}

// The points the window observes. A point without an inverse-depth point (a bearing nearly in its reference
// image plane, a non-finite or negative inverse distance: corrupt, no pinhole image saw it) or without its
// reference keyframe is left out, as are its observations, rather than failing the whole BA; it stays in the
// map as it was.
void collectPoints(const LocalMap& map, BaStates& states) {
  for (const KeyframeState& s : states.keyframes) {
    const KeyframeData& kf = *map.keyframes().get(s.handle);
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (!kf.has_map_point[k]) continue;
      const MapPointData* mp = map.mapPoints().get(kf.map_point[k]);
      if (mp == nullptr || states.seen(kf.map_point[k])) continue;
      Vector3d point;
      if (!map.keyframes().valid(mp->reference) || !(mp->inverse_depth >= 0.0) ||
          !factors::inverseDepthPointFromBearing(mp->bearing_c, mp->inverse_depth, point)) {
        states.left_out.insert(handleKey(kf.map_point[k]));
        continue;
      }
      point.z() = std::max(point.z(), kMinInverseDepth);  // Ceres needs a feasible start
      states.addPoint(kf.map_point[k], point);
    }
  }
}

// Fixed keyframes: every other keyframe sharing at least `min_covisible` of the window's points (an anchor,
// the server's refined pose, with any), and every point's reference keyframe. Returns the anchors among them.
int addFixedKeyframes(const LocalMap& map, int min_covisible, BaStates& states) {
  std::unordered_map<std::uint64_t, int> shared;
  map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (states.hasKeyframe(h)) return;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_map_point[k] && states.hasPoint(kf.map_point[k])) ++shared[handleKey(h)];
    }
  });
  int anchors = 0;
  map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (states.hasKeyframe(h)) return;
    const auto it = shared.find(handleKey(h));
    const int n = it != shared.end() ? it->second : 0;
    if ((kf.anchor && n > 0) || n >= min_covisible) {
      states.addKeyframe(h, false);
      anchors += kf.anchor ? 1 : 0;
    }
  });
  for (const PointState& p : states.points) states.addKeyframe(map.mapPoints().get(p.handle)->reference, false);
  return anchors;
}

std::optional<std::uint64_t> oldestFixedSequence(const LocalMap& map, const BaStates& states) {
  std::optional<std::uint64_t> oldest;
  for (const KeyframeState& s : states.keyframes) {
    const KeyframeData& kf = *map.keyframes().get(s.handle);
    if (!s.in_window && !kf.anchor && (!oldest || kf.sequence < *oldest)) oldest = kf.sequence;
  }
  return oldest;
}

void addParameterBlocks(BaStates& states, factors::PoseBlock& extrinsics, ceres::Problem& problem) {
  auto* pose_manifold = new factors::PoseManifold();  // owned by the problem, as are the cost functions
  problem.AddParameterBlock(extrinsics.data(), factors::kPoseSize, pose_manifold);
  problem.SetParameterBlockConstant(extrinsics.data());
  for (KeyframeState& s : states.keyframes) {
    problem.AddParameterBlock(s.pose.data(), factors::kPoseSize, pose_manifold);
    if (!s.in_window) problem.SetParameterBlockConstant(s.pose.data());
  }
  for (PointState& p : states.points) {
    problem.AddParameterBlock(p.point.data(), factors::kInverseDepthPointSize);
    problem.SetParameterLowerBound(p.point.data(), 2, kMinInverseDepth);
  }
}

// The blocks every observation may share: the extrinsics (held), and the time offset when estimated (the solve's
// start and the centre of its prior).
struct SharedBlocks {
  factors::PoseBlock extrinsics;
  bool estimate_time_offset = false;
  double time_correction_s = 0.0;
};

void addTimeOffsetBlock(const LocalBundleAdjustmentOptions& options, SharedBlocks& shared, ceres::Problem& problem) {
  if (!shared.estimate_time_offset) return;
  double& td = shared.time_correction_s;
  td = std::clamp(td, -options.max_time_offset_s, options.max_time_offset_s);
  problem.AddParameterBlock(&td, 1);
  problem.SetParameterLowerBound(&td, 0, -options.max_time_offset_s);
  problem.SetParameterUpperBound(&td, 0, options.max_time_offset_s);
  using Scalar = Eigen::Matrix<double, 1, 1>;
  problem.AddResidualBlock(
      new factors::VectorPriorFactor<1>(Scalar(td), Scalar(1.0 / options.time_offset_prior_sigma_s)), nullptr, &td);
}

// An observation from keyframe s of a point whose reference keyframe r is another one, with the time offset when
// it is estimated. Returns whether the offset took part.
bool addPointObservation(std::unique_ptr<factors::InverseDepthPointFactor> cost, KeyframeState& s, KeyframeState& r,
                         PointState& p, SharedBlocks& shared, double cauchy_scale, ceres::Problem& problem) {
  auto* loss = new ceres::CauchyLoss(cauchy_scale);
  if (!shared.estimate_time_offset) {
    problem.AddResidualBlock(cost.release(), loss, s.pose.data(), r.pose.data(), shared.extrinsics.data(),
                             p.point.data());
    return false;
  }
  problem.AddResidualBlock(new factors::TimeOffsetPointFactor(std::move(cost), s.motion, r.motion), loss, s.pose.data(),
                           r.pose.data(), shared.extrinsics.data(), p.point.data(), &shared.time_correction_s);
  return true;
}

// cam1's observation of keypoint k, kept only when it agrees with the current estimate: a wrong stereo
// match would otherwise pull the point's depth. Returns whether it was added.
bool addSecondCameraFactor(const KeyframeData& kf, std::uint16_t k, KeyframeState& s, KeyframeState& r, PointState& p,
                           SharedBlocks& shared, const LocalBundleAdjustmentOptions& options, ceres::Problem& problem,
                           LocalBundleAdjustmentSummary& summary) {
  const double sigma1 = options.sigma_px * std::pow(options.pyramid_scale_factor, kf.right_octave[k]);
  Eigen::Vector2d residual;
  if (&r == &s) {
    auto host = std::make_unique<factors::InverseDepthPointSecondCameraHostFactor>(
        kf.right_undistorted_px[k], options.second_intrinsics, sigma1, options.T_c1_c0);
    double* block = p.point.data();
    const bool evaluable = host->Evaluate(&block, residual.data(), nullptr);
    if (!evaluable || residual.norm() > options.max_second_camera_error_sigma) return false;
    problem.AddResidualBlock(host.release(), new ceres::CauchyLoss(options.cauchy_scale), block);
    return true;
  }
  auto cost = std::make_unique<factors::InverseDepthPointFactor>(kf.right_undistorted_px[k], options.second_intrinsics,
                                                                 sigma1, options.T_c1_c0);
  const double* blocks[] = {s.pose.data(), r.pose.data(), shared.extrinsics.data(), p.point.data()};
  const bool evaluable = cost->Evaluate(blocks, residual.data(), nullptr);
  if (!evaluable || residual.norm() > options.max_second_camera_error_sigma) return false;
  summary.time_offset_factors +=
      addPointObservation(std::move(cost), s, r, p, shared, options.cauchy_scale, problem) ? 1 : 0;
  return true;
}

// Reprojection factors: every observation of a window point from a keyframe in the problem.
void addReprojectionFactors(const LocalMap& map, const LocalBundleAdjustmentOptions& options, BaStates& states,
                            SharedBlocks& shared, ceres::Problem& problem, LocalBundleAdjustmentSummary& summary) {
  for (KeyframeState& s : states.keyframes) {
    const KeyframeData& kf = *map.keyframes().get(s.handle);
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (!kf.has_map_point[k]) continue;
      PointState* p = states.point(kf.map_point[k]);
      if (p == nullptr) continue;
      const PoolHandle ref = map.mapPoints().get(p->handle)->reference;
      KeyframeState& r = ref == s.handle ? s : states.keyframe(ref);
      const double sigma = options.sigma_px * std::pow(options.pyramid_scale_factor, kf.keypoints[k].octave);
      if (&r == &s) {
        problem.AddResidualBlock(
            new factors::InverseDepthPointHostFactor(kf.undistorted_px[k], options.intrinsics, sigma),
            new ceres::CauchyLoss(options.cauchy_scale), p->point.data());
      } else {
        auto cost = std::make_unique<factors::InverseDepthPointFactor>(kf.undistorted_px[k], options.intrinsics, sigma);
        summary.time_offset_factors +=
            addPointObservation(std::move(cost), s, r, *p, shared, options.cauchy_scale, problem) ? 1 : 0;
      }
      ++summary.reprojection_factors;
      summary.anchor_factors += kf.anchor ? 1 : 0;
      if (options.use_second_camera && kf.has_right[k]) {
        if (addSecondCameraFactor(kf, k, s, r, *p, shared, options, problem, summary)) {
          ++summary.reprojection_factors;
          ++summary.second_camera_factors;
        } else {
          ++summary.second_camera_rejected;
        }
      }
    }
  }
}

// IMU and bias random-walk factors between consecutive window keyframes. Returns how many pairs.
int addImuFactors(const LocalMap& map, const LocalBundleAdjustmentOptions& options,
                  const std::vector<PoolHandle>& window, BaStates& states, ceres::Problem& problem) {
  int pairs = 0;
  for (std::size_t i = 1; i < window.size(); ++i) {
    const KeyframeData& kf = *map.keyframes().get(window[i]);
    const KeyframeData& previous = *map.keyframes().get(window[i - 1]);
    // The preintegration must start at exactly the previous window keyframe: an anchor in between, or a
    // removed keyframe, breaks the chain.
    if (!kf.has_preintegration || !(kf.preintegration_from == previous.id)) continue;
    KeyframeState& a = states.keyframe(window[i - 1]);
    KeyframeState& b = states.keyframe(window[i]);
    problem.AddResidualBlock(new factors::ImuFactor(kf.preintegration), nullptr, a.pose.data(), a.velocity.data(),
                             a.bias.data(), b.pose.data(), b.velocity.data());
    problem.AddResidualBlock(new factors::BiasRandomWalkFactor(options.noise, kf.preintegration.dt()), nullptr,
                             a.bias.data(), b.bias.data());
    ++pairs;
  }
  return pairs;
}

// Points first, everything else after: each point is one block, seen only with keyframe states, so the
// Schur complement eliminates all of them and the reduced system holds the keyframes alone. Ceres wants
// every block of the problem in the ordering, constant ones too.
std::shared_ptr<ceres::ParameterBlockOrdering> pointsFirstOrdering(std::vector<PointState>& points,
                                                                   const ceres::Problem& problem) {
  auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
  for (PointState& p : points) ordering->AddElementToGroup(p.point.data(), 0);
  std::vector<double*> blocks_in_problem;
  problem.GetParameterBlocks(&blocks_in_problem);
  for (double* block : blocks_in_problem) {
    if (!ordering->IsMember(block)) ordering->AddElementToGroup(block, 1);
  }
  return ordering;
}

void writeBack(const BaStates& states, LocalMap& map) {
  for (const KeyframeState& s : states.keyframes) {
    if (!s.in_window) continue;
    KeyframeData& kf = *map.keyframes().get(s.handle);
    kf.T_w_s = factors::poseFromBlock(s.pose.data());
    kf.v_w = s.velocity;
    kf.bias.gyro = s.bias.head<3>();
    kf.bias.accel = s.bias.tail<3>();
  }
  for (const PointState& p : states.points) {
    MapPointData& mp = *map.mapPoints().get(p.handle);
    factors::bearingFromInverseDepthPoint(p.point, mp.bearing_c, mp.inverse_depth);
  }
}

}  // namespace

Result<LocalBundleAdjustmentSummary> runLocalBundleAdjustment(LocalMap& map,
                                                              const LocalBundleAdjustmentOptions& options,
                                                              const std::function<bool()>& stop) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  LocalBundleAdjustmentSummary summary;

  const std::vector<PoolHandle> window = selectWindow(map, options.window);
  if (window.empty()) return Error{ErrorCode::kNotFound, "local BA: no keyframe to optimise"};
  BaStates states(map);
  for (PoolHandle h : window) states.addKeyframe(h, true);
  summary.window_keyframes = static_cast<int>(states.keyframes.size());
  collectPoints(map, states);
  summary.map_points_left_out = static_cast<int>(states.left_out.size());
  summary.anchor_keyframes = addFixedKeyframes(map, options.min_covisible, states);
  summary.fixed_keyframes = static_cast<int>(states.keyframes.size()) - summary.window_keyframes;
  summary.newest_sequence = map.keyframes().get(window.back())->sequence;
  summary.oldest_fixed_sequence = oldestFixedSequence(map, states);
  summary.map_points = static_cast<int>(states.points.size());

  ceres::Problem problem;
  SharedBlocks shared;
  shared.extrinsics = factors::poseToBlock(map.extrinsics());
  shared.estimate_time_offset = options.estimate_time_offset && options.use_imu;
  shared.time_correction_s = map.timeCorrectionS();
  addParameterBlocks(states, shared.extrinsics, problem);
  addTimeOffsetBlock(options, shared, problem);
  addReprojectionFactors(map, options, states, shared, problem, summary);
  if (options.use_imu) summary.imu_factors = addImuFactors(map, options, window, states, problem);
  if (summary.fixed_keyframes == 0) {  // the gauge
    problem.SetParameterBlockConstant(states.keyframes.front().pose.data());
    // Without the IMU (or with no IMU link) and without stereo, scale is free as well: hold a second pose.
    if (summary.imu_factors == 0 && summary.second_camera_factors == 0 && states.keyframes.size() > 1) {
      problem.SetParameterBlockConstant(states.keyframes[1].pose.data());
    }
  }

  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::SPARSE_SCHUR;
  // Without points (all left out) Ceres picks the elimination itself, as group 0 would be empty.
  if (!states.points.empty()) solver_options.linear_solver_ordering = pointsFirstOrdering(states.points, problem);
  solver_options.max_num_iterations = options.max_iterations;
  solver_options.num_threads = 1;
  std::optional<StopWhenAsked> stop_when_asked;
  if (stop) {
    stop_when_asked.emplace(stop, options.max_iterations);
    solver_options.callbacks.push_back(&*stop_when_asked);
  }
  ceres::Solver::Summary ceres_summary;
  ceres::Solve(solver_options, &problem, &ceres_summary);
  summary.stopped_early = stop_when_asked && stop_when_asked->stopped();
  if (!ceres_summary.IsSolutionUsable()) {
    return Error{ErrorCode::kDegenerate, "local BA failed: " + ceres_summary.message};
  }
  summary.iterations = static_cast<int>(ceres_summary.iterations.size()) - 1;
  summary.initial_cost = ceres_summary.initial_cost;
  summary.final_cost = ceres_summary.final_cost;
  writeBack(states, map);
  // A window whose observations all come from their points' reference keyframes says nothing of the offset.
  if (summary.time_offset_factors > 0) map.setTimeCorrectionS(shared.time_correction_s);
  return summary;
}

}  // namespace cvislam::agent
