#include "test/sim/world.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "test/sim/random.hpp"

namespace cvislam::sim {

namespace {

constexpr std::uint64_t kTextureStream = 0x7E47;

// The two in-face axes of a face perpendicular to `axis`.
inline int firstAxis(int axis) {
  return axis == 0 ? 1 : 0;
}
inline int secondAxis(int axis) {
  return axis == 2 ? 1 : 2;
}

}  // namespace

World::World(WorldLayout layout, const WorldOptions& options) : layout_(std::move(layout)) {
  const int boxes = 1 + static_cast<int>(layout_.obstacles.size());
  faces_.resize(6 * static_cast<std::size_t>(boxes));
  const double floor_z = layout_.hall.min_w.z();
  for (int b = 0; b < boxes; ++b) {
    const Box& bx = box(b);
    const Eigen::Vector3d size = bx.max_w - bx.min_w;
    for (int axis = 0; axis < 3; ++axis) {
      for (int side = 0; side < 2; ++side) {
        const int face = 6 * b + 2 * axis + side;
        // An obstacle's bottom on the floor is never seen.
        if (b > 0 && axis == 2 && side == 0 && bx.min_w.z() <= floor_z + 1e-6) continue;
        Face& f = faces_[static_cast<std::size_t>(face)];
        f.texture = std::make_unique<Texture>(
            size(firstAxis(axis)), size(secondAxis(axis)),
            deriveSeed(options.seed, kTextureStream, static_cast<std::uint64_t>(face)), options.texture);
        // Soft, fixed "lighting": floors brighter, ceilings darker, walls by direction.
        static constexpr float kBrightness[6] = {0.92F, 0.84F, 0.88F, 0.96F, 1.0F, 0.72F};
        f.brightness = kBrightness[2 * axis + side];
      }
    }
  }
}

RayHit World::cast(const Eigen::Vector3d& o_w, const Eigen::Vector3d& d_w, const int* candidates,
                   int candidate_count) const {
  const Eigen::Vector3d inv(1.0 / d_w.x(), 1.0 / d_w.y(), 1.0 / d_w.z());
  // Hall: the exit through its walls.
  RayHit hit;
  hit.t_m = std::numeric_limits<double>::infinity();
  for (int axis = 0; axis < 3; ++axis) {
    if (d_w(axis) == 0.0) continue;  // parallel to these walls (inv is infinite)
    const bool positive = d_w(axis) > 0.0;
    const double plane = positive ? layout_.hall.max_w(axis) : layout_.hall.min_w(axis);
    const double t = (plane - o_w(axis)) * inv(axis);
    if (t < hit.t_m) {
      hit.t_m = t;
      hit.face = 2 * axis + (positive ? 1 : 0);
    }
  }
  // Obstacles: the entry through their faces.
  for (int k = 0; k < candidate_count; ++k) {
    const int index = candidates[k];
    const Box& bx = layout_.obstacles[static_cast<std::size_t>(index)];
    double t_near = -std::numeric_limits<double>::infinity();
    double t_far = std::numeric_limits<double>::infinity();
    int near_axis = 0;
    for (int axis = 0; axis < 3; ++axis) {
      double t0 = (bx.min_w(axis) - o_w(axis)) * inv(axis);
      double t1 = (bx.max_w(axis) - o_w(axis)) * inv(axis);
      if (t0 > t1) std::swap(t0, t1);
      if (t0 > t_near) {
        t_near = t0;
        near_axis = axis;
      }
      t_far = std::min(t_far, t1);
    }
    if (t_near <= t_far && t_near > 0.0 && t_near < hit.t_m) {
      hit.t_m = t_near;
      // Entering through the min face when moving towards +axis.
      hit.face = 6 * (index + 1) + 2 * near_axis + (d_w(near_axis) > 0.0 ? 0 : 1);
    }
  }
  hit.p_w = o_w + hit.t_m * d_w;
  return hit;
}

RayHit World::cast(const Eigen::Vector3d& o_w, const Eigen::Vector3d& d_w) const {
  std::vector<int> all(layout_.obstacles.size());
  for (std::size_t i = 0; i < all.size(); ++i) all[i] = static_cast<int>(i);
  return cast(o_w, d_w, all.data(), static_cast<int>(all.size()));
}

Eigen::Vector2d World::surfaceCoordinates(int face, const Eigen::Vector3d& p_w) const {
  const Box& bx = box(face / 6);
  const int axis = (face % 6) / 2;
  const int a = firstAxis(axis), b = secondAxis(axis);
  return {p_w(a) - bx.min_w(a), p_w(b) - bx.min_w(b)};
}

Eigen::Vector3d World::faceNormal(int face) const {
  const int axis = (face % 6) / 2;
  const int side = face % 2;
  const bool hall = face / 6 == 0;
  Eigen::Vector3d n = Eigen::Vector3d::Zero();
  // Obstacle faces point outwards, hall faces inwards.
  n(axis) = (side == 1) != hall ? 1.0 : -1.0;
  return n;
}

float World::shade(const RayHit& hit, double footprint_m) const {
  const Face& f = faces_[static_cast<std::size_t>(hit.face)];
  if (!f.texture) return 0.0F;
  const Eigen::Vector2d uv = surfaceCoordinates(hit.face, hit.p_w);
  return f.brightness * f.texture->sample(uv.x(), uv.y(), footprint_m);
}

double World::clearance(const Eigen::Vector3d& p_w) const {
  const Eigen::Vector3d to_min = p_w - layout_.hall.min_w;
  const Eigen::Vector3d to_max = layout_.hall.max_w - p_w;
  double d = std::min(to_min.minCoeff(), to_max.minCoeff());
  for (const Box& bx : layout_.obstacles) {
    const Eigen::Vector3d outside = (bx.min_w - p_w).cwiseMax(p_w - bx.max_w);
    const double dist = outside.maxCoeff() > 0.0 ? outside.cwiseMax(0.0).norm() : outside.maxCoeff();
    d = std::min(d, dist);
  }
  return d;
}

}  // namespace cvislam::sim
