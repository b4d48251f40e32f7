// The simulated world: a hall (the inside of an axis-aligned box) holding axis-aligned boxes (pillars, crates,
// shelves), every face with its own procedural texture. Ray casting is a slab test per box.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "test/sim/texture.hpp"

namespace cvislam::sim {

struct Box {
  Eigen::Vector3d min_w = Eigen::Vector3d::Zero();
  Eigen::Vector3d max_w = Eigen::Vector3d::Ones();
  std::string kind = "box";  // "pillar", "shelf", "crate", ...
};

struct WorldLayout {
  Box hall;  // the room; cameras are inside it
  std::vector<Box> obstacles;
};

struct WorldOptions {
  std::uint64_t seed = 0;
  TextureOptions texture;
};

// One textured face: box b, axis a, side (0 = the min face, 1 = the max face). Faces are numbered
// 6 * box + 2 * axis + side, with box 0 the hall and box i + 1 obstacle i.
struct RayHit {
  double t_m = 0.0;  // distance along the unit ray
  int face = -1;
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
};

class World {
 public:
  World(WorldLayout layout, const WorldOptions& options);

  // Nearest hit of the ray o + t d (d unit, o inside the hall), considering the hall and the obstacles
  // listed in `candidates` (indices into layout().obstacles). The hall always returns a hit.
  [[nodiscard]] RayHit cast(const Eigen::Vector3d& o_w, const Eigen::Vector3d& d_w, const int* candidates,
                            int candidate_count) const;
  [[nodiscard]] RayHit cast(const Eigen::Vector3d& o_w, const Eigen::Vector3d& d_w) const;  // all obstacles

  // Grey value [0, 255] of a face at a point on it, for a pixel footprint [m] on the surface.
  [[nodiscard]] float shade(const RayHit& hit, double footprint_m) const;

  [[nodiscard]] const WorldLayout& layout() const { return layout_; }
  // Surface coordinates (u, v) [m] of a point on a face, and that face's texture.
  [[nodiscard]] Eigen::Vector2d surfaceCoordinates(int face, const Eigen::Vector3d& p_w) const;
  [[nodiscard]] const Texture* texture(int face) const { return faces_[static_cast<std::size_t>(face)].texture.get(); }
  [[nodiscard]] Eigen::Vector3d faceNormal(int face) const;  // pointing towards the viewer side
  // Distance from a point to the nearest obstacle or hall face (negative inside an obstacle or outside the hall).
  [[nodiscard]] double clearance(const Eigen::Vector3d& p_w) const;

 private:
  struct Face {
    std::unique_ptr<Texture> texture;  // null for faces nobody can see (bottoms on the floor)
    float brightness = 1.0F;           // a fixed per-face factor, as diffuse lighting would give
  };
  [[nodiscard]] const Box& box(int index) const {
    return index == 0 ? layout_.hall : layout_.obstacles[static_cast<std::size_t>(index - 1)];
  }

  WorldLayout layout_;
  std::vector<Face> faces_;
};

}  // namespace cvislam::sim
