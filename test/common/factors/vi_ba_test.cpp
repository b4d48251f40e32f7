// A small visual-inertial bundle adjustment on the synthetic scene: it converges from a perturbed start to
// the truth, and its information matrix has exactly the gauge freedom of visual-inertial estimation.
#include <algorithm>
#include <cmath>
#include <cstdio>

#include <ceres/ceres.h>
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <Eigen/SparseCore>

#include "common/factors/inverse_depth_point_factor.hpp"
#include "common/factors/state_layout.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::factors {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;

test::ViScenarioOptions scenarioOptions(int keyframes, int points) {
  test::ViScenarioOptions options;
  options.keyframes = keyframes;
  options.points = points;
  options.bias.gyro = Vector3d(0.004, -0.003, 0.002);
  options.bias.accel = Vector3d(0.03, -0.02, 0.04);
  return options;
}

// The scene's VI-BA from `state`, the first keyframe's pose held (the gauge), solved to tight tolerances.
ceres::Solver::Summary solveViBa(const test::ViScenario& scenario, test::ViBaState& state, int max_iterations) {
  ceres::Problem problem;
  test::addViBaFactors(scenario, state, problem);
  problem.SetParameterBlockConstant(state.poses[0].data());
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::SPARSE_SCHUR;
  options.max_num_iterations = max_iterations;
  options.function_tolerance = 1e-12;
  options.gradient_tolerance = 1e-14;
  options.parameter_tolerance = 1e-12;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  return summary;
}

TEST(VisualInertialBundleAdjustment, ConvergesFromAPerturbedStartToTheTruth) {
  const test::ViScenario scenario = test::makeViScenario(scenarioOptions(8, 300));
  ASSERT_EQ(scenario.points.size(), 300u);
  const test::ViBaState truth = test::trueViBaState(scenario);
  test::ViBaState state = truth;
  test::perturbViBaState(state, 0.1, 2.0 * M_PI / 180.0, 3);

  const ceres::Solver::Summary summary = solveViBa(scenario, state, 50);
  ASSERT_TRUE(summary.IsSolutionUsable()) << summary.FullReport();
  std::printf("VI-BA: %d keyframes, %zu points, %zu observations: cost %.3e -> %.3e in %d iterations\n",
              scenario.options.keyframes, scenario.points.size(), scenario.observations.size(), summary.initial_cost,
              summary.final_cost, static_cast<int>(summary.iterations.size()) - 1);

  for (std::size_t i = 0; i < truth.poses.size(); ++i) {
    const SE3d T = poseFromBlock(state.poses[i].data());
    const SE3d T_true = poseFromBlock(truth.poses[i].data());
    EXPECT_LT((T.translation() - T_true.translation()).norm(), 1e-4) << "keyframe " << i;
    EXPECT_LT((T_true.so3().inverse() * T.so3()).log().norm(), 1e-5) << "keyframe " << i;
    EXPECT_LT((state.velocities[i] - truth.velocities[i]).norm(), 1e-4) << "keyframe " << i;
    EXPECT_LT((state.biases[i].head<3>() - truth.biases[i].head<3>()).norm(), 1e-4) << "keyframe " << i;
    EXPECT_LT((state.biases[i].tail<3>() - truth.biases[i].tail<3>()).norm(), 5e-3) << "keyframe " << i;
  }
  for (std::size_t j = 0; j < truth.bearings.size(); ++j) {
    EXPECT_LT(std::acos(std::min(1.0, state.bearings[j].dot(truth.bearings[j]))), 1e-6) << "point " << j;
    EXPECT_NEAR(state.inverse_depths[j] / truth.inverse_depths[j], 1.0, 1e-4) << "point " << j;
  }
}

// With pixel noise the optimum is no longer the truth, and where it lies depends on the noise drawn: over 30
// noise seeds of this scene (x86-64) the worst keyframe ended 1.4 to 14.7 mm (median 5 mm) from the truth, and
// the aarch64 build draws another realisation from the same seed (a visibility test near its threshold flips,
// so 16 fewer observations take noise). So the solver is held to what it controls: from the perturbed start it
// reaches the same optimum as a solve started at the truth. The distance to the truth gets the noise's bound.
TEST(VisualInertialBundleAdjustment, WithPixelNoiseReachesTheOptimumAStartAtTheTruthReaches) {
  test::ViScenarioOptions options = scenarioOptions(8, 300);
  options.pixel_sigma = 0.5;
  const test::ViScenario scenario = test::makeViScenario(options);
  const test::ViBaState truth = test::trueViBaState(scenario);
  const auto solve = [&](test::ViBaState& state) { return solveViBa(scenario, state, 100); };
  test::ViBaState optimum = truth;
  const ceres::Solver::Summary reference = solve(optimum);
  ASSERT_TRUE(reference.IsSolutionUsable()) << reference.FullReport();
  test::ViBaState state = truth;
  test::perturbViBaState(state, 0.1, 2.0 * M_PI / 180.0, 4);
  const ceres::Solver::Summary summary = solve(state);
  ASSERT_TRUE(summary.IsSolutionUsable()) << summary.FullReport();

  double to_optimum_m = 0.0;
  double to_optimum_deg = 0.0;
  double to_truth_m = 0.0;
  double to_truth_deg = 0.0;
  for (std::size_t i = 0; i < truth.poses.size(); ++i) {
    const SE3d T = poseFromBlock(state.poses[i].data());
    const SE3d T_opt = poseFromBlock(optimum.poses[i].data());
    const SE3d T_true = poseFromBlock(truth.poses[i].data());
    to_optimum_m = std::max(to_optimum_m, (T.translation() - T_opt.translation()).norm());
    to_optimum_deg = std::max(to_optimum_deg, (T_opt.so3().inverse() * T.so3()).log().norm() * 180.0 / M_PI);
    to_truth_m = std::max(to_truth_m, (T.translation() - T_true.translation()).norm());
    to_truth_deg = std::max(to_truth_deg, (T_true.so3().inverse() * T.so3()).log().norm() * 180.0 / M_PI);
  }
  std::printf(
      "VI-BA with 0.5 px noise: cost %.6g (from the truth %.6g); worst keyframe %.4f mm, %.6f deg from the "
      "optimum, %.2f mm, %.4f deg from the truth\n",
      summary.final_cost, reference.final_cost, 1e3 * to_optimum_m, to_optimum_deg, 1e3 * to_truth_m, to_truth_deg);
  EXPECT_NEAR(summary.final_cost, reference.final_cost, 1e-6 * reference.final_cost);
  EXPECT_LT(to_optimum_m, 1e-4);
  EXPECT_LT(to_optimum_deg, 1e-3);
  EXPECT_LT(to_truth_m, 0.02);
  EXPECT_LT(to_truth_deg, 0.1);
}

// The same problem with each point as one (a, b, rho) block (inverse_depth_point_factor.hpp) and the points
// eliminated first: both parameterisations describe the same points, so they must reach the same optimum; and
// only the one-block form lets the Schur complement eliminate every point.
TEST(VisualInertialBundleAdjustment, OneBlockPointsReachTheSameOptimumAndAreAllEliminated) {
  test::ViScenarioOptions options = scenarioOptions(8, 300);
  options.pixel_sigma = 0.5;
  const test::ViScenario scenario = test::makeViScenario(options);
  test::ViBaState start = test::trueViBaState(scenario);
  test::perturbViBaState(start, 0.1, 2.0 * M_PI / 180.0, 5);
  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::SPARSE_SCHUR;
  solver_options.max_num_iterations = 100;
  solver_options.function_tolerance = 1e-14;
  solver_options.gradient_tolerance = 1e-16;
  solver_options.parameter_tolerance = 1e-14;

  test::ViBaState two = start;
  ceres::Problem two_problem;
  test::addViBaFactors(scenario, two, two_problem);
  two_problem.SetParameterBlockConstant(two.poses[0].data());
  ceres::Solver::Summary two_summary;
  ceres::Solve(solver_options, &two_problem, &two_summary);
  ASSERT_TRUE(two_summary.IsSolutionUsable()) << two_summary.FullReport();

  test::ViBaState one = start;
  std::vector<Vector3d> points = test::inverseDepthPoints(one);
  ceres::Problem one_problem;
  solver_options.linear_solver_ordering = test::addViBaFactorsWithPointBlocks(scenario, one, points, one_problem);
  one_problem.SetParameterBlockConstant(one.poses[0].data());
  ceres::Solver::Summary one_summary;
  ceres::Solve(solver_options, &one_problem, &one_summary);
  ASSERT_TRUE(one_summary.IsSolutionUsable()) << one_summary.FullReport();
  std::printf(
      "two blocks per point: cost %.6e in %d iterations, eliminated %d of %zu point blocks; one block: "
      "cost %.6e in %d iterations, eliminated %d of %zu\n",
      two_summary.final_cost, static_cast<int>(two_summary.iterations.size()) - 1,
      two_summary.linear_solver_ordering_used.front(), 2 * points.size(), one_summary.final_cost,
      static_cast<int>(one_summary.iterations.size()) - 1, one_summary.linear_solver_ordering_used.front(),
      points.size());

  EXPECT_EQ(one_summary.linear_solver_ordering_used.front(), static_cast<int>(points.size()));
  EXPECT_LT(two_summary.linear_solver_ordering_used.front(), 2 * static_cast<int>(points.size()));
  EXPECT_NEAR(one_summary.final_cost, two_summary.final_cost, 1e-8 * two_summary.final_cost);
  for (std::size_t i = 0; i < one.poses.size(); ++i) {
    const SE3d T_one = poseFromBlock(one.poses[i].data());
    const SE3d T_two = poseFromBlock(two.poses[i].data());
    EXPECT_LT((T_one.translation() - T_two.translation()).norm(), 1e-6) << "keyframe " << i;
    EXPECT_LT((T_two.so3().inverse() * T_one.so3()).log().norm(), 1e-7) << "keyframe " << i;
  }
  for (std::size_t j = 0; j < points.size(); ++j) {
    const Vector3d X_two = two.bearings[j].normalized() / two.inverse_depths[j];
    EXPECT_LT((inverseDepthPointInCamera(points[j]) - X_two).norm(), 1e-6 * X_two.norm()) << "point " << j;
  }
}

// J^T J at the truth, with nothing fixed but the calibrated extrinsics: its null space must be the four
// unobservable directions of visual-inertial estimation (global position and yaw), and nothing else.
TEST(VisualInertialBundleAdjustment, InformationMatrixHasAFourDimensionalGaugeFreedom) {
  const test::ViScenario scenario = test::makeViScenario(scenarioOptions(6, 80));
  test::ViBaState state = test::trueViBaState(scenario);
  ceres::Problem problem;
  test::addViBaFactors(scenario, state, problem);

  // Columns in this order, each block in its tangent space: per keyframe pose(6) velocity(3) bias(6); then per
  // point bearing(2) inverse depth(1).
  ceres::Problem::EvaluateOptions evaluate_options;
  for (std::size_t i = 0; i < state.poses.size(); ++i) {
    evaluate_options.parameter_blocks.push_back(state.poses[i].data());
    evaluate_options.parameter_blocks.push_back(state.velocities[i].data());
    evaluate_options.parameter_blocks.push_back(state.biases[i].data());
  }
  for (std::size_t j = 0; j < state.bearings.size(); ++j) {
    evaluate_options.parameter_blocks.push_back(state.bearings[j].data());
    evaluate_options.parameter_blocks.push_back(&state.inverse_depths[j]);
  }
  ceres::CRSMatrix crs;
  ASSERT_TRUE(problem.Evaluate(evaluate_options, nullptr, nullptr, nullptr, &crs));
  Eigen::MatrixXd J = Eigen::MatrixXd::Zero(crs.num_rows, crs.num_cols);
  for (int r = 0; r < crs.num_rows; ++r) {
    for (int k = crs.rows[static_cast<std::size_t>(r)]; k < crs.rows[static_cast<std::size_t>(r) + 1]; ++k) {
      J(r, crs.cols[static_cast<std::size_t>(k)]) = crs.values[static_cast<std::size_t>(k)];
    }
  }
  const int keyframe_columns = 15 * static_cast<int>(state.poses.size());
  ASSERT_EQ(crs.num_cols, keyframe_columns + 3 * static_cast<int>(state.bearings.size()));

  const Eigen::MatrixXd H = J.transpose() * J;
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(H);
  const Eigen::VectorXd& lambda = eigen.eigenvalues();  // ascending
  const double largest = lambda(lambda.size() - 1);
  std::printf("information matrix %dx%d: smallest eigenvalues / largest:", crs.num_cols, crs.num_cols);
  for (int k = 0; k < 6; ++k) std::printf(" %.1e", lambda(k) / largest);
  std::printf("\n");
  // Numerically zero is ~100 eps relative to the largest eigenvalue; the weakest observable direction of
  // this 2.5 s window sits about three orders of magnitude above that.
  constexpr double kNumericalZero = 1e-14;
  for (int k = 0; k < 4; ++k) EXPECT_LT(std::abs(lambda(k)) / largest, kNumericalZero) << "eigenvalue " << k;
  EXPECT_GT(lambda(4) / largest, 100.0 * kNumericalZero) << "a fifth unobservable direction";

  // The null space is spanned by global translation and yaw about gravity (world z): shifting or turning
  // the whole world changes no residual. Points live in their reference keyframes and do not move.
  const auto gauge_direction = [&](const Vector3d& translation, double yaw) {
    Eigen::VectorXd delta = Eigen::VectorXd::Zero(crs.num_cols);
    const Vector3d axis_w = Vector3d::UnitZ();
    for (std::size_t i = 0; i < state.poses.size(); ++i) {
      const SE3d T = poseFromBlock(state.poses[i].data());
      const int c = 15 * static_cast<int>(i);
      delta.segment<3>(c) = translation + yaw * axis_w.cross(T.translation());
      delta.segment<3>(c + 3) = yaw * (T.so3().inverse() * axis_w);
      delta.segment<3>(c + 6) = yaw * axis_w.cross(state.velocities[i]);
    }
    return delta;
  };
  for (const Eigen::VectorXd& null_direction :
       {gauge_direction(Vector3d::UnitX(), 0.0), gauge_direction(Vector3d::UnitY(), 0.0),
        gauge_direction(Vector3d::UnitZ(), 0.0), gauge_direction(Vector3d::Zero(), 1.0)}) {
    EXPECT_LT((J * null_direction).norm(), 1e-6 * null_direction.norm());
  }
  // Roll is observable: gravity fixes it.
  Eigen::VectorXd roll = Eigen::VectorXd::Zero(crs.num_cols);
  for (std::size_t i = 0; i < state.poses.size(); ++i) {
    const SE3d T = poseFromBlock(state.poses[i].data());
    const int c = 15 * static_cast<int>(i);
    roll.segment<3>(c) = Vector3d::UnitX().cross(T.translation());
    roll.segment<3>(c + 3) = T.so3().inverse() * Vector3d::UnitX();
    roll.segment<3>(c + 6) = Vector3d::UnitX().cross(state.velocities[i]);
  }
  EXPECT_GT((J * roll).norm(), 1.0);
}

}  // namespace
}  // namespace cvislam::factors
