// Preintegration, every factor's Evaluate with Jacobians, and one local visual-inertial BA of 10 keyframes
// and 1000 points, each reported as p50 and p99 over repetitions.
//
//   build/default/bin/bench_factors --benchmark_out=factors.json --benchmark_out_format=json
#include <algorithm>
#include <vector>

#include <benchmark/benchmark.h>
#include <ceres/ceres.h>

#include "common/factors/imu_factor.hpp"
#include "common/factors/inverse_depth_point_factor.hpp"
#include "common/factors/prior_factor.hpp"
#include "common/factors/reprojection_factor.hpp"
#include "test/bench/percentiles.hpp"
#include "test/support/cost_evaluation.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam {
namespace {

void withPercentiles(benchmark::internal::Benchmark* b, int repetitions) {
  bench::withPercentiles(b, repetitions);
  b->Unit(benchmark::kMicrosecond);
}

const test::ViScenario& scenario() {
  static const test::ViScenario s = [] {
    test::ViScenarioOptions options;
    options.imu_rate_hz = 200.0;
    options.keyframes = 10;
    options.points = 1000;
    options.bias.gyro = Eigen::Vector3d(0.004, -0.003, 0.002);
    options.bias.accel = Eigen::Vector3d(0.03, -0.02, 0.04);
    options.pixel_sigma = 0.5;
    return test::makeViScenario(options);
  }();
  return s;
}

void BM_Preintegrate(benchmark::State& state) {
  const auto samples = static_cast<std::size_t>(state.range(0));
  const auto& imu = scenario().imu;
  imu::Preintegration pre(imu::ImuBias{}, scenario().noise);
  for (auto _ : state) {
    pre.reset(imu::ImuBias{});
    for (std::size_t k = 0; k < samples; ++k) pre.integrate(0.005, imu[k].gyro_s, imu[k].accel_s);
    benchmark::DoNotOptimize(pre.covariance().data());
  }
  state.SetItemsProcessed(static_cast<std::int64_t>(samples) * state.iterations());
}
BENCHMARK(BM_Preintegrate)->Arg(10)->Arg(200)->Apply([](auto* b) { withPercentiles(b, 20); });

// Evaluates `cost` with all Jacobians on `blocks`.
void evaluateLoop(benchmark::State& state, const ceres::CostFunction& cost, std::vector<const double*> blocks) {
  test::CostEvaluation evaluation(cost, std::move(blocks));
  for (auto _ : state) {
    const bool ok = evaluation.evaluate();
    benchmark::DoNotOptimize(ok);
    benchmark::DoNotOptimize(evaluation.firstJacobian());
  }
}

void BM_ImuFactorEvaluate(benchmark::State& state) {
  const test::ViScenario& s = scenario();
  test::ViBaState truth = test::trueViBaState(s);
  const factors::ImuFactor cost(s.preintegrations[3]);
  evaluateLoop(state, cost,
               {truth.poses[3].data(), truth.velocities[3].data(), truth.biases[3].data(), truth.poses[4].data(),
                truth.velocities[4].data()});
}
BENCHMARK(BM_ImuFactorEvaluate)->Apply([](auto* b) { withPercentiles(b, 20); });

void BM_BiasRandomWalkFactorEvaluate(benchmark::State& state) {
  test::ViBaState truth = test::trueViBaState(scenario());
  const factors::BiasRandomWalkFactor cost(scenario().noise, 0.5);
  evaluateLoop(state, cost, {truth.biases[3].data(), truth.biases[4].data()});
}
BENCHMARK(BM_BiasRandomWalkFactorEvaluate)->Apply([](auto* b) { withPercentiles(b, 20); });

void BM_ReprojectionFactorEvaluate(benchmark::State& state) {
  const test::ViScenario& s = scenario();
  test::ViBaState truth = test::trueViBaState(s);
  const auto& o = *std::find_if(s.observations.begin(), s.observations.end(), [&](const test::ViObservation& x) {
    return x.keyframe != s.points[static_cast<std::size_t>(x.point)].reference_keyframe;
  });
  const auto j = static_cast<std::size_t>(o.point);
  const factors::ReprojectionFactor cost(o.keypoint_px, s.intrinsics, 1.0);
  evaluateLoop(state, cost,
               {truth.poses[static_cast<std::size_t>(o.keyframe)].data(),
                truth.poses[static_cast<std::size_t>(s.points[j].reference_keyframe)].data(), truth.extrinsics.data(),
                truth.bearings[j].data(), &truth.inverse_depths[j]});
}
BENCHMARK(BM_ReprojectionFactorEvaluate)->Apply([](auto* b) { withPercentiles(b, 20); });

void BM_InverseDepthPointFactorEvaluate(benchmark::State& state) {
  const test::ViScenario& s = scenario();
  test::ViBaState truth = test::trueViBaState(s);
  std::vector<Eigen::Vector3d> points = test::inverseDepthPoints(truth);
  const auto& o = *std::find_if(s.observations.begin(), s.observations.end(), [&](const test::ViObservation& x) {
    return x.keyframe != s.points[static_cast<std::size_t>(x.point)].reference_keyframe;
  });
  const auto j = static_cast<std::size_t>(o.point);
  const factors::InverseDepthPointFactor cost(o.keypoint_px, s.intrinsics, 1.0);
  evaluateLoop(state, cost,
               {truth.poses[static_cast<std::size_t>(o.keyframe)].data(),
                truth.poses[static_cast<std::size_t>(s.points[j].reference_keyframe)].data(), truth.extrinsics.data(),
                points[j].data()});
}
BENCHMARK(BM_InverseDepthPointFactorEvaluate)->Apply([](auto* b) { withPercentiles(b, 20); });

void BM_PosePriorFactorEvaluate(benchmark::State& state) {
  test::ViBaState truth = test::trueViBaState(scenario());
  const factors::PosePriorFactor cost(factors::poseFromBlock(truth.poses[2].data()),
                                      Eigen::Matrix<double, 6, 6>::Identity() * 100.0);
  evaluateLoop(state, cost, {truth.poses[3].data()});
}
BENCHMARK(BM_PosePriorFactorEvaluate)->Apply([](auto* b) { withPercentiles(b, 20); });

void BM_BearingPriorFactorEvaluate(benchmark::State& state) {
  test::ViBaState truth = test::trueViBaState(scenario());
  const factors::BearingPriorFactor cost(truth.bearings[0], Eigen::Matrix2d::Identity() * 100.0);
  evaluateLoop(state, cost, {truth.bearings[1].data()});
}
BENCHMARK(BM_BearingPriorFactorEvaluate)->Apply([](auto* b) { withPercentiles(b, 20); });

// One local BA as the agent's mapping thread would run it: 10 keyframes (poses, velocities, biases) and 1000
// points, 0.5 px noise, a perturbed start, the first keyframe fixed, single-threaded SPARSE_SCHUR, at most
// 10 iterations; the problem is built outside the timing. Two ways to hold a point:
//   TwoBlockPoints  bearing (unit-sphere manifold) + inverse depth, the ReprojectionFactor family. Two blocks
//                   per point cannot both be Schur-eliminated: Ceres picks an independent set itself, and the
//                   blocks it leaves over stay in the reduced system.
//   OneBlockPoints  the inverse-depth point (a, b, rho), the InverseDepthPointFactor family, with the ordering
//                   points first: every point is eliminated, the reduced system holds the keyframes only.
// Both start from the same perturbed state. final_cost counts as a check that they solve the same problem.
template <bool kOneBlockPoints>
void localBundleAdjustment(benchmark::State& state) {
  const test::ViScenario& s = scenario();
  std::int64_t iterations_total = 0;
  double final_cost_total = 0.0;
  for (auto _ : state) {
    state.PauseTiming();
    test::ViBaState ba_state = test::trueViBaState(s);
    test::perturbViBaState(ba_state, 0.05, 0.01, 5);
    std::vector<Eigen::Vector3d> points = test::inverseDepthPoints(ba_state);
    ceres::Problem problem;
    ceres::Solver::Options options;
    if (kOneBlockPoints) {
      options.linear_solver_ordering = test::addViBaFactorsWithPointBlocks(s, ba_state, points, problem);
    } else {
      test::addViBaFactors(s, ba_state, problem);
    }
    problem.SetParameterBlockConstant(ba_state.poses[0].data());
    options.linear_solver_type = ceres::SPARSE_SCHUR;
    options.max_num_iterations = 10;
    options.num_threads = 1;
    ceres::Solver::Summary summary;
    state.ResumeTiming();
    ceres::Solve(options, &problem, &summary);
    iterations_total += static_cast<std::int64_t>(summary.iterations.size()) - 1;
    final_cost_total += summary.final_cost;
  }
  state.counters["solver_iterations"] =
      benchmark::Counter(static_cast<double>(iterations_total), benchmark::Counter::kAvgIterations);
  state.counters["final_cost"] = benchmark::Counter(final_cost_total, benchmark::Counter::kAvgIterations);
  state.counters["observations"] = static_cast<double>(s.observations.size());
}

void BM_LocalBundleAdjustment10Keyframes1000Points_TwoBlockPoints(benchmark::State& state) {
  localBundleAdjustment<false>(state);
}
void BM_LocalBundleAdjustment10Keyframes1000Points_OneBlockPoints(benchmark::State& state) {
  localBundleAdjustment<true>(state);
}
BENCHMARK(BM_LocalBundleAdjustment10Keyframes1000Points_TwoBlockPoints)->Iterations(1)->Apply([](auto* b) {
  withPercentiles(b, 30);
  b->Unit(benchmark::kMillisecond);
});
BENCHMARK(BM_LocalBundleAdjustment10Keyframes1000Points_OneBlockPoints)->Iterations(1)->Apply([](auto* b) {
  withPercentiles(b, 30);
  b->Unit(benchmark::kMillisecond);
});

}  // namespace
}  // namespace cvislam

BENCHMARK_MAIN();
