#include "test/sim/renderer.hpp"

#include <algorithm>
#include <cmath>

namespace cvislam::sim {

Renderer::Renderer(camera::CameraModel camera, const RendererOptions& options) : camera_(std::move(camera)) {
  const int w = camera_.width(), h = camera_.height();
  rays_.resize(static_cast<std::size_t>(w) * static_cast<std::size_t>(h));
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      rays_[static_cast<std::size_t>(y) * static_cast<std::size_t>(w) + static_cast<std::size_t>(x)] =
          camera_.unproject(Eigen::Vector2d(x, y));
    }
  }
  inv_focal_ = 2.0 / (camera_.calibration().fx + camera_.calibration().fy);
  const int ts = std::max(1, options.tile_size_px);
  for (int y0 = 0; y0 < h; y0 += ts) {
    for (int x0 = 0; x0 < w; x0 += ts) {
      Tile tile;
      tile.x0 = x0;
      tile.y0 = y0;
      tile.x1 = std::min(w, x0 + ts);
      tile.y1 = std::min(h, y0 + ts);
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (int y = tile.y0; y < tile.y1; ++y) {
        for (int x = tile.x0; x < tile.x1; ++x) sum += ray(x, y);
      }
      tile.axis_c = sum.normalized();
      double min_cos = 1.0;
      for (int y = tile.y0; y < tile.y1; ++y) {
        for (int x = tile.x0; x < tile.x1; ++x) min_cos = std::min(min_cos, tile.axis_c.dot(ray(x, y)));
      }
      // A small margin keeps the test conservative against rounding.
      const double half = std::acos(std::clamp(min_cos, -1.0, 1.0)) + 1e-4;
      tile.cos_half = std::cos(half);
      tile.sin_half = std::sin(half);
      tiles_.push_back(tile);
    }
  }
}

void Renderer::candidates(const World& world, const geometry::SE3d& T_c_w, const Tile& tile,
                          std::vector<int>& out) const {
  out.clear();
  const auto& obstacles = world.layout().obstacles;
  for (std::size_t i = 0; i < obstacles.size(); ++i) {
    const Box& bx = obstacles[i];
    const Eigen::Vector3d c_c = T_c_w * (0.5 * (bx.min_w + bx.max_w));
    const double r = 0.5 * (bx.max_w - bx.min_w).norm();
    const double dist = c_c.norm();
    if (dist <= r) {
      out.push_back(static_cast<int>(i));
      continue;
    }
    // The sphere meets the cone iff the angle between the axis and the centre <= half + asin(r / dist).
    const double sin_b = r / dist;
    const double cos_b = std::sqrt(1.0 - sin_b * sin_b);
    const double cos_sum = tile.cos_half * cos_b - tile.sin_half * sin_b;  // cos(half + beta)
    // half < pi/2 and beta <= pi/2, so half + beta < pi and comparing cosines is exact.
    if (tile.axis_c.dot(c_c) >= cos_sum * dist) out.push_back(static_cast<int>(i));
  }
}

float Renderer::shadePixel(const World& world, const Eigen::Vector3d& o_w, const Eigen::Matrix3d& R_w_c,
                           std::size_t pixel, const std::vector<int>& cands) const {
  const Eigen::Vector3d d_w = R_w_c * rays_[pixel];
  const RayHit hit = world.cast(o_w, d_w, cands.data(), static_cast<int>(cands.size()));
  // The pixel's footprint on the surface grows with distance and with obliqueness.
  const double cos_incidence = std::abs(d_w((hit.face % 6) / 2));
  const double footprint = hit.t_m * inv_focal_ / std::sqrt(std::max(cos_incidence, 0.1));
  return world.shade(hit, footprint);
}

void Renderer::render(const World& world, const geometry::SE3d& T_w_c, double gain, dataset::GrayImage& image) const {
  const int w = camera_.width(), h = camera_.height();
  if (image.width != w || image.height != h) image = dataset::GrayImage(w, h);
  const geometry::SE3d T_c_w = T_w_c.inverse();
  const Eigen::Matrix3d R_w_c = T_w_c.rotationMatrix();
  const Eigen::Vector3d& o_w = T_w_c.translation();
  const auto g = static_cast<float>(gain);
  std::vector<int> cands;
  cands.reserve(world.layout().obstacles.size());
  for (const Tile& tile : tiles_) {
    candidates(world, T_c_w, tile, cands);
    for (int y = tile.y0; y < tile.y1; ++y) {
      for (int x = tile.x0; x < tile.x1; ++x) {
        const std::size_t p = static_cast<std::size_t>(y) * static_cast<std::size_t>(w) + static_cast<std::size_t>(x);
        const float v = g * shadePixel(world, o_w, R_w_c, p, cands);
        image.pixels[p] = static_cast<std::uint8_t>(std::clamp(v + 0.5F, 0.0F, 255.0F));
      }
    }
  }
}

RayHit Renderer::castPixel(const World& world, const geometry::SE3d& T_w_c, int x, int y) const {
  const geometry::SE3d T_c_w = T_w_c.inverse();
  for (const Tile& tile : tiles_) {
    if (x >= tile.x0 && x < tile.x1 && y >= tile.y0 && y < tile.y1) {
      std::vector<int> cands;
      candidates(world, T_c_w, tile, cands);
      const Eigen::Vector3d d_w = T_w_c.rotationMatrix() * ray(x, y);
      return world.cast(T_w_c.translation(), d_w, cands.data(), static_cast<int>(cands.size()));
    }
  }
  return {};
}

}  // namespace cvislam::sim
