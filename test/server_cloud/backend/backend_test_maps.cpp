#include "test/server_cloud/backend/backend_test_maps.hpp"

#include <map>
#include <random>
#include <set>
#include <thread>
#include <vector>

#include <Eigen/Core>

namespace cvislam::server::backend::test_maps {
camera::CameraModel pinholeCamera(const test::ViScenario& s) {
  dataset::CameraCalibration c;
  c.width = 752;
  c.height = 480;
  c.fx = s.intrinsics.fx;
  c.fy = s.intrinsics.fy;
  c.cx = s.intrinsics.cx;
  c.cy = s.intrinsics.cy;
  c.distortion_coefficients = {0.0, 0.0, 0.0, 0.0};
  c.T_b_c = s.T_s_c;
  return *camera::CameraModel::create(c);
}

AgentSensors sensorsOf(const test::ViScenario& s) {
  AgentSensors sensors{.mode = SensorMode::kMono,
                       .uses_imu = true,
                       .cam0 = pinholeCamera(s),
                       .cam1 = std::nullopt,
                       .T_s_c0 = s.T_s_c,
                       .T_s_c1 = {},
                       .imu_noise = s.noise,
                       .imu_rate_hz = s.options.imu_rate_hz};
  return sensors;
}

namespace {

using Eigen::Vector3d;

constexpr std::uint32_t kGeneration = 100'000;  // point counters: generation * kGeneration + scenario index

features::Descriptor descriptorOf(std::uint32_t point) {
  std::mt19937_64 rng(1000 + point);
  features::Descriptor d{};
  for (auto& byte : d) byte = static_cast<std::uint8_t>(rng() & 0xFFU);
  return d;
}

}  // namespace

void buildAgentMap(MapContent& map, const test::ViScenario& s, const AgentPlan& plan, AgentRecord* record) {
  std::map<int, std::vector<const test::ViObservation*>> by_keyframe;
  for (const auto& o : s.observations) by_keyframe[o.keyframe].push_back(&o);
  std::set<std::uint32_t> made;
  for (int k = plan.first; k <= plan.last; ++k) {
    ServerKeyframe kf;
    kf.id = KeyframeId{plan.agent, static_cast<std::uint32_t>(k)};
    kf.t_ns = s.keyframe_t_ns[static_cast<std::size_t>(k)] + 1'000'000'000;
    const SE3d E = plan.E(k);
    kf.T_w_s = E * s.keyframe_states[static_cast<std::size_t>(k)].T_w_s;
    kf.v_w = E.so3() * s.keyframe_states[static_cast<std::size_t>(k)].v_w;
    for (const test::ViObservation* o : by_keyframe[k]) {
      features::Keypoint key;
      key.px = o->keypoint_px.cast<float>();
      kf.keypoints.push_back(key);
      kf.descriptors.push_back(descriptorOf(static_cast<std::uint32_t>(o->point)));
    }
    kf.point.resize(kf.keypoints.size());
    kf.has_point.assign(kf.keypoints.size(), 0);
    if (k > plan.first) {
      kf.imu_from = KeyframeId{plan.agent, static_cast<std::uint32_t>(k - 1)};
      for (const dataset::ImuSample& sample : s.imu) {
        if (sample.t_ns >= s.keyframe_t_ns[static_cast<std::size_t>(k - 1)] &&
            sample.t_ns <= s.keyframe_t_ns[static_cast<std::size_t>(k)]) {
          dataset::ImuSample shifted = sample;
          shifted.t_ns += 1'000'000'000;
          kf.imu.push_back(shifted);
        }
      }
      kf.preintegration = s.preintegrations[static_cast<std::size_t>(k - 1)];
    }
    const std::size_t keypoints = kf.keypoints.size();
    ASSERT_TRUE(map.addKeyframe(std::move(kf)).ok());
    if (record != nullptr) {
      record->keyframes[static_cast<std::uint32_t>(k)] =
          AgentRecord::HeldKeyframe{map.id(), 0, static_cast<std::uint32_t>(keypoints)};
    }
    const int generation = plan.generation(k);
    for (std::size_t i = 0; i < by_keyframe[k].size(); ++i) {
      const test::ViObservation& o = *by_keyframe[k][i];
      const auto counter = static_cast<std::uint32_t>(generation) * kGeneration + static_cast<std::uint32_t>(o.point);
      const MapPointId id{plan.agent, counter};
      if (made.insert(counter).second) {
        ServerMapPoint p;
        p.id = id;
        p.reference = KeyframeId{plan.agent, static_cast<std::uint32_t>(k)};
        p.p_w = E * s.points[static_cast<std::size_t>(o.point)].p_w;
        p.descriptor = descriptorOf(static_cast<std::uint32_t>(o.point));
        ASSERT_TRUE(map.addPoint(p).ok());
        if (record != nullptr) record->points[counter] = map.id();
      }
      ASSERT_TRUE(
          map.addObservation(KeyframeId{plan.agent, static_cast<std::uint32_t>(k)}, static_cast<std::uint16_t>(i), id)
              .ok());
    }
  }
}

void buildTwoAgentsFusedMap(MapContent& map, const test::ViScenario& s) {
  buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 7}, nullptr);
  buildAgentMap(map, s, AgentPlan{.agent = 2, .first = 8, .last = 15}, nullptr);
  for (std::size_t p = 0; p < s.points.size(); ++p) {
    const MapPointId a{1, static_cast<std::uint32_t>(p)};
    const MapPointId b{2, static_cast<std::uint32_t>(p)};
    if (map.point(a) != nullptr && map.point(b) != nullptr) {
      ASSERT_TRUE(map.mergePoints(b, a).ok());
    }
  }
  ASSERT_TRUE(map.checkConsistency().ok());
}

void perturbAllButTheGauge(MapContent& map, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> noise(0.0, 1.0);
  const auto vec = [&](double sigma) {
    const double x = noise(rng);
    const double y = noise(rng);
    const double z = noise(rng);
    return Eigen::Vector3d(sigma * x, sigma * y, sigma * z);
  };
  for (const auto& [id, kf_const] : map.keyframes()) {
    if (id == KeyframeId{1, 0}) continue;
    ServerKeyframe* kf = map.keyframe(id);
    kf->T_w_s = SE3d(kf->T_w_s.so3() * geometry::SO3d::exp(vec(0.01)), kf->T_w_s.translation() + vec(0.05));
    kf->v_w += vec(0.05);
  }
  std::vector<MapPointId> ids;
  for (const auto& [id, p] : map.points()) ids.push_back(id);
  for (const MapPointId& id : ids) map.point(id)->p_w += vec(0.05);
}

double maxPositionError(const MapContent& map, const test::ViScenario& s, AgentId agent, const SE3d& T_truth_map) {
  double worst = 0.0;
  for (const auto& [id, kf] : map.keyframes()) {
    if (id.agent != agent) continue;
    const Vector3d truth = s.keyframe_states[id.counter].T_w_s.translation();
    worst = std::max(worst, ((T_truth_map * kf.T_w_s).translation() - truth).norm());
  }
  return worst;
}

test::ViScenario scenario(int keyframes, double interval_s, double pixel_sigma) {
  test::ViScenarioOptions o;
  o.keyframes = keyframes;
  o.keyframe_interval_s = interval_s;
  o.points = 300;
  o.imu_rate_hz = 200.0;
  o.pixel_sigma = pixel_sigma;
  o.seed = 11;
  return test::makeViScenario(o);
}

recognition::MatchRecord matchRecord(recognition::QueryKind kind, const KeyframeId& query, MapId query_map,
                                     const KeyframeId& candidate, MapId candidate_map) {
  recognition::MatchRecord record;
  record.kind = kind;
  record.match.query = query;
  record.match.candidate = candidate;
  record.match.query_map = query_map;
  record.match.candidate_map = candidate_map;
  return record;
}

recognition::MatchRecord exactLoop(MapId map, const test::ViScenario& s, std::uint32_t query, std::uint32_t candidate) {
  recognition::MatchRecord record =
      matchRecord(recognition::QueryKind::kLoop, KeyframeId{1, query}, map, KeyframeId{1, candidate}, map);
  record.match.T_cmap_cq = s.keyframe_states[query].T_w_s * s.T_s_c;
  return record;
}

bool addArrivingKeyframes(ServerMap& map, const test::ViScenario& s, const AgentPlan& plan) {
  MapContent late(0);
  buildAgentMap(late, s, plan, nullptr);
  for (int k = plan.first; k <= plan.last; ++k) {
    ServerKeyframe kf = *late.keyframe(KeyframeId{plan.agent, static_cast<std::uint32_t>(k)});
    kf.point.assign(kf.keypoints.size(), MapPointId{});
    kf.has_point.assign(kf.keypoints.size(), 0);
    if (!map.write()->addKeyframe(std::move(kf)).ok()) return false;
  }
  return true;
}

bool eventually(const std::function<bool()>& done) {
  for (int i = 0; i < 6000; ++i) {
    if (done()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return false;
}

}  // namespace cvislam::server::backend::test_maps
