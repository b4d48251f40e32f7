#include "test/server_cloud/maps/example_maps.hpp"

#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

namespace cvislam::test {

namespace {

using server::MapContent;
using server::ServerKeyframe;
using server::ServerMapPoint;

// The example is made by this file alone: a refusal is a bug here, so it stops the test binary loudly.
void require(const Status& s) {
  if (!s.ok()) {
    std::fprintf(stderr, "fillExampleMission: %s\n", s.error().toString().c_str());
    std::abort();
  }
}

struct MapFiller {
  MapContent& map;
  std::mt19937& rng;
  const ExampleMissionOptions& options;
  std::vector<MapPointId> previous_points;  // the newest keyframe's own points

  void addKeyframe(AgentId agent, std::uint32_t counter, std::int64_t t_ns, std::uint32_t& point_counter) {
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    ServerKeyframe kf;
    kf.id = KeyframeId{agent, counter};
    kf.agent_map = 0;
    kf.t_ns = t_ns;
    kf.T_w_s = geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(u(rng), u(rng), u(rng)) * 0.3),
                              Eigen::Vector3d(u(rng) * 10.0, u(rng) * 10.0, u(rng)));
    kf.v_w = Eigen::Vector3d(u(rng), u(rng), u(rng));
    kf.bias.gyro = Eigen::Vector3d(u(rng), u(rng), u(rng)) * 1e-3;
    kf.bias.accel = Eigen::Vector3d(u(rng), u(rng), u(rng)) * 1e-2;
    kf.refined = counter % 3 == 0;
    kf.keypoints.resize(options.keypoints_per_keyframe);
    kf.descriptors.resize(options.keypoints_per_keyframe);
    for (auto& k : kf.keypoints)
      k.px = Eigen::Vector2f(static_cast<float>(320.0 + 300.0 * u(rng)), static_cast<float>(240.0 + 200.0 * u(rng)));
    require(map.addKeyframe(std::move(kf)));
    const KeyframeId id{agent, counter};
    std::uint16_t keypoint = 0;
    std::vector<MapPointId> own;
    for (std::uint32_t i = 0; i < options.points_per_keyframe && keypoint < options.keypoints_per_keyframe; ++i) {
      ServerMapPoint p;
      p.id = MapPointId{agent, point_counter++};
      p.reference = id;
      p.p_w = Eigen::Vector3d(u(rng) * 20.0, u(rng) * 20.0, u(rng) * 3.0);
      for (auto& byte : p.descriptor) byte = static_cast<std::uint8_t>(rng() & 0xFFU);
      require(map.addPoint(p));
      require(map.addObservation(id, keypoint++, p.id));
      own.push_back(p.id);
    }
    for (const MapPointId& p : previous_points) {
      if (keypoint >= options.keypoints_per_keyframe) break;
      require(map.addObservation(id, keypoint++, p));
    }
    previous_points = std::move(own);
  }
};

}  // namespace

void fillExampleMission(server::MissionRegistry& missions, const ExampleMissionOptions& options) {
  std::mt19937 rng(options.seed);
  auto mission = missions.getOrCreate(options.name);
  auto shared = mission->stack().createMap({1, 0});
  auto alone = mission->stack().createMap({3, 0});
  std::uint32_t points1 = 0;
  std::uint32_t points2 = 0;
  std::uint32_t points3 = 0;
  {
    auto content = shared->write();
    MapFiller filler{*content, rng, options, {}};
    for (std::uint32_t c = 0; c < options.keyframes_per_agent; ++c) {
      const std::int64_t t_ns = 1'000'000'000 + static_cast<std::int64_t>(c) * 500'000'000;
      filler.addKeyframe(1, c, t_ns, points1);
      filler.addKeyframe(2, c, t_ns + 250'000'000, points2);
    }
  }
  {
    auto content = alone->write();
    MapFiller filler{*content, rng, options, {}};
    for (std::uint32_t c = 0; c < options.keyframes_per_agent / 2; ++c) {
      filler.addKeyframe(3, c, 2'000'000'000 + static_cast<std::int64_t>(c) * 400'000'000, points3);
    }
  }
  for (AgentId a : {1, 2, 3}) mission->agent(a);
}

}  // namespace cvislam::test
