#include "test/server_cloud/recognition/synthetic_keyframes.hpp"

#include <algorithm>
#include <cmath>
#include <set>

#include "common/dataset/image.hpp"

namespace cvislam::test {

Result<ViewMaker> ViewMaker::create(const dataset::CameraCalibration& calibration) {
  Result<camera::CameraModel> model = camera::CameraModel::create(calibration);
  if (!model) return model.error();
  Result<features::OrbExtractor> extractor = features::OrbExtractor::create(features::OrbOptions{});
  if (!extractor) return extractor.error();
  return ViewMaker(sim::Renderer(std::move(model).value()), std::move(extractor).value(), calibration.T_b_c);
}

SyntheticView ViewMaker::render(const sim::World& world, const geometry::SE3d& T_w_s, bool mirror) {
  const geometry::SE3d T_w_c = T_w_s * T_s_c_;
  dataset::GrayImage image;
  renderer_.render(world, T_w_c, 1.0, image);
  if (mirror) {
    for (int y = 0; y < image.height; ++y) {
      const auto row = image.pixels.begin() + static_cast<std::ptrdiff_t>(y) * image.width;
      std::reverse(row, row + image.width);
    }
  }
  SyntheticView view;
  view.T_w_s = T_w_s;
  const auto n = static_cast<std::size_t>(extractor_.options().max_features);
  view.keypoints.resize(n);
  view.descriptors.resize(n);
  const int count = extractor_.extract(image.pixels, image.width, image.height, view.keypoints, view.descriptors);
  view.keypoints.resize(static_cast<std::size_t>(count));
  view.descriptors.resize(static_cast<std::size_t>(count));
  const camera::CameraModel& cam = renderer_.camera();
  for (const features::Keypoint& k : view.keypoints) {
    Eigen::Vector2d px = k.px.cast<double>();
    if (mirror) px.x() = static_cast<double>(image.width - 1) - px.x();
    const Eigen::Vector3d ray_c = cam.unproject(px);
    const sim::RayHit hit = world.cast(T_w_c.translation(), T_w_c.rotationMatrix() * ray_c);
    if (hit.face < 0) {
      view.p_w.emplace_back(Eigen::Vector3d::Zero());
      view.face.push_back(-1);
      continue;
    }
    Eigen::Vector3d p_w = hit.p_w;
    if (mirror) {
      Eigen::Vector3d p_c = T_w_c.inverse() * p_w;
      p_c.x() = -p_c.x();
      p_w = T_w_c * p_c;
    }
    view.p_w.push_back(p_w);
    view.face.push_back(mirror ? -2 - hit.face : hit.face);  // a mirrored spot is no spot of the real world
  }
  return view;
}

SyntheticMap::SyntheticMap(server::MapContent& map, const sim::World& world, AgentId agent,
                           const SyntheticMapOptions& options)
    : map_(map), world_(world), agent_(agent), options_(options), rng_(sim::deriveSeed(options.seed, 77, agent)) {}

Result<KeyframeId> SyntheticMap::add(const SyntheticView& view, const geometry::SE3d& E_map_w, std::int64_t t_ns) {
  const std::uint32_t index = next_keyframe_++;
  server::ServerKeyframe kf;
  kf.id = KeyframeId{agent_, index};
  kf.t_ns = t_ns >= 0 ? t_ns : static_cast<std::int64_t>(index) * 500'000'000;
  kf.T_w_s = E_map_w * view.T_w_s;
  kf.keypoints = view.keypoints;
  kf.descriptors = view.descriptors;
  const KeyframeId id = kf.id;
  if (Status s = map_.addKeyframe(std::move(kf)); !s) return s.error();
  const Eigen::Vector3d o_w = view.T_w_s.translation();
  std::set<MapPointId> observed;
  for (std::size_t i = 0; i < view.keypoints.size(); ++i) {
    const int face = view.face[i];
    if (face == -1) continue;
    // Mirrored spots (face <= -2) get their own points: no real spot matches them.
    const Eigen::Vector2d uv = face >= 0 ? world_.surfaceCoordinates(face, view.p_w[i]) : view.p_w[i].head<2>();
    const auto key = std::make_tuple(face, static_cast<std::int64_t>(std::floor(uv.x() / options_.cell_m)),
                                     static_cast<std::int64_t>(std::floor(uv.y() / options_.cell_m)));
    auto it = spots_.find(key);
    const bool fresh = it == spots_.end() ||
                       index - it->second.last_keyframe > static_cast<std::uint32_t>(options_.association_window) ||
                       map_.point(it->second.point) == nullptr;
    if (fresh) {
      server::ServerMapPoint point;
      point.id = MapPointId{agent_, next_point_++};
      point.reference = id;
      const Eigen::Vector3d ray = view.p_w[i] - o_w;
      const double noise = options_.depth_noise * rng_.normal();
      point.p_w = E_map_w * (view.p_w[i] + noise * ray);
      point.descriptor = view.descriptors[i];
      point.octave = view.keypoints[i].octave;
      if (Status s = map_.addPoint(point); !s) return s.error();
      it = spots_.insert_or_assign(key, Spot{point.id, index}).first;
    }
    if (!observed.insert(it->second.point).second) continue;  // another keypoint of this keyframe has it
    if (Status s = map_.addObservation(id, static_cast<std::uint16_t>(i), it->second.point); !s) return s.error();
    it->second.last_keyframe = index;
  }
  return id;
}

}  // namespace cvislam::test
