// ORB extraction (500 features, 8x6 grid) and brute-force matching on real EuRoC V1_01 frames, p50/p99,
// with the heap allocations per frame (this binary counts operator new; extract must make none); and the
// frame loader's PNG decoding of those frames' files, OpenCV (libpng) against the agent's own decoder.
//
//   taskset -c 1 build/default/bin/bench_features
#include <utility>
#include <vector>

#include <benchmark/benchmark.h>

#include "common/dataset/euroc.hpp"
#include "common/dataset/image_codecs.hpp"
#include "common/dataset/png_gray.hpp"
#include "common/features/orb.hpp"
#include "test/bench/percentiles.hpp"
#include "test/support/allocation_counter.hpp"
#include "test/support/test_data.hpp"

namespace cvislam {
namespace {

std::vector<dataset::GrayImage> loadFrames() {
  std::vector<dataset::GrayImage> frames;
  const auto path = test::findData("euroc-v101-excerpt");
  if (path.empty()) return frames;
  auto seq = dataset::EurocSequence::open(path);
  if (!seq.ok()) return frames;
  for (std::size_t i = 0; i < seq->rigFrames().size(); i += 4) {
    auto image = seq->loadImage(0, i);
    if (image.ok()) frames.push_back(std::move(*image));
  }
  return frames;
}

const std::vector<dataset::GrayImage>& frames() {
  static const std::vector<dataset::GrayImage> f = loadFrames();
  return f;
}

void BM_OrbExtract500(benchmark::State& state) {
  if (frames().empty()) {
    state.SkipWithError("euroc-v101-excerpt not found (set CVISLAM_DATA_DIR)");
    return;
  }
  auto extractor = features::OrbExtractor::create({});
  std::vector<features::Keypoint> keypoints(500);
  std::vector<features::Descriptor> descriptors(500);
  std::size_t i = 0;
  long allocations = 0;
  for (auto _ : state) {
    const dataset::GrayImage& image = frames()[i++ % frames().size()];
    const long before = test::allocationCount();
    benchmark::DoNotOptimize(extractor->extract(image.pixels, image.width, image.height, keypoints, descriptors));
    allocations += test::allocationCount() - before;
  }
  state.counters["allocations_per_frame"] =
      benchmark::Counter(static_cast<double>(allocations), benchmark::Counter::kAvgIterations);
}
BENCHMARK(BM_OrbExtract500)->Unit(benchmark::kMillisecond)->Apply([](auto* b) { bench::withPercentiles(b, 20); });

void BM_MatchBruteForce500x500(benchmark::State& state) {
  if (frames().size() < 2) {
    state.SkipWithError("euroc-v101-excerpt not found (set CVISLAM_DATA_DIR)");
    return;
  }
  auto extractor = features::OrbExtractor::create({});
  std::vector<features::Keypoint> k0(500);
  std::vector<features::Keypoint> k1(500);
  std::vector<features::Descriptor> d0(500);
  std::vector<features::Descriptor> d1(500);
  const int n0 = extractor->extract(frames()[0].pixels, frames()[0].width, frames()[0].height, k0, d0);
  const int n1 = extractor->extract(frames()[1].pixels, frames()[1].width, frames()[1].height, k1, d1);
  std::vector<features::DescriptorMatch> matches(500);
  for (auto _ : state) {
    benchmark::DoNotOptimize(features::matchDescriptors(std::span(d0).first(static_cast<std::size_t>(n0)),
                                                        std::span(d1).first(static_cast<std::size_t>(n1)), {},
                                                        matches));
  }
}
BENCHMARK(BM_MatchBruteForce500x500)->Unit(benchmark::kMillisecond)->Apply([](auto* b) {
  bench::withPercentiles(b, 20);
});

// Decodes the excerpt's cam0 files in turn into one preallocated frame; `png` null = OpenCV.
void decodeFrames(benchmark::State& state, dataset::GrayPngDecoder* png) {
  const auto path = test::findData("euroc-v101-excerpt");
  auto seq = path.empty() ? Result<dataset::EurocSequence>(Error{ErrorCode::kNotFound, "no data"})
                          : dataset::EurocSequence::open(path);
  if (!seq.ok()) {
    state.SkipWithError("euroc-v101-excerpt not found (set CVISLAM_DATA_DIR)");
    return;
  }
  const auto& cal = seq->cam0().calibration;
  std::vector<std::uint8_t> pixels(static_cast<std::size_t>(cal.width) * static_cast<std::size_t>(cal.height));
  const std::size_t n = seq->cam0().frames.size();
  std::size_t i = 0;
  long allocations = 0;
  for (auto _ : state) {
    const long before = test::allocationCount();
    const std::size_t frame = i++ % n;
    Status st = Status::Ok();
    if (png != nullptr) {
      st = seq->loadImageInto(0, frame, pixels, *png);
    } else if (auto image = dataset::readImageAsGray(seq->cam0().imagePath(frame)); image.ok()) {
      pixels = std::move(image->pixels);  // OpenCV allocates its own image anyway
    } else {
      st = image.error();
    }
    allocations += test::allocationCount() - before;
    if (!st.ok()) {
      state.SkipWithError(st.error().message().c_str());
      return;
    }
    benchmark::DoNotOptimize(pixels.data());
  }
  state.counters["allocations_per_frame"] =
      benchmark::Counter(static_cast<double>(allocations), benchmark::Counter::kAvgIterations);
}

void BM_DecodePngOpenCv(benchmark::State& state) {
  decodeFrames(state, nullptr);
}
BENCHMARK(BM_DecodePngOpenCv)->Unit(benchmark::kMillisecond)->Apply([](auto* b) { bench::withPercentiles(b, 20); });

void BM_DecodePngOwn(benchmark::State& state) {
  dataset::GrayPngDecoder png;
  decodeFrames(state, &png);
}
BENCHMARK(BM_DecodePngOwn)->Unit(benchmark::kMillisecond)->Apply([](auto* b) { bench::withPercentiles(b, 20); });

}  // namespace
}  // namespace cvislam

BENCHMARK_MAIN();
