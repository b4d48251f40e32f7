// The ORB pyramid's row filters (common/features/pyramid_filters.hpp): the 16-lane (AVX2) and 8-lane forms against
// a plain per-pixel reference, on random images whose widths leave every remainder of both lane counts, so that
// the vector bodies, their scalar tails and the replicated borders are all compared.
#include "common/features/pyramid_filters.hpp"

#include <algorithm>
#include <cstdint>
#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace cvislam::features::detail {
namespace {

std::vector<std::uint8_t> randomImage(int width, int height, std::mt19937& rng) {
  std::uniform_int_distribution<int> value(0, 255);
  std::vector<std::uint8_t> image(static_cast<std::size_t>(width) * static_cast<std::size_t>(height));
  for (std::uint8_t& p : image) p = static_cast<std::uint8_t>(value(rng));
  return image;
}

// One 7-tap pass at `centre` along an axis of `length` pixels, borders replicated, rounded to 8 bits of range;
// `at(i)` reads pixel i of the axis.
template <typename At>
unsigned blurTaps(int centre, int length, At at) {
  unsigned acc = 0;
  for (int i = 0; i < 7; ++i) {
    acc += at(std::clamp(centre + i - kBlurRadius, 0, length - 1)) * kBlurWeights[static_cast<std::size_t>(i)];
  }
  return (acc + 128) >> 8;
}

// The blur pixel by pixel: vertical pass, then horizontal.
std::vector<std::uint8_t> referenceBlur(const std::vector<std::uint8_t>& img, int w, int h) {
  const auto at = [w](int x, int y) { return static_cast<std::size_t>(y * w + x); };
  std::vector<std::uint16_t> vertical(img.size());
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x)
      vertical[at(x, y)] = static_cast<std::uint16_t>(blurTaps(y, h, [&](int yy) { return img[at(x, yy)]; }));
  }
  std::vector<std::uint8_t> out(img.size());
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x)
      out[at(x, y)] = static_cast<std::uint8_t>(blurTaps(x, w, [&](int xx) { return vertical[at(xx, y)]; }));
  }
  return out;
}

TEST(PyramidFilters, BothBlursGiveTheReferencePixelsForEveryWidth) {
  std::mt19937 rng(17);
  for (int w = 1; w <= 70; ++w) {
    const int h = 1 + w % 9;
    const std::vector<std::uint8_t> img = randomImage(w, h, rng);
    const std::vector<std::uint8_t> expected = referenceBlur(img, w, h);
    std::vector<std::uint16_t> scratch(static_cast<std::size_t>(w) + 16);
    for (const bool wide : {false, true}) {
      std::vector<std::uint8_t> out(img.size(), 0);
      (wide ? blurRowsWide : blurRowsNarrow)(img.data(), w, h, 0, h, out.data(), scratch.data());
      ASSERT_EQ(out, expected) << (wide ? "wide" : "narrow") << ", " << w << " x " << h;
    }
  }
}

TEST(PyramidFilters, ABlurOfSomeRowsWritesThoseRowsOnly) {
  std::mt19937 rng(18);
  constexpr int kW = 53;
  constexpr int kH = 20;
  const std::vector<std::uint8_t> img = randomImage(kW, kH, rng);
  const std::vector<std::uint8_t> expected = referenceBlur(img, kW, kH);
  std::vector<std::uint16_t> scratch(kW + 16);
  std::vector<std::uint8_t> out(img.size(), 7);
  blurRowsWide(img.data(), kW, kH, -4, 5, out.data(), scratch.data());   // clipped to rows 0..4
  blurRowsWide(img.data(), kW, kH, 17, 30, out.data(), scratch.data());  // rows 17..19
  for (int y = 0; y < kH; ++y) {
    for (int x = 0; x < kW; ++x) {
      const auto i = static_cast<std::size_t>(y * kW + x);
      EXPECT_EQ(out[i], (y < 5 || y >= 17) ? expected[i] : 7) << x << ", " << y;
    }
  }
}

TEST(PyramidFilters, BothBlendsGiveTheWeightedSumForEveryWidth) {
  std::mt19937 rng(19);
  for (int w = 1; w <= 70; ++w) {
    const std::vector<std::uint8_t> upper = randomImage(w, 1, rng);
    const std::vector<std::uint8_t> lower = randomImage(w, 1, rng);
    for (const std::uint16_t lower_weight : {0, 1, 77, 128, 255, 256}) {
      const auto upper_weight = static_cast<std::uint16_t>(256 - lower_weight);
      for (const bool wide : {false, true}) {
        std::vector<std::uint16_t> out(static_cast<std::size_t>(w), 0);
        (wide ? blendRowsWide : blendRowsNarrow)(upper.data(), lower.data(), upper_weight, lower_weight, w, out.data());
        for (int x = 0; x < w; ++x) {
          const auto i = static_cast<std::size_t>(x);
          ASSERT_EQ(out[i], upper[i] * upper_weight + lower[i] * lower_weight)
              << (wide ? "wide" : "narrow") << ", width " << w << ", x " << x << ", lower weight " << lower_weight;
        }
      }
    }
  }
}

// Downsampling taps as the pyramid makes them: source index and weight of the right neighbour of each pixel.
TEST(PyramidFilters, BothResamplesGiveTheBilinearPixelsForEveryWidth) {
  std::mt19937 rng(20);
  std::uniform_int_distribution<int> value(0, 255 * 256);
  std::uniform_int_distribution<int> weight(0, 256);
  for (int width = 1; width <= 70; ++width) {
    const int source = width + width / 5 + 1;
    std::vector<std::uint16_t> row(static_cast<std::size_t>(source));
    for (std::uint16_t& v : row) v = static_cast<std::uint16_t>(value(rng));
    std::vector<std::int32_t> index(static_cast<std::size_t>(width));
    std::vector<std::int32_t> weights(static_cast<std::size_t>(width));
    for (int x = 0; x < width; ++x) {
      index[static_cast<std::size_t>(x)] = std::min(x + x / 5, source - 2);
      weights[static_cast<std::size_t>(x)] = weight(rng);
    }
    for (const bool wide : {false, true}) {
      std::vector<std::uint8_t> out(static_cast<std::size_t>(width), 0);
      (wide ? resampleRowWide : resampleRowNarrow)(row.data(), index.data(), weights.data(), 1, width, out.data());
      for (int x = 0; x < width; ++x) {
        const auto i = static_cast<std::size_t>(x);
        const auto s = static_cast<std::size_t>(index[i]);
        const auto w = static_cast<std::uint32_t>(weights[i]);
        const std::uint32_t expected = (row[s] * (256U - w) + row[s + 1] * w + 32768U) >> 16U;
        ASSERT_EQ(out[i], expected) << (wide ? "wide" : "narrow") << ", width " << width << ", x " << x;
      }
    }
  }
  // A one-pixel source row: step 0, both taps the same pixel.
  const std::vector<std::uint16_t> one = {40000};
  const std::vector<std::int32_t> zeros(9, 0);
  const std::vector<std::int32_t> weights = {0, 1, 2, 50, 128, 200, 255, 256, 3};
  for (const bool wide : {false, true}) {
    std::vector<std::uint8_t> out(9, 0);
    (wide ? resampleRowWide : resampleRowNarrow)(one.data(), zeros.data(), weights.data(), 0, 9, out.data());
    for (const std::uint8_t p : out) EXPECT_EQ(p, (40000U * 256U + 32768U) >> 16U) << (wide ? "wide" : "narrow");
  }
}

}  // namespace
}  // namespace cvislam::features::detail
