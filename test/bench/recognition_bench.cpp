// Place recognition costs, p50/p99 over repetitions:
// - BM_DatabaseQuery/N: one BoW query (map-matching scope: three quarters of the database) against a database of
//   N keyframes, N up to 10,000. The keyframes are the BoW vectors of the real EuRoC V1_01 excerpt's frames
//   (cam0 and cam1, 190), repeated with new ids: the same few places seen again and again, so posting lists are
//   as long as a mission that keeps revisiting gives. Counter bytes_per_keyframe: the database's memory.
// - BM_Transform: BoW and direct-index vectors of one keyframe (500 descriptors).
// - BM_VerifyCandidate: the verification of one true candidate (matching, RANSAC, refinement, guided search) on
//   simulated views (the loop preset's world, seed 1).
//
//   taskset -c 1 build/default/bin/bench_recognition --benchmark_out=recognition.json
#include <memory>
#include <vector>

#include <benchmark/benchmark.h>

#include "common/dataset/euroc.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "common/features/orb.hpp"
#include "common/features/vocabulary.hpp"
#include "common/geometry/alignment.hpp"
#include "server_cloud/recognition/keyframe_database.hpp"
#include "server_cloud/recognition/place_recognition.hpp"
#include "test/bench/percentiles.hpp"
#include "test/server_cloud/recognition/synthetic_keyframes.hpp"
#include "test/sim/presets.hpp"
#include "test/support/test_data.hpp"

namespace cvislam {
namespace {

namespace rec = server::recognition;

const features::Vocabulary* vocabulary() {
  static const std::unique_ptr<features::Vocabulary> v = [] {
    auto loaded = features::Vocabulary::load(CVISLAM_VOCABULARY_FILE);
    return loaded ? std::make_unique<features::Vocabulary>(std::move(loaded).value()) : nullptr;
  }();
  return v.get();
}

struct RealKeyframes {
  std::vector<std::vector<features::Descriptor>> descriptors;
  std::vector<features::BowVector> bow;
  std::vector<features::FeatureVector> features;
};

const RealKeyframes& realKeyframes() {
  static const RealKeyframes k = [] {
    RealKeyframes out;
    const auto path = test::findData("euroc-v101-excerpt");
    if (path.empty() || vocabulary() == nullptr) return out;
    auto seq = dataset::EurocSequence::open(path);
    if (!seq.ok()) return out;
    auto extractor = features::OrbExtractor::create({});
    std::vector<features::Keypoint> keypoints(500);
    std::vector<features::Descriptor> descriptors(500);
    for (std::size_t i = 0; i < seq->rigFrames().size(); ++i) {
      for (int cam = 0; cam < 2; ++cam) {
        auto image = seq->loadImage(cam, i);
        if (!image.ok()) continue;
        const int n = extractor->extract(image->pixels, image->width, image->height, keypoints, descriptors);
        out.descriptors.emplace_back(descriptors.begin(), descriptors.begin() + n);
        features::BowVector bow;
        features::FeatureVector fv;
        vocabulary()->transform(out.descriptors.back(), bow, &fv, 2);
        out.bow.push_back(std::move(bow));
        out.features.push_back(std::move(fv));
      }
    }
    return out;
  }();
  return k;
}

void BM_DatabaseQuery(benchmark::State& state) {
  const RealKeyframes& real = realKeyframes();
  if (real.bow.empty()) {
    state.SkipWithError("needs the vocabulary and euroc-v101-excerpt (set CVISLAM_DATA_DIR)");
    return;
  }
  const auto n = static_cast<std::size_t>(state.range(0));
  rec::KeyframeDatabase db(vocabulary()->wordCount());
  for (std::size_t i = 0; i < n; ++i) {
    const std::size_t k = i % real.bow.size();
    (void)db.add(KeyframeId{static_cast<AgentId>(i % 4), static_cast<std::uint32_t>(i)},
                 static_cast<server::MapId>(i % 4), real.bow[k], real.features[k]);
  }
  rec::DatabaseQuery query;
  query.scope = rec::QueryScope::kOtherMaps;
  query.map = 0;
  std::size_t q = 0;
  std::size_t results = 0;
  for (auto _ : state) {
    const auto out = db.query(real.bow[(q++ * 37) % real.bow.size()], query);
    results += out.size();
    benchmark::DoNotOptimize(out.data());
  }
  state.counters["keyframes"] = static_cast<double>(n);
  state.counters["bytes_per_keyframe"] = static_cast<double>(db.memoryBytes()) / static_cast<double>(n);
  state.counters["results"] = benchmark::Counter(static_cast<double>(results), benchmark::Counter::kAvgIterations);
}
BENCHMARK(BM_DatabaseQuery)
    ->Arg(100)
    ->Arg(1000)
    ->Arg(3000)
    ->Arg(10000)
    ->Unit(benchmark::kMillisecond)
    ->Apply([](auto* b) { bench::withPercentiles(b, 10); });

void BM_Transform(benchmark::State& state) {
  const RealKeyframes& real = realKeyframes();
  if (real.bow.empty()) {
    state.SkipWithError("needs the vocabulary and euroc-v101-excerpt (set CVISLAM_DATA_DIR)");
    return;
  }
  features::BowVector bow;
  features::FeatureVector fv;
  std::size_t i = 0;
  for (auto _ : state) {
    vocabulary()->transform(real.descriptors[i++ % real.descriptors.size()], bow, &fv, 2);
    benchmark::DoNotOptimize(bow.data());
  }
}
BENCHMARK(BM_Transform)->Unit(benchmark::kMillisecond)->Apply([](auto* b) { bench::withPercentiles(b, 10); });

// Map B (agent 1) saw the place, in a frame 40 deg and a few metres off; map A's keyframe comes back to it.
struct VerificationScene {
  std::unique_ptr<sim::World> world;
  std::unique_ptr<server::MapContent> a = std::make_unique<server::MapContent>(0);
  std::unique_ptr<server::MapContent> b = std::make_unique<server::MapContent>(1);
  std::unique_ptr<rec::KeyframeDatabase> db;
  std::unique_ptr<rec::AgentCamera> camera;
  bool ok = false;
};

const VerificationScene& scene() {
  static const VerificationScene s = [] {
    VerificationScene out;
    if (vocabulary() == nullptr) return out;
    sim::MissionPlanOptions plan_options;
    plan_options.preset = "loop";
    plan_options.seed = 1;
    auto plan = sim::planMission(plan_options);
    if (!plan) return out;
    sim::WorldOptions world_options;
    world_options.seed = 1;
    out.world = std::make_unique<sim::World>(plan->layout, world_options);
    auto maker = test::ViewMaker::create(dataset::eurocCam0());
    if (!maker) return out;
    out.camera = std::make_unique<rec::AgentCamera>(rec::AgentCamera{maker->camera(), maker->T_s_c()});
    out.db = std::make_unique<rec::KeyframeDatabase>(vocabulary()->wordCount());
    const auto pose = [&](double t) { return plan->agents[0].trajectory.state(t).T_w_b; };
    const geometry::SE3d E_b_w(geometry::rotationAboutZ(0.7), Eigen::Vector3d(3.0, -2.0, 0.5));
    const auto build = [&](server::MapContent& map, AgentId agent, std::vector<geometry::SE3d> poses,
                           const geometry::SE3d& E) {
      test::SyntheticMap builder(map, *out.world, agent, {});
      for (const auto& T : poses) {
        auto id = builder.add(maker->render(*out.world, T), E);
        if (!id) return false;
        features::BowVector bow;
        features::FeatureVector fv;
        vocabulary()->transform(map.keyframe(*id)->descriptors, bow, &fv, rec::RecognitionOptions{}.direct_level);
        if (!out.db->add(*id, map.id(), std::move(bow), std::move(fv)).ok()) return false;
      }
      return true;
    };
    const geometry::SE3d side(geometry::SO3d(), Eigen::Vector3d(0.0, 0.3, 0.0));
    out.ok = build(*out.b, 1, {pose(14.0), pose(14.5), pose(15.0), pose(15.5)}, E_b_w) &&
             build(*out.a, 0, {pose(14.6) * side}, geometry::SE3d());
    return out;
  }();
  return s;
}

void BM_VerifyCandidate(benchmark::State& state) {
  const VerificationScene& s = scene();
  if (!s.ok) {
    state.SkipWithError("could not build the scene (is the vocabulary there?)");
    return;
  }
  const rec::CameraLookup cameras = [&](AgentId) { return s.camera.get(); };
  const rec::RecognitionOptions options;
  int inliers = 0;
  for (auto _ : state) {
    const rec::Verification v =
        rec::verifyCandidate(*s.db, *s.a, KeyframeId{0, 0}, *s.b, KeyframeId{1, 1}, 0.1, cameras, options);
    if (!v.accepted()) {
      state.SkipWithError(("the true candidate was rejected: " + v.detail).c_str());
      return;
    }
    inliers = v.match->inliers;
  }
  state.counters["inliers"] = inliers;
}
BENCHMARK(BM_VerifyCandidate)->Unit(benchmark::kMillisecond)->Apply([](auto* b) { bench::withPercentiles(b, 10); });

}  // namespace
}  // namespace cvislam

BENCHMARK_MAIN();
