// Procedural surface textures: deterministic, multi-scale, high-contrast and not periodic.
//
// Each surface gets its own seed. The pattern is a "dead leaves" image: opaque rectangles, discs and bars at
// five scales (3 cm to 60 cm), drawn from large to small, over hash-based value noise, and lit by a slow
// (2.5 m) brightness modulation. Nothing repeats, so places look different to a place recogniser; every scale carries
// corners, so ORB finds features near and far. The texture is stored as a mip pyramid for lookups at any distance.
#pragma once

#include <cstdint>
#include <vector>

namespace cvislam::sim {

struct TextureOptions {
  double texel_size_m = 0.01;  // level 0
  double min_feature_m = 0.03;
  double max_feature_m = 0.6;
  double coverage_per_scale = 0.35;  // mean fraction of the area each scale's shapes cover (they overlap)
};

class Texture {
 public:
  // A width_m x height_m surface patch, generated from the seed (the same seed gives the same bytes).
  Texture(double width_m, double height_m, std::uint64_t seed, const TextureOptions& options);

  // Intensity in [0, 255] at surface coordinates (u, v) [m], bilinear, from the pyramid level whose texel is
  // closest to (not larger than) footprint_m, the size of one pixel on the surface.
  [[nodiscard]] float sample(double u_m, double v_m, double footprint_m) const;
  // Level-0 texel grid (for tests).
  [[nodiscard]] int width() const { return levels_.front().width; }
  [[nodiscard]] int height() const { return levels_.front().height; }
  [[nodiscard]] std::uint8_t texel(int x, int y) const { return levels_.front().at(x, y); }
  [[nodiscard]] double texelSize() const { return texel_size_m_; }

 private:
  struct Level {
    int width = 0;
    int height = 0;
    float inv_texel = 0.0F;  // texels per metre
    std::vector<std::uint8_t> data;
    [[nodiscard]] std::uint8_t at(int x, int y) const {
      return data[static_cast<std::size_t>(y) * static_cast<std::size_t>(width) + static_cast<std::size_t>(x)];
    }
  };
  std::vector<Level> levels_;
  double texel_size_m_ = 0.01;
  float inv_texel_size_ = 100.0F;
};

}  // namespace cvislam::sim
