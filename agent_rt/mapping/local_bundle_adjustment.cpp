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
#include "common/factors/state_layout.hpp"

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

}  // namespace

Result<LocalBundleAdjustmentSummary> runLocalBundleAdjustment(LocalMap& map,
                                                              const LocalBundleAdjustmentOptions& options,
                                                              const std::function<bool()>& stop) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  LocalBundleAdjustmentSummary summary;

  // The window: the newest non-anchor keyframes, by sequence.
  std::vector<std::pair<std::uint64_t, PoolHandle>> by_sequence;
  map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (!kf.anchor) by_sequence.emplace_back(kf.sequence, h);
  });
  std::sort(by_sequence.begin(), by_sequence.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  if (by_sequence.empty()) return Error{ErrorCode::kNotFound, "local BA: no keyframe to optimise"};
  const std::size_t first = by_sequence.size() > static_cast<std::size_t>(options.window)
                                ? by_sequence.size() - static_cast<std::size_t>(options.window)
                                : 0;

  std::unordered_map<std::uint64_t, std::size_t> keyframe_index;  // handle -> index in `keyframes`
  std::vector<KeyframeState> keyframes;
  const auto add_keyframe = [&](PoolHandle h, bool in_window) -> std::size_t {
    const auto [it, inserted] = keyframe_index.emplace(handleKey(h), keyframes.size());
    if (inserted) {
      const KeyframeData& kf = *map.keyframes().get(h);
      KeyframeState s;
      s.handle = h;
      s.pose = factors::poseToBlock(kf.T_w_s);
      s.velocity = kf.v_w;
      s.bias << kf.bias.gyro, kf.bias.accel;
      s.in_window = in_window;
      keyframes.push_back(s);
    }
    return it->second;
  };
  for (std::size_t i = first; i < by_sequence.size(); ++i) add_keyframe(by_sequence[i].second, true);
  summary.window_keyframes = static_cast<int>(keyframes.size());

  // The points the window observes, and how many of them every other keyframe shares. A point without an
  // inverse-depth point (a bearing nearly in its reference image plane, a non-finite or negative inverse
  // distance: corrupt, no pinhole image saw it) or without its reference keyframe is left out, as are its
  // observations, rather than failing the whole BA; it stays in the map as it was.
  std::unordered_map<std::uint64_t, std::size_t> point_index;
  std::unordered_set<std::uint64_t> left_out;
  std::vector<PointState> points;
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    const KeyframeData& kf = *map.keyframes().get(keyframes[i].handle);
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (!kf.has_map_point[k]) continue;
      const MapPointData* mp = map.mapPoints().get(kf.map_point[k]);
      if (mp == nullptr) continue;
      const std::uint64_t key = handleKey(kf.map_point[k]);
      if (point_index.count(key) != 0 || left_out.count(key) != 0) continue;
      Vector3d point;
      if (!map.keyframes().valid(mp->reference) || !(mp->inverse_depth >= 0.0) ||
          !factors::inverseDepthPointFromBearing(mp->bearing_c, mp->inverse_depth, point)) {
        left_out.insert(key);
        continue;
      }
      point.z() = std::max(point.z(), kMinInverseDepth);  // Ceres needs a feasible start
      point_index.emplace(key, points.size());
      points.push_back({kf.map_point[k], point});
    }
  }
  summary.map_points_left_out = static_cast<int>(left_out.size());
  std::unordered_map<std::uint64_t, int> shared;
  map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (keyframe_index.count(handleKey(h)) != 0) return;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_map_point[k] && point_index.count(handleKey(kf.map_point[k])) != 0) ++shared[handleKey(h)];
    }
  });
  map.keyframes().forEach([&](PoolHandle h, const KeyframeData& kf) {
    if (keyframe_index.count(handleKey(h)) != 0) return;
    const auto it = shared.find(handleKey(h));
    // An anchor (the server's) counts with any shared point: its pose is the server's refined one.
    const int n = it != shared.end() ? it->second : 0;
    if ((kf.anchor && n > 0) || n >= options.min_covisible) {
      add_keyframe(h, false);
      summary.anchor_keyframes += kf.anchor ? 1 : 0;
    }
  });
  for (const PointState& p : points) {  // reference keyframes are needed as fixed poses at least
    add_keyframe(map.mapPoints().get(p.handle)->reference, false);
  }
  summary.fixed_keyframes = static_cast<int>(keyframes.size()) - summary.window_keyframes;
  summary.map_points = static_cast<int>(points.size());

  ceres::Problem problem;
  auto* pose_manifold = new factors::PoseManifold();  // owned by the problem, as are the cost functions
  factors::PoseBlock extrinsics = factors::poseToBlock(map.extrinsics());
  problem.AddParameterBlock(extrinsics.data(), factors::kPoseSize, pose_manifold);
  problem.SetParameterBlockConstant(extrinsics.data());
  for (KeyframeState& s : keyframes) {
    problem.AddParameterBlock(s.pose.data(), factors::kPoseSize, pose_manifold);
    if (!s.in_window) problem.SetParameterBlockConstant(s.pose.data());
  }
  for (PointState& p : points) {
    problem.AddParameterBlock(p.point.data(), factors::kInverseDepthPointSize);
    problem.SetParameterLowerBound(p.point.data(), 2, kMinInverseDepth);
  }

  // Reprojection factors: every observation of a window point from a keyframe in the problem.
  for (KeyframeState& s : keyframes) {
    const KeyframeData& kf = *map.keyframes().get(s.handle);
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (!kf.has_map_point[k]) continue;
      const auto pit = point_index.find(handleKey(kf.map_point[k]));
      if (pit == point_index.end()) continue;
      PointState& p = points[pit->second];
      const PoolHandle ref = map.mapPoints().get(p.handle)->reference;
      const double sigma = options.sigma_px * std::pow(options.pyramid_scale_factor, kf.keypoints[k].octave);
      auto* loss = new ceres::CauchyLoss(options.cauchy_scale);
      if (ref == s.handle) {
        problem.AddResidualBlock(
            new factors::InverseDepthPointHostFactor(kf.undistorted_px[k], options.intrinsics, sigma), loss,
            p.point.data());
      } else {
        KeyframeState& r = keyframes[keyframe_index.at(handleKey(ref))];
        problem.AddResidualBlock(new factors::InverseDepthPointFactor(kf.undistorted_px[k], options.intrinsics, sigma),
                                 loss, s.pose.data(), r.pose.data(), extrinsics.data(), p.point.data());
      }
      ++summary.reprojection_factors;
      summary.anchor_factors += kf.anchor ? 1 : 0;
      if (options.use_second_camera && kf.has_right[k]) {
        const double sigma1 = options.sigma_px * std::pow(options.pyramid_scale_factor, kf.right_octave[k]);
        std::unique_ptr<ceres::CostFunction> cost;
        std::vector<double*> blocks;
        if (ref == s.handle) {
          cost = std::make_unique<factors::InverseDepthPointSecondCameraHostFactor>(
              kf.right_undistorted_px[k], options.second_intrinsics, sigma1, options.T_c1_c0);
          blocks = {p.point.data()};
        } else {
          KeyframeState& r = keyframes[keyframe_index.at(handleKey(ref))];
          cost = std::make_unique<factors::InverseDepthPointFactor>(kf.right_undistorted_px[k],
                                                                    options.second_intrinsics, sigma1, options.T_c1_c0);
          blocks = {s.pose.data(), r.pose.data(), extrinsics.data(), p.point.data()};
        }
        Eigen::Vector2d residual;
        const bool evaluable = cost->Evaluate(blocks.data(), residual.data(), nullptr);
        if (!evaluable || residual.norm() > options.max_second_camera_error_sigma) {
          ++summary.second_camera_rejected;
          continue;
        }
        problem.AddResidualBlock(cost.release(), new ceres::CauchyLoss(options.cauchy_scale), blocks);
        ++summary.reprojection_factors;
        ++summary.second_camera_factors;
      }
    }
  }

  // IMU and bias random-walk factors between consecutive window keyframes.
  if (options.use_imu) {
    for (std::size_t i = first + 1; i < by_sequence.size(); ++i) {
      const KeyframeData& kf = *map.keyframes().get(by_sequence[i].second);
      const KeyframeData& previous = *map.keyframes().get(by_sequence[i - 1].second);
      // The preintegration must start at exactly the previous window keyframe: an anchor in between, or a
      // removed keyframe, breaks the chain.
      if (!kf.has_preintegration || !(kf.preintegration_from == previous.id)) continue;
      KeyframeState& a = keyframes[keyframe_index.at(handleKey(by_sequence[i - 1].second))];
      KeyframeState& b = keyframes[keyframe_index.at(handleKey(by_sequence[i].second))];
      problem.AddResidualBlock(new factors::ImuFactor(kf.preintegration), nullptr, a.pose.data(), a.velocity.data(),
                               a.bias.data(), b.pose.data(), b.velocity.data());
      problem.AddResidualBlock(new factors::BiasRandomWalkFactor(options.noise, kf.preintegration.dt()), nullptr,
                               a.bias.data(), b.bias.data());
      ++summary.imu_factors;
    }
  }
  if (summary.fixed_keyframes == 0) {  // the gauge
    problem.SetParameterBlockConstant(keyframes.front().pose.data());
    // Without the IMU (or with no IMU link) and without stereo, scale is free as well: hold a second pose.
    if (summary.imu_factors == 0 && summary.second_camera_factors == 0 && keyframes.size() > 1) {
      problem.SetParameterBlockConstant(keyframes[1].pose.data());
    }
  }

  // Points first, everything else after: each point is one block, seen only with keyframe states, so the
  // Schur complement eliminates all of them and the reduced system holds the keyframes alone. Ceres wants
  // every block of the problem in the ordering, constant ones too.
  // Without points (all left out) Ceres picks the elimination itself, as group 0 would be empty.
  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::SPARSE_SCHUR;
  if (!points.empty()) {
    auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
    for (PointState& p : points) ordering->AddElementToGroup(p.point.data(), 0);
    std::vector<double*> blocks_in_problem;
    problem.GetParameterBlocks(&blocks_in_problem);
    for (double* block : blocks_in_problem) {
      if (!ordering->IsMember(block)) ordering->AddElementToGroup(block, 1);
    }
    solver_options.linear_solver_ordering = ordering;
  }
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

  // Write back what was optimised.
  for (const KeyframeState& s : keyframes) {
    if (!s.in_window) continue;
    KeyframeData& kf = *map.keyframes().get(s.handle);
    kf.T_w_s = factors::poseFromBlock(s.pose.data());
    kf.v_w = s.velocity;
    kf.bias.gyro = s.bias.head<3>();
    kf.bias.accel = s.bias.tail<3>();
  }
  for (const PointState& p : points) {
    MapPointData& mp = *map.mapPoints().get(p.handle);
    factors::bearingFromInverseDepthPoint(p.point, mp.bearing_c, mp.inverse_depth);
  }
  return summary;
}

}  // namespace cvislam::agent
