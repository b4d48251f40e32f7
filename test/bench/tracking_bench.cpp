// Motion-only pose optimisation of one frame: ~260 observations of the synthetic scene, 0.5 px noise, 20 %
// wrong matches, a start 5 cm and 2 deg off. p50/p99 over repetitions.
//
//   taskset -c 0 build/default/bin/bench_tracking
#include <random>
#include <vector>

#include <benchmark/benchmark.h>

#include "agent_rt/tracking/pose_optimizer.hpp"
#include "test/bench/percentiles.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam {
namespace {

void BM_OptimizePose(benchmark::State& state) {
  test::ViScenarioOptions options;
  options.pixel_sigma = 0.5;
  const test::ViScenario s = test::makeViScenario(options);
  std::vector<agent::PoseObservation> observations;
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (const test::ViObservation& o : s.observations) {
    if (o.keyframe != 3) continue;
    agent::PoseObservation p{s.points[static_cast<std::size_t>(o.point)].p_w, o.keypoint_px, 0.5};
    if (unit(rng) < 0.2) p.keypoint_px = Eigen::Vector2d(752.0 * unit(rng), 480.0 * unit(rng));
    observations.push_back(p);
  }
  const geometry::SE3d& truth = s.keyframe_states[3].T_w_s;
  const geometry::SE3d initial(truth.so3() * geometry::SO3d::exp(Eigen::Vector3d(0.02, -0.02, 0.015)),
                               truth.translation() + Eigen::Vector3d(0.03, -0.03, 0.02));
  std::vector<std::uint8_t> outlier(observations.size());
  const agent::PoseOptimizerOptions optimizer_options;
  for (auto _ : state) {
    auto result = agent::optimizePose(observations, initial, s.T_s_c, s.intrinsics, optimizer_options, outlier);
    benchmark::DoNotOptimize(result);
  }
  state.counters["observations"] = static_cast<double>(observations.size());
}
BENCHMARK(BM_OptimizePose)->Unit(benchmark::kMicrosecond)->Apply([](auto* b) { bench::withPercentiles(b, 20); });

}  // namespace
}  // namespace cvislam

BENCHMARK_MAIN();
