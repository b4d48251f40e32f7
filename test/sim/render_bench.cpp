// Frames rendered per second on one core at EuRoC cam0 resolution (752 x 480), along the loop preset.
// Run: taskset -c 1 build/default/bin/sim_render_bench   (p50 and p99 over 20 repetitions of 0.5 s)
#include <benchmark/benchmark.h>

#include "common/camera/camera_model.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "test/bench/percentiles.hpp"
#include "test/sim/presets.hpp"
#include "test/sim/renderer.hpp"

namespace cvislam::sim {
namespace {

void renderFrames(benchmark::State& state, const char* preset) {
  MissionPlanOptions options;
  options.preset = preset;
  options.seed = 1;
  options.duration_s = 30.0;
  auto plan = planMission(options);
  if (!plan) {
    state.SkipWithError(plan.error().toString().c_str());
    return;
  }
  WorldOptions world_options;
  world_options.seed = options.seed;
  const World world(plan->layout, world_options);
  const Renderer renderer(camera::CameraModel::create(dataset::eurocCam0()).value());
  const geometry::SE3d T_b_c = renderer.camera().calibration().T_b_c;
  dataset::GrayImage image;
  double t = 0.0;
  for (auto _ : state) {
    renderer.render(world, plan->agents[0].trajectory.state(t).T_w_b * T_b_c, 1.0, image);
    benchmark::DoNotOptimize(image.pixels.data());
    t += 0.05;
    if (t > options.duration_s) t = 0.0;
  }
  state.counters["frames_per_s"] =
      benchmark::Counter(static_cast<double>(state.iterations()), benchmark::Counter::kIsRate);
}

void renderLoop752x480(benchmark::State& state) {
  renderFrames(state, "loop");
}
void renderAggressive752x480(benchmark::State& state) {
  renderFrames(state, "aggressive");
}
BENCHMARK(renderLoop752x480)->Unit(benchmark::kMillisecond)->MinTime(0.5)->Apply([](auto* b) {
  bench::withPercentiles(b, 20);
});
BENCHMARK(renderAggressive752x480)->Unit(benchmark::kMillisecond)->MinTime(0.5)->Apply([](auto* b) {
  bench::withPercentiles(b, 20);
});

}  // namespace
}  // namespace cvislam::sim
