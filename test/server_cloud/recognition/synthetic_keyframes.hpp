// Server keyframes made from the simulator, for place-recognition tests and its evaluation: a rendered cam0
// image, its ORB keypoints and descriptors (the agent's extractor), and for each keypoint the surface point its
// ray hits (exact, from the world's geometry). A SyntheticMap turns such views into one server map as an agent's
// VIO would have built it: keypoints that see the same surface spot within a window of recent keyframes share a
// map point (as the local map tracks it), older ones get a new point (as after drift nobody re-associates
// them); points carry a drift transform of the keyframe that made them and noise along the ray.
//
// What this leaves out, on purpose: the agent's own tracking errors and its keyframe choice. Recognition is
// measured on its own here; the mission shows it on maps the agents built.
#pragma once

#include <cstdint>
#include <map>
#include <tuple>
#include <vector>

#include <Eigen/Core>

#include "common/camera/camera_model.hpp"
#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/stack/map_content.hpp"
#include "test/sim/random.hpp"
#include "test/sim/renderer.hpp"
#include "test/sim/world.hpp"

namespace cvislam::test {

struct SyntheticView {
  geometry::SE3d T_w_s;  // true body pose in the simulator's world
  std::vector<features::Keypoint> keypoints;
  std::vector<features::Descriptor> descriptors;
  std::vector<Eigen::Vector3d> p_w;  // per keypoint: the true surface point
  std::vector<int> face;             // per keypoint: the face hit (-1: none)
};

class ViewMaker {
 public:
  // cam0 of `calibration`, ORB with the agent's defaults.
  static Result<ViewMaker> create(const dataset::CameraCalibration& calibration);

  // Renders the view from body pose T_w_s. `mirror` flips the image left-right before extraction and mirrors the
  // points in the camera frame to match (x -> -x): a place that looks like the mirror image of this one.
  SyntheticView render(const sim::World& world, const geometry::SE3d& T_w_s, bool mirror = false);

  [[nodiscard]] const camera::CameraModel& camera() const { return renderer_.camera(); }
  [[nodiscard]] const geometry::SE3d& T_s_c() const { return T_s_c_; }

 private:
  ViewMaker(sim::Renderer renderer, features::OrbExtractor extractor, geometry::SE3d T_s_c)
      : renderer_(std::move(renderer)), extractor_(std::move(extractor)), T_s_c_(T_s_c) {}
  sim::Renderer renderer_;
  features::OrbExtractor extractor_;
  geometry::SE3d T_s_c_;
};

struct SyntheticMapOptions {
  int association_window = 20;  // keyframes within which a surface spot keeps its map point
  double cell_m = 0.02;         // surface spots closer than this (on one face) are one map point
  double depth_noise = 0.01;    // point noise along the ray, as a fraction of the depth (1 sigma)
  std::uint64_t seed = 1;
};

// One agent's server map, built from its views in order.
class SyntheticMap {
 public:
  // The world gives the surface coordinates of each keypoint's spot; both must outlive this.
  SyntheticMap(server::MapContent& map, const sim::World& world, AgentId agent, const SyntheticMapOptions& options);

  // Adds the view as the agent's next keyframe, its pose and points moved by `E_map_w` (the map frame and the
  // drift at this keyframe: the estimate is E_map_w * truth), at time t_ns (default: 0.5 s per keyframe).
  // Returns its id.
  Result<KeyframeId> add(const SyntheticView& view, const geometry::SE3d& E_map_w, std::int64_t t_ns = -1);

  [[nodiscard]] server::MapContent& map() { return map_; }

 private:
  server::MapContent& map_;
  const sim::World& world_;
  AgentId agent_;
  SyntheticMapOptions options_;
  sim::Rng rng_;
  std::uint32_t next_keyframe_ = 0;
  std::uint32_t next_point_ = 0;
  struct Spot {
    MapPointId point;
    std::uint32_t last_keyframe = 0;
  };
  std::map<std::tuple<int, std::int64_t, std::int64_t>, Spot> spots_;  // (face, cell u, cell v)
};

}  // namespace cvislam::test
