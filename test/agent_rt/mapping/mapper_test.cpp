// Mapping's keyframe pipeline on a synthetic scene with exact keypoints and one random descriptor per 3D
// point (so matching is by identity): the monocular two-view start, linking of tracking's matches, fusion of
// existing points by projection, triangulation of new points, culling, and the bound on own keyframes.
#include "agent_rt/mapping/mapper.hpp"

#include <cmath>
#include <memory>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/runtime/message_conversions.hpp"
#include "common/dataset/euroc_calibration.hpp"

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

struct Scene {
  std::vector<Vector3d> p_w;
  std::vector<std::array<std::uint8_t, 32>> descriptors;
};

Scene makeScene(int points, std::uint64_t seed) {
  Scene s;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> x(-4.0, 4.0);
  std::uniform_real_distribution<double> y(-3.0, 3.0);
  std::uniform_real_distribution<double> z(4.0, 9.0);
  std::uniform_int_distribution<int> byte(0, 255);
  for (int i = 0; i < points; ++i) {
    s.p_w.emplace_back(x(rng), y(rng), z(rng));
    std::array<std::uint8_t, 32> d{};
    for (auto& b : d) b = static_cast<std::uint8_t>(byte(rng));
    s.descriptors.push_back(d);
  }
  return s;
}

class MapperTest : public ::testing::Test {
 protected:
  void SetUp() override {
    calibration_ = dataset::eurocCam0();
    calibration_.distortion = dataset::DistortionModel::kNone;
    camera_.emplace(camera::CameraModel::create(calibration_).value());
    T_s_c_ = calibration_.T_b_c;
    MapperOptions options;
    options.use_imu = false;
    options.max_keyframes = 6;
    options.ba.window = 4;
    options.ba.intrinsics = {calibration_.fx, calibration_.fy, calibration_.cx, calibration_.cy};
    options.imu_init_keyframes = 4;
    options.imu_init_max_keyframes = 6;
    options.mono_init_min_matches = 50;
    options_ = options;
    auto mapper = Mapper::create(options, *camera_, nullptr, T_s_c_, SE3d());
    ASSERT_TRUE(mapper.ok()) << mapper.error().toString();
    mapper_ = std::move(mapper.value());
    message_ = std::make_unique<KeyframeMessage>();
    snapshot_ = std::make_unique<MapSnapshotMessage>();
  }

  // The camera looks along world z; keyframe k sits at x = 0.25 k, with a small yaw. `scale` scales the
  // camera's position (a monocular map is the scene up to scale about camera 0).
  [[nodiscard]] SE3d truePose(int k, double scale = 1.0) const {
    const SE3d T_w_c(SO3d::exp(Vector3d(0.0, 0.02 * k, 0.0)), scale * Vector3d(0.25 * k, 0.02 * k, 0.0));
    return T_w_c * T_s_c_.inverse();
  }

  // A keyframe message seeing the scene from keyframe k's true pose; tracking's matches where `match_ids`
  // names a map point for a scene point.
  const KeyframeMessage& keyframe(int k, KeyframeKind kind, const SE3d& T_w_s_estimate,
                                  const std::vector<MapPointId>* match_ids = nullptr) {
    KeyframeMessage& m = *message_;
    m = KeyframeMessage{};
    m.sequence = static_cast<std::uint64_t>(k);
    m.kind = kind;
    m.state.id = KeyframeId{0, static_cast<std::uint32_t>(k)};
    m.state.t_ns = 1'000'000'000LL * (k + 1);
    m.state.T_w_s = toMsg(T_w_s_estimate);
    const SE3d T_c_w = (truePose(k) * T_s_c_).inverse();
    keypoint_point_.clear();
    for (std::size_t i = 0; i < scene_.p_w.size() && m.keypoint_count < kMaxKeypointsPerKeyframe; ++i) {
      const Vector3d p_c = T_c_w * scene_.p_w[i];
      const auto px = camera_->project(p_c);
      if (p_c.z() < 0.5 || !px || px->x() < 20 || px->y() < 20 || px->x() > 730 || px->y() > 460) continue;
      const std::uint16_t k_index = m.keypoint_count++;
      m.keypoints[k_index] = KeypointMsg{static_cast<float>(px->x()), static_cast<float>(px->y()), 1.0F, 0.0F, 0};
      m.descriptors[k_index] = scene_.descriptors[i];
      if (match_ids != nullptr && (*match_ids)[i].counter != 0xFFFFFFFF) {
        m.matched[k_index] = (*match_ids)[i];
        m.has_match[k_index] = 1;
      }
      keypoint_point_.push_back(i);
    }
    return m;
  }

  dataset::CameraCalibration calibration_;
  std::optional<camera::CameraModel> camera_;
  SE3d T_s_c_;
  MapperOptions options_;
  std::unique_ptr<Mapper> mapper_;
  std::unique_ptr<KeyframeMessage> message_;
  std::unique_ptr<MapSnapshotMessage> snapshot_;
  std::vector<std::size_t> keypoint_point_;
  Scene scene_ = makeScene(400, 3);
};

TEST_F(MapperTest, MonocularStartLinkFuseTriangulateAndBound) {
  // Keyframe 0 starts the map; keyframe 1 is too close (no parallax) ... keyframe 2 initialises.
  auto r0 = mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_);
  ASSERT_TRUE(r0.ok()) << r0.error().toString();
  EXPECT_TRUE(r0->new_map);
  EXPECT_EQ(snapshot_->point_count, 0u);  // no map yet: tracking keeps waiting
  auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_);
  ASSERT_TRUE(r2.ok());
  ASSERT_TRUE(r2->mono_initialised_now) << r2->note;
  ASSERT_GT(snapshot_->point_count, 200u);

  // The map is the scene up to one scale: compare each point's position relative to keyframe 0's camera.
  const SE3d T_c0_w_true = (truePose(0) * T_s_c_).inverse();
  std::vector<double> ratios;
  for (std::uint32_t i = 0; i < snapshot_->point_count; ++i) {
    const MapPointMsg& p = snapshot_->points[i];
    // Points are made from matches of keyframe 0 and 2; find the scene point by descriptor.
    for (std::size_t j = 0; j < scene_.p_w.size(); ++j) {
      if (scene_.descriptors[j] != p.descriptor) continue;
      const Vector3d estimate = (truePose(0) * T_s_c_).inverse() * Vector3d(p.p_w[0], p.p_w[1], p.p_w[2]);
      const Vector3d truth = T_c0_w_true * scene_.p_w[j];
      ratios.push_back(estimate.norm() / truth.norm());
      EXPECT_LT(geometry::rayAngle(estimate, truth), 1e-3);
    }
  }
  ASSERT_GT(ratios.size(), 200u);
  double mean = 0.0;
  for (double r : ratios) mean += r / static_cast<double>(ratios.size());
  double spread = 0.0;
  for (double r : ratios) spread = std::max(spread, std::abs(r / mean - 1.0));
  std::printf("two-view map: %zu points, scale %.3f, largest relative depth error %.4f\n", ratios.size(), mean, spread);
  EXPECT_LT(spread, 0.01);

  // Keyframe 3 arrives with tracking's matches for every scene point the map holds (by descriptor).
  std::vector<MapPointId> ids(scene_.p_w.size(), MapPointId{0, 0xFFFFFFFF});
  for (std::uint32_t i = 0; i < snapshot_->point_count; ++i) {
    for (std::size_t j = 0; j < scene_.p_w.size(); ++j) {
      if (scene_.descriptors[j] == snapshot_->points[i].descriptor) ids[j] = snapshot_->points[i].id;
    }
  }
  const SE3d T_w_s_3 = truePose(3, mean);  // in the map's scale
  auto r3 = mapper_->process(keyframe(3, KeyframeKind::kTracked, T_w_s_3, &ids), *snapshot_);
  ASSERT_TRUE(r3.ok());
  int expected_links = 0;
  for (std::size_t i : keypoint_point_) expected_links += ids[i].counter != 0xFFFFFFFF ? 1 : 0;
  EXPECT_EQ(r3->linked, expected_links);
  EXPECT_GT(r3->triangulated, 0);  // scene points keyframes 0/2 did not share, seen again from 3
  // Every point of the map, old or new, sits where the scene has it (in the map's scale) after local BA.
  int checked = 0;
  for (std::uint32_t i = 0; i < snapshot_->point_count; ++i) {
    const MapPointMsg& p = snapshot_->points[i];
    for (std::size_t j = 0; j < scene_.p_w.size(); ++j) {
      if (scene_.descriptors[j] != p.descriptor) continue;
      const Vector3d estimate(p.p_w[0], p.p_w[1], p.p_w[2]);
      EXPECT_LT((estimate - mean * scene_.p_w[j]).norm(), 0.01 * mean * scene_.p_w[j].norm()) << "point " << j;
      ++checked;
    }
  }
  EXPECT_EQ(checked, static_cast<int>(snapshot_->point_count));

  // Keyframe 4 comes without tracking's matches: fusion finds the map's points by projection.
  const std::uint32_t points_before = snapshot_->point_count;
  const SE3d T_w_s_4 = truePose(4, mean);
  auto r4 = mapper_->process(keyframe(4, KeyframeKind::kTracked, T_w_s_4), *snapshot_);
  ASSERT_TRUE(r4.ok());
  std::printf("keyframe 3: linked %d, triangulated %d; keyframe 4: fused %d of %u points\n", r3->linked,
              r3->triangulated, r4->fused, points_before);
  EXPECT_GT(r4->fused, static_cast<int>(0.6 * points_before));
  EXPECT_EQ(r4->triangulated, 0);  // every keypoint was fused to an existing point: nothing duplicated

  // Own keyframes stay bounded by max_keyframes (6): the oldest go.
  for (int k = 5; k < 12; ++k) {
    const SE3d T = truePose(k, mean);
    ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, T), *snapshot_).ok());
    EXPECT_LE(mapper_->map().keyframes().size(), 6u);
  }
  EXPECT_EQ(snapshot_->keyframe_count, 6u);
}

TEST_F(MapperTest, RefusesAnOversizedMessage) {
  KeyframeMessage& m = *message_;
  m = KeyframeMessage{};
  m.keypoint_count = static_cast<std::uint16_t>(kMaxKeypointsPerKeyframe + 1);
  auto r = mapper_->process(m, *snapshot_);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message().find("capacity"), std::string::npos);
}

TEST(MapperOptions, NamesBadValues) {
  MapperOptions o;
  o.max_keyframes = 1;
  EXPECT_NE(o.validate().error().message().find("max_keyframes"), std::string::npos);
  o = MapperOptions{};
  o.ba.window = 30;
  EXPECT_NE(o.validate().error().message().find("window"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::agent
