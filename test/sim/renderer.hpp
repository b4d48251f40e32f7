// Renders grey images of a World by ray casting, one ray per pixel centre.
//
// Speed: the distorted-pixel -> unit-ray table is computed once per camera. The image is cut into tiles, and
// each tile's rays fit in a cone (precomputed); per frame, only the obstacles whose bounding sphere meets a
// tile's cone are tested for that tile's rays.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "common/camera/camera_model.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "common/dataset/image.hpp"
#include "common/geometry/lie.hpp"
#include "test/sim/world.hpp"

namespace cvislam::sim {

struct RendererOptions {
  int tile_size_px = 16;
};

class Renderer {
 public:
  explicit Renderer(camera::CameraModel camera, const RendererOptions& options = {});

  // Renders into `image` (resized as needed); gain scales intensities (exposure), 1 = nominal.
  void render(const World& world, const geometry::SE3d& T_w_c, double gain, dataset::GrayImage& image) const;
  // What the renderer sees through pixel (x, y) (the same code path as render()).
  [[nodiscard]] RayHit castPixel(const World& world, const geometry::SE3d& T_w_c, int x, int y) const;

  [[nodiscard]] const camera::CameraModel& camera() const { return camera_; }
  [[nodiscard]] Eigen::Vector3d ray(int x, int y) const {
    return rays_[static_cast<std::size_t>(y) * static_cast<std::size_t>(camera_.width()) + static_cast<std::size_t>(x)];
  }

 private:
  struct Tile {
    int x0 = 0, y0 = 0, x1 = 0, y1 = 0;  // pixel range [x0, x1) x [y0, y1)
    Eigen::Vector3d axis_c = Eigen::Vector3d::UnitZ();
    double cos_half = 1.0;  // cone half-angle
    double sin_half = 0.0;
  };
  // Obstacles whose bounding sphere may meet the tile's cone.
  void candidates(const World& world, const geometry::SE3d& T_c_w, const Tile& tile, std::vector<int>& out) const;
  [[nodiscard]] float shadePixel(const World& world, const Eigen::Vector3d& o_w, const Eigen::Matrix3d& R_w_c,
                                 std::size_t pixel, const std::vector<int>& candidates) const;

  camera::CameraModel camera_;
  std::vector<Eigen::Vector3d> rays_;  // unit rays in the camera frame, row-major
  std::vector<Tile> tiles_;
  double inv_focal_ = 0.0;  // angle of one pixel [rad]
};

}  // namespace cvislam::sim
