// A synthetic visual-inertial scene with exact ground truth, for the factor tests and benchmarks: a smooth
// camera-IMU trajectory (analytic position and rotation), IMU samples from its analytic derivatives, points
// on a box in front of the camera, and their pixel observations in each keyframe.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <ceres/ordered_groups.h>
#include <ceres/problem.h>
#include <Eigen/Core>

#include "common/dataset/types.hpp"
#include "common/factors/reprojection_factor.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::test {

struct ViScenarioOptions {
  int keyframes = 8;
  double keyframe_interval_s = 0.5;
  int points = 300;
  // Samples are instantaneous readings, as a real IMU's and EuRoC's are.
  double imu_rate_hz = 1000.0;
  imu::ImuBias bias;         // added to every IMU sample
  double pixel_sigma = 0.0;  // Gaussian noise on the observations
  std::uint64_t seed = 7;
};

struct ViPoint {
  int reference_keyframe = 0;
  Eigen::Vector3d bearing_c = Eigen::Vector3d::UnitZ();  // in the reference camera
  double inverse_depth = 1.0;
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
};

struct ViObservation {
  int keyframe = 0;
  int point = 0;
  Eigen::Vector2d keypoint_px = Eigen::Vector2d::Zero();
};

struct ViScenario {
  ViScenarioOptions options;
  factors::PinholeIntrinsics intrinsics;
  geometry::SE3d T_s_c;  // EuRoC cam0 extrinsics
  imu::ImuNoise noise;
  std::vector<std::int64_t> keyframe_t_ns;
  std::vector<imu::NavState> keyframe_states;
  std::vector<dataset::ImuSample> imu;
  std::vector<imu::Preintegration> preintegrations;  // between keyframe k and k+1, at bias_lin = 0
  std::vector<ViPoint> points;
  std::vector<ViObservation> observations;
};

// The optimisation states of a scenario, in the Ceres layouts of common/factors/state_layout.hpp.
struct ViBaState {
  std::vector<factors::PoseBlock> poses;
  std::vector<Eigen::Vector3d> velocities;
  std::vector<Eigen::Matrix<double, 6, 1>> biases;
  std::vector<Eigen::Vector3d> bearings;
  std::vector<double> inverse_depths;
  factors::PoseBlock extrinsics = factors::PoseBlock::Zero();
};

// The true states (biases as in the options).
ViBaState trueViBaState(const ViScenario& scenario);

// Perturbs every state but the first pose, deterministically from `seed`: positions by up to
// `position_m`, rotations by up to `rotation_rad`, velocities by up to 0.1 m/s, bearings by up to 0.5 deg,
// inverse depths by up to 10 %. Biases start at zero.
void perturbViBaState(ViBaState& state, double position_m, double rotation_rad, std::uint64_t seed);

// Adds the scenario's factors on `state` to `problem`: reprojection (Cauchy loss of 1 px, sigma 1 px), IMU
// and bias random walk between consecutive keyframes, manifolds on poses and bearings. The extrinsics are
// held constant. Nothing else is fixed: the caller chooses the gauge.
void addViBaFactors(const ViScenario& scenario, ViBaState& state, ceres::Problem& problem);

// `state`'s points as one block each, the inverse-depth point (a, b, rho) of
// common/factors/inverse_depth_point_factor.hpp, converted from its bearings and inverse distances.
std::vector<Eigen::Vector3d> inverseDepthPoints(const ViBaState& state);

// As addViBaFactors, but each point is one block of `points` (InverseDepthPointFactor and
// InverseDepthPointHostFactor, same losses and sigmas); `state`'s bearings and inverse depths are not used.
// Returns the Schur ordering that eliminates the points first (group 0) and keeps everything else in group 1,
// for Solver::Options::linear_solver_ordering.
std::shared_ptr<ceres::ParameterBlockOrdering> addViBaFactorsWithPointBlocks(const ViScenario& scenario,
                                                                             ViBaState& state,
                                                                             std::vector<Eigen::Vector3d>& points,
                                                                             ceres::Problem& problem);

// The true state at time t (seconds from the start).
imu::NavState trueViState(double t_s);

ViScenario makeViScenario(const ViScenarioOptions& options);

}  // namespace cvislam::test
