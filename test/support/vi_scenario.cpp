#include "test/support/vi_scenario.hpp"

#include <cmath>
#include <random>

#include <ceres/loss_function.h>

#include "common/dataset/euroc_calibration.hpp"

#include "common/factors/imu_factor.hpp"
#include "common/factors/inverse_depth_point_factor.hpp"
#include "common/factors/manifolds.hpp"

namespace cvislam::test {

using Eigen::Vector3d;
using geometry::SO3d;

namespace {

constexpr double kImageWidth = 752.0;
constexpr double kImageHeight = 480.0;

// Fixed rotation that makes the camera look along world +x (image x to world -y, image y to world -z)
// when phi = 0.
SO3d baseRotation() {
  Eigen::Matrix3d R_w_c;
  R_w_c.col(0) = -Vector3d::UnitY();
  R_w_c.col(1) = -Vector3d::UnitZ();
  R_w_c.col(2) = Vector3d::UnitX();
  return SO3d(R_w_c) * dataset::eurocCam0().T_b_c.so3().inverse();
}

// Rotation R_w_s(t) = R_base Exp(phi(t)) and position p_w(t), with analytic derivatives.
Vector3d phiAt(double t) {
  return {0.15 * std::sin(0.9 * t), 0.12 * std::cos(0.7 * t) - 0.12, 0.25 * std::sin(0.4 * t)};
}
Vector3d phiDotAt(double t) {
  return {0.135 * std::cos(0.9 * t), -0.084 * std::sin(0.7 * t), 0.1 * std::cos(0.4 * t)};
}
Vector3d positionAt(double t) {
  return {0.8 * std::sin(0.5 * t), 1.2 * std::sin(0.8 * t), 1.5 + 0.3 * std::sin(1.1 * t)};
}
Vector3d velocityAt(double t) {
  return {0.4 * std::cos(0.5 * t), 0.96 * std::cos(0.8 * t), 0.33 * std::cos(1.1 * t)};
}
Vector3d accelerationAt(double t) {
  return {-0.2 * std::sin(0.5 * t), -0.768 * std::sin(0.8 * t), -0.363 * std::sin(1.1 * t)};
}

std::int64_t toNs(double t_s) {
  return std::llround(t_s * 1e9);
}

// IMU and bias random-walk factors between consecutive keyframes.
void addImuFactors(const ViScenario& scenario, ViBaState& state, ceres::Problem& problem) {
  for (std::size_t i = 0; i + 1 < state.poses.size(); ++i) {
    const imu::Preintegration& pre = scenario.preintegrations[i];
    problem.AddResidualBlock(new factors::ImuFactor(pre), nullptr, state.poses[i].data(), state.velocities[i].data(),
                             state.biases[i].data(), state.poses[i + 1].data(), state.velocities[i + 1].data());
    problem.AddResidualBlock(new factors::BiasRandomWalkFactor(scenario.noise, pre.dt()), nullptr,
                             state.biases[i].data(), state.biases[i + 1].data());
  }
}

}  // namespace

imu::NavState trueViState(double t_s) {
  imu::NavState state;
  state.T_w_s = geometry::SE3d(baseRotation() * SO3d::exp(phiAt(t_s)), positionAt(t_s));
  state.v_w = velocityAt(t_s);
  return state;
}

ViScenario makeViScenario(const ViScenarioOptions& options) {
  ViScenario s;
  s.options = options;
  s.T_s_c = dataset::eurocCam0().T_b_c;
  std::mt19937_64 rng(options.seed);

  // IMU: d/dt Exp(phi) = Exp(phi) [Jr(phi) phi_dot]x, so the body rate is Jr(phi) phi_dot.
  const double imu_dt = 1.0 / options.imu_rate_hz;
  const double duration = options.keyframe_interval_s * (options.keyframes - 1);
  const int sample_count = static_cast<int>(std::llround(duration / imu_dt)) + 1;
  for (int k = 0; k < sample_count; ++k) {
    const double t = k * imu_dt;
    const SO3d R_w_s = baseRotation() * SO3d::exp(phiAt(t));
    dataset::ImuSample sample;
    sample.t_ns = toNs(t);
    sample.gyro_s = SO3d::rightJacobian(phiAt(t)) * phiDotAt(t) + options.bias.gyro;
    sample.accel_s = R_w_s.inverse() * (accelerationAt(t) - imu::kGravityW) + options.bias.accel;
    s.imu.push_back(sample);
  }

  for (int i = 0; i < options.keyframes; ++i) {
    const double t = i * options.keyframe_interval_s;
    s.keyframe_t_ns.push_back(toNs(t));
    s.keyframe_states.push_back(trueViState(t));
  }
  for (int i = 0; i + 1 < options.keyframes; ++i) {
    imu::Preintegration pre(imu::ImuBias{}, s.noise);
    const Status status = pre.integrateInterval(s.imu, s.keyframe_t_ns[static_cast<std::size_t>(i)],
                                                s.keyframe_t_ns[static_cast<std::size_t>(i) + 1]);
    (void)status;  // the samples cover every interval by construction
    s.preintegrations.push_back(pre);
  }

  // Points on the faces of a box in front of the camera, kept when at least two keyframes see them.
  std::uniform_real_distribution<double> y_dist(-4.0, 4.0);
  std::uniform_real_distribution<double> z_dist(-1.0, 4.0);
  std::uniform_real_distribution<double> x_dist(5.0, 9.0);
  std::normal_distribution<double> pixel_noise(0.0, 1.0);
  int attempts = 0;
  while (static_cast<int>(s.points.size()) < options.points && attempts++ < 100 * options.points) {
    const Vector3d p_w(x_dist(rng), y_dist(rng), z_dist(rng));
    std::vector<ViObservation> seen;
    for (int i = 0; i < options.keyframes; ++i) {
      const geometry::SE3d T_c_w = (s.keyframe_states[static_cast<std::size_t>(i)].T_w_s * s.T_s_c).inverse();
      const Vector3d p_c = T_c_w * p_w;
      if (p_c.z() < 0.5) continue;
      const Eigen::Vector2d px(s.intrinsics.fx * p_c.x() / p_c.z() + s.intrinsics.cx,
                               s.intrinsics.fy * p_c.y() / p_c.z() + s.intrinsics.cy);
      if (px.x() < 0.0 || px.y() < 0.0 || px.x() >= kImageWidth || px.y() >= kImageHeight) continue;
      seen.push_back({i, static_cast<int>(s.points.size()), px});
    }
    if (seen.size() < 2) continue;
    ViPoint point;
    point.reference_keyframe = seen.front().keyframe;
    point.p_w = p_w;
    const geometry::SE3d T_c_w =
        (s.keyframe_states[static_cast<std::size_t>(point.reference_keyframe)].T_w_s * s.T_s_c).inverse();
    const Vector3d p_c = T_c_w * p_w;
    point.bearing_c = p_c.normalized();
    point.inverse_depth = 1.0 / p_c.norm();
    for (ViObservation& o : seen) {
      if (options.pixel_sigma > 0.0) {
        o.keypoint_px += options.pixel_sigma * Eigen::Vector2d(pixel_noise(rng), pixel_noise(rng));
      }
      s.observations.push_back(o);
    }
    s.points.push_back(point);
  }
  return s;
}

ViBaState trueViBaState(const ViScenario& scenario) {
  ViBaState state;
  for (const imu::NavState& kf : scenario.keyframe_states) {
    state.poses.push_back(factors::poseToBlock(kf.T_w_s));
    state.velocities.push_back(kf.v_w);
    Eigen::Matrix<double, 6, 1> bias;
    bias << scenario.options.bias.gyro, scenario.options.bias.accel;
    state.biases.push_back(bias);
  }
  for (const ViPoint& p : scenario.points) {
    state.bearings.push_back(p.bearing_c);
    state.inverse_depths.push_back(p.inverse_depth);
  }
  state.extrinsics = factors::poseToBlock(scenario.T_s_c);
  return state;
}

void perturbViBaState(ViBaState& state, double position_m, double rotation_rad, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  const auto random3 = [&] { return Vector3d(unit(rng), unit(rng), unit(rng)); };
  const factors::PoseManifold pose_manifold;
  const factors::UnitBearingManifold bearing_manifold;
  for (std::size_t i = 1; i < state.poses.size(); ++i) {
    Eigen::Matrix<double, 6, 1> delta;
    delta << position_m * random3(), rotation_rad * random3() / std::sqrt(3.0);
    factors::PoseBlock perturbed;
    pose_manifold.Plus(state.poses[i].data(), delta.data(), perturbed.data());
    state.poses[i] = perturbed;
    state.velocities[i] += 0.1 * random3();
  }
  for (auto& bias : state.biases) bias.setZero();
  const double bearing_rad = 0.5 * M_PI / 180.0;
  for (std::size_t j = 0; j < state.bearings.size(); ++j) {
    const Eigen::Vector2d delta(bearing_rad * unit(rng) / std::sqrt(2.0), bearing_rad * unit(rng) / std::sqrt(2.0));
    Vector3d perturbed;
    bearing_manifold.Plus(state.bearings[j].data(), delta.data(), perturbed.data());
    state.bearings[j] = perturbed;
    state.inverse_depths[j] *= 1.0 + 0.1 * unit(rng);
  }
}

void addViBaFactors(const ViScenario& scenario, ViBaState& state, ceres::Problem& problem) {
  // Ceres takes ownership of cost functions, losses and manifolds unless told otherwise.
  auto* pose_manifold = new factors::PoseManifold();
  auto* bearing_manifold = new factors::UnitBearingManifold();
  for (auto& pose : state.poses) problem.AddParameterBlock(pose.data(), factors::kPoseSize, pose_manifold);
  problem.AddParameterBlock(state.extrinsics.data(), factors::kPoseSize, pose_manifold);
  problem.SetParameterBlockConstant(state.extrinsics.data());
  for (auto& bearing : state.bearings) problem.AddParameterBlock(bearing.data(), 3, bearing_manifold);

  for (const ViObservation& o : scenario.observations) {
    const auto j = static_cast<std::size_t>(o.point);
    const int ref = scenario.points[j].reference_keyframe;
    auto* loss = new ceres::CauchyLoss(1.0);
    if (o.keyframe == ref) {
      problem.AddResidualBlock(new factors::ReprojectionHostFactor(o.keypoint_px, scenario.intrinsics, 1.0), loss,
                               state.bearings[j].data());
    } else {
      problem.AddResidualBlock(new factors::ReprojectionFactor(o.keypoint_px, scenario.intrinsics, 1.0), loss,
                               state.poses[static_cast<std::size_t>(o.keyframe)].data(),
                               state.poses[static_cast<std::size_t>(ref)].data(), state.extrinsics.data(),
                               state.bearings[j].data(), &state.inverse_depths[j]);
    }
  }
  addImuFactors(scenario, state, problem);
}

std::vector<Vector3d> inverseDepthPoints(const ViBaState& state) {
  std::vector<Vector3d> points(state.bearings.size());
  for (std::size_t j = 0; j < points.size(); ++j) {
    // The scene's points are in front of their reference cameras, well inside the image: always converts.
    const bool converted = factors::inverseDepthPointFromBearing(state.bearings[j], state.inverse_depths[j], points[j]);
    (void)converted;
  }
  return points;
}

std::shared_ptr<ceres::ParameterBlockOrdering> addViBaFactorsWithPointBlocks(const ViScenario& scenario,
                                                                             ViBaState& state,
                                                                             std::vector<Vector3d>& points,
                                                                             ceres::Problem& problem) {
  auto* pose_manifold = new factors::PoseManifold();
  for (auto& pose : state.poses) problem.AddParameterBlock(pose.data(), factors::kPoseSize, pose_manifold);
  problem.AddParameterBlock(state.extrinsics.data(), factors::kPoseSize, pose_manifold);
  problem.SetParameterBlockConstant(state.extrinsics.data());
  for (auto& point : points) problem.AddParameterBlock(point.data(), factors::kInverseDepthPointSize);

  for (const ViObservation& o : scenario.observations) {
    const auto j = static_cast<std::size_t>(o.point);
    const int ref = scenario.points[j].reference_keyframe;
    auto* loss = new ceres::CauchyLoss(1.0);
    if (o.keyframe == ref) {
      problem.AddResidualBlock(new factors::InverseDepthPointHostFactor(o.keypoint_px, scenario.intrinsics, 1.0), loss,
                               points[j].data());
    } else {
      problem.AddResidualBlock(new factors::InverseDepthPointFactor(o.keypoint_px, scenario.intrinsics, 1.0), loss,
                               state.poses[static_cast<std::size_t>(o.keyframe)].data(),
                               state.poses[static_cast<std::size_t>(ref)].data(), state.extrinsics.data(),
                               points[j].data());
    }
  }
  addImuFactors(scenario, state, problem);

  auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
  for (auto& point : points) ordering->AddElementToGroup(point.data(), 0);
  std::vector<double*> blocks;
  problem.GetParameterBlocks(&blocks);
  for (double* block : blocks) {
    if (!ordering->IsMember(block)) ordering->AddElementToGroup(block, 1);
  }
  return ordering;
}

}  // namespace cvislam::test
