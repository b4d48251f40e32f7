#include "test/sim/texture.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <numbers>

#include "test/sim/random.hpp"

namespace cvislam::sim {

namespace {

// Value noise on an integer lattice: smooth, non-periodic, deterministic from the seed.
double latticeValue(std::int64_t ix, std::int64_t iy, std::uint64_t seed) {
  const std::uint64_t h =
      mix64(seed ^ mix64(static_cast<std::uint64_t>(ix) * 0x9E3779B97F4A7C15ULL + static_cast<std::uint64_t>(iy)));
  return static_cast<double>(h >> 11U) * 0x1.0p-53;
}

double valueNoise(double x, double y, std::uint64_t seed) {
  const double fx = std::floor(x), fy = std::floor(y);
  const auto ix = static_cast<std::int64_t>(fx), iy = static_cast<std::int64_t>(fy);
  double tx = x - fx, ty = y - fy;
  tx = tx * tx * (3.0 - 2.0 * tx);
  ty = ty * ty * (3.0 - 2.0 * ty);
  const double a = latticeValue(ix, iy, seed), b = latticeValue(ix + 1, iy, seed);
  const double c = latticeValue(ix, iy + 1, seed), d = latticeValue(ix + 1, iy + 1, seed);
  return (a + (b - a) * tx) * (1.0 - ty) + (c + (d - c) * tx) * ty;
}

}  // namespace

Texture::Texture(double width_m, double height_m, std::uint64_t seed, const TextureOptions& options)
    : texel_size_m_(options.texel_size_m), inv_texel_size_(static_cast<float>(1.0 / options.texel_size_m)) {
  const double tau = options.texel_size_m;
  Level base;
  base.width = std::max(2, static_cast<int>(std::ceil(width_m / tau)) + 1);
  base.height = std::max(2, static_cast<int>(std::ceil(height_m / tau)) + 1);
  base.inv_texel = inv_texel_size_;
  const auto w = static_cast<std::size_t>(base.width), h = static_cast<std::size_t>(base.height);

  // Background: three octaves of value noise (1 m, 0.3 m, 0.1 m), in [0, 1].
  std::vector<float> value(w * h);
  const std::uint64_t noise_seed = deriveSeed(seed, 1);
  for (std::size_t y = 0; y < h; ++y) {
    for (std::size_t x = 0; x < w; ++x) {
      const double u = static_cast<double>(x) * tau, v = static_cast<double>(y) * tau;
      const double n = 0.5 * valueNoise(u / 1.0, v / 1.0, noise_seed) +
                       0.3 * valueNoise(u / 0.3, v / 0.3, noise_seed + 1) +
                       0.2 * valueNoise(u / 0.1, v / 0.1, noise_seed + 2);
      value[y * w + x] = static_cast<float>(n);
    }
  }

  // Dead leaves, from the largest scale to the smallest.
  Rng rng(deriveSeed(seed, 2));
  const double area = width_m * height_m;
  const double scale_ratio = options.max_feature_m / options.min_feature_m;
  constexpr int kScales = 5;
  for (int scale = kScales - 1; scale >= 0; --scale) {
    const double size = options.min_feature_m * std::pow(scale_ratio, static_cast<double>(scale) / (kScales - 1));
    // Large shapes cover more than small ones, so that structure at every scale survives the overdraw.
    const double coverage = options.coverage_per_scale * (0.5 + 0.25 * scale);
    const auto count = static_cast<std::size_t>(coverage * area / (size * size));
    for (std::size_t k = 0; k < count; ++k) {
      const double cu = rng.uniform(-0.5 * size, width_m + 0.5 * size);
      const double cv = rng.uniform(-0.5 * size, height_m + 0.5 * size);
      const double s = size * rng.uniform(0.6, 1.6);
      const double kind = rng.uniform();
      // High contrast: dark or bright, rarely mid-grey.
      const double level = rng.uniform() < 0.5 ? rng.uniform(0.0, 0.3) : rng.uniform(0.7, 1.0);
      double half_a = 0.5 * s, half_b = 0.5 * s;
      if (kind < 0.5) {  // rectangle
        const double aspect = std::exp(rng.uniform(-1.0, 1.0));
        half_a *= aspect;
        half_b /= aspect;
      } else if (kind >= 0.8) {  // bar
        half_b *= 0.15;
      }
      const double angle = kind < 0.3 ? 0.0 : rng.uniform(0.0, std::numbers::pi);
      const double ca = std::cos(angle), sa = std::sin(angle);
      const double reach = std::hypot(half_a, half_b);
      const int x0 = std::max(0, static_cast<int>(std::floor((cu - reach) / tau)));
      const int x1 = std::min(base.width - 1, static_cast<int>(std::ceil((cu + reach) / tau)));
      const int y0 = std::max(0, static_cast<int>(std::floor((cv - reach) / tau)));
      const int y1 = std::min(base.height - 1, static_cast<int>(std::ceil((cv + reach) / tau)));
      const bool disc = kind >= 0.5 && kind < 0.8;
      for (int y = y0; y <= y1; ++y) {
        for (int x = x0; x <= x1; ++x) {
          const double du = x * tau - cu, dv = y * tau - cv;
          const double a = ca * du + sa * dv, b = -sa * du + ca * dv;
          const bool inside =
              disc ? (a * a + b * b <= half_a * half_a) : (std::abs(a) <= half_a && std::abs(b) <= half_b);
          if (!inside) continue;
          float& t = value[static_cast<std::size_t>(y) * w + static_cast<std::size_t>(x)];
          // The noise already stored modulates the new shape slightly, so large shapes are not flat.
          t = static_cast<float>(0.8 * level + 0.2 * static_cast<double>(t));
        }
      }
    }
  }

  // A slow brightness modulation (2.5 m value noise, +-12 %) makes places differ at a glance, as lighting and
  // dirt do in a real hall, and keeps distant, filtered views from averaging out to flat grey.
  base.data.resize(w * h);
  const std::uint64_t light_seed = deriveSeed(seed, 3);
  for (std::size_t y = 0; y < h; ++y) {
    for (std::size_t x = 0; x < w; ++x) {
      const double light =
          0.88 + 0.24 * valueNoise(static_cast<double>(x) * tau / 2.5, static_cast<double>(y) * tau / 2.5, light_seed);
      const double grey = (15.0 + 225.0 * static_cast<double>(value[y * w + x])) * light;
      base.data[y * w + x] = static_cast<std::uint8_t>(std::lround(std::clamp(grey, 0.0, 255.0)));
    }
  }
  levels_.push_back(std::move(base));

  // Mip pyramid by 2x2 box filtering.
  constexpr int kMaxLevels = 7;
  while (static_cast<int>(levels_.size()) < kMaxLevels && levels_.back().width >= 8 && levels_.back().height >= 8) {
    const Level& fine = levels_.back();
    Level coarse;
    coarse.width = (fine.width + 1) / 2;
    coarse.height = (fine.height + 1) / 2;
    coarse.inv_texel = fine.inv_texel * 0.5F;
    coarse.data.resize(static_cast<std::size_t>(coarse.width) * static_cast<std::size_t>(coarse.height));
    for (int y = 0; y < coarse.height; ++y) {
      for (int x = 0; x < coarse.width; ++x) {
        const int xa = std::min(2 * x, fine.width - 1), xb = std::min(2 * x + 1, fine.width - 1);
        const int ya = std::min(2 * y, fine.height - 1), yb = std::min(2 * y + 1, fine.height - 1);
        const int sum = fine.at(xa, ya) + fine.at(xb, ya) + fine.at(xa, yb) + fine.at(xb, yb);
        coarse
            .data[static_cast<std::size_t>(y) * static_cast<std::size_t>(coarse.width) + static_cast<std::size_t>(x)] =
            static_cast<std::uint8_t>((sum + 2) / 4);
      }
    }
    levels_.push_back(std::move(coarse));
  }
}

float Texture::sample(double u_m, double v_m, double footprint_m) const {
  // Level L has texels 2^L * tau; pick the largest L with 2^L * tau <= footprint.
  // floor(log2(ratio)) from the float's exponent bits (std::ilogb is an out-of-line call on the hot path).
  const float ratio = static_cast<float>(footprint_m) * inv_texel_size_;
  const int exponent = static_cast<int>((std::bit_cast<std::uint32_t>(ratio) >> 23U) & 0xFFU) - 127;
  const int level = std::clamp(exponent, 0, static_cast<int>(levels_.size()) - 1);
  const Level& l = levels_[static_cast<std::size_t>(level)];
  // Texel (i, j) of level 0 is centred at (i, j) * tau: level 0 has no half-texel offset; level L averages
  // texels 2i and 2i+1, so its centre is at (2i + 0.5) * tau.
  const float offset = level == 0 ? 0.0F : 0.5F - 0.5F / static_cast<float>(1 << level);
  const float x = std::clamp(static_cast<float>(u_m) * l.inv_texel - offset, 0.0F, static_cast<float>(l.width - 1));
  const float y = std::clamp(static_cast<float>(v_m) * l.inv_texel - offset, 0.0F, static_cast<float>(l.height - 1));
  const int x0 = std::min(static_cast<int>(x), l.width - 2), y0 = std::min(static_cast<int>(y), l.height - 2);
  const float tx = x - static_cast<float>(x0), ty = y - static_cast<float>(y0);
  const std::size_t i = static_cast<std::size_t>(y0) * static_cast<std::size_t>(l.width) + static_cast<std::size_t>(x0);
  const float a = l.data[i], b = l.data[i + 1];
  const float c = l.data[i + static_cast<std::size_t>(l.width)], d = l.data[i + static_cast<std::size_t>(l.width) + 1];
  return (a + (b - a) * tx) * (1.0F - ty) + (c + (d - c) * tx) * ty;
}

}  // namespace cvislam::sim
