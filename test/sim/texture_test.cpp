// Textures: deterministic from their seed, high contrast at fine and coarse scales, and not periodic (a patch
// matches nowhere else, so place recognition is not fooled by repeats).
#include "test/sim/texture.hpp"

#include <cmath>
#include <vector>

#include <gtest/gtest.h>

namespace cvislam::sim {
namespace {

constexpr double kWidthM = 4.0;
constexpr double kHeightM = 3.0;

std::vector<double> patch(const Texture& t, int x0, int y0, int size) {
  std::vector<double> out;
  out.reserve(static_cast<std::size_t>(size) * static_cast<std::size_t>(size));
  for (int y = y0; y < y0 + size; ++y) {
    for (int x = x0; x < x0 + size; ++x) out.push_back(t.texel(x, y));
  }
  return out;
}

double normalizedCrossCorrelation(const std::vector<double>& a, const std::vector<double>& b) {
  double ma = 0.0, mb = 0.0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    ma += a[i];
    mb += b[i];
  }
  ma /= static_cast<double>(a.size());
  mb /= static_cast<double>(b.size());
  double ab = 0.0, aa = 0.0, bb = 0.0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    ab += (a[i] - ma) * (b[i] - mb);
    aa += (a[i] - ma) * (a[i] - ma);
    bb += (b[i] - mb) * (b[i] - mb);
  }
  return ab / std::sqrt(aa * bb);
}

double standardDeviation(const std::vector<double>& v) {
  double m = 0.0, s = 0.0;
  for (double x : v) m += x;
  m /= static_cast<double>(v.size());
  for (double x : v) s += (x - m) * (x - m);
  return std::sqrt(s / static_cast<double>(v.size()));
}

TEST(Texture, SameSeedGivesTheSameTexelsAndAnotherSeedDoesNot) {
  const Texture a(kWidthM, kHeightM, 5, TextureOptions{});
  const Texture b(kWidthM, kHeightM, 5, TextureOptions{});
  const Texture c(kWidthM, kHeightM, 6, TextureOptions{});
  EXPECT_EQ(patch(a, 0, 0, 300), patch(b, 0, 0, 300));
  EXPECT_LT(std::abs(normalizedCrossCorrelation(patch(a, 0, 0, 300), patch(c, 0, 0, 300))), 0.1);
}

TEST(Texture, HasHighContrastAtFineAndCoarseScales) {
  const Texture sut(kWidthM, kHeightM, 9, TextureOptions{});
  EXPECT_GT(standardDeviation(patch(sut, 0, 0, 300)), 50.0);  // 1 cm texels
  std::vector<double> coarse;                                 // seen through 8 cm pixels (mip level 3)
  for (double v = 0.0; v < kHeightM; v += 0.08) {
    for (double u = 0.0; u < kWidthM; u += 0.08) coarse.push_back(static_cast<double>(sut.sample(u, v, 0.08)));
  }
  EXPECT_GT(standardDeviation(coarse), 25.0);
}

TEST(Texture, APatchMatchesNowhereElse) {
  const Texture sut(kWidthM, kHeightM, 13, TextureOptions{});
  constexpr int kPatch = 48;  // 48 cm
  const std::vector<double> reference = patch(sut, 100, 80, kPatch);
  double best = -1.0;
  for (int y = 0; y + kPatch < sut.height(); y += 5) {
    for (int x = 0; x + kPatch < sut.width(); x += 5) {
      if (std::abs(x - 100) < 10 && std::abs(y - 80) < 10) continue;  // the patch itself and its immediate shifts
      best = std::max(best, normalizedCrossCorrelation(reference, patch(sut, x, y, kPatch)));
    }
  }
  EXPECT_LT(best, 0.5);
  RecordProperty("best_ncc_elsewhere", std::to_string(best));
}

}  // namespace
}  // namespace cvislam::sim
