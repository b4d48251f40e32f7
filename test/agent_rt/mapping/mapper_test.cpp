// Mapping's keyframe pipeline on a synthetic scene with exact keypoints and one random descriptor per 3D
// point (so matching is by identity): the monocular two-view start, linking of tracking's matches, fusion of
// existing points by projection, triangulation of new points, culling, and the bound on own keyframes.
#include "agent_rt/mapping/mapper.hpp"

#include <cmath>
#include <memory>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/messages/conversions.hpp"
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
    options.retention.place_keyframes = 0;  // the newest only, unless a test asks for more
    options.ba.window = 4;
    options.ba.intrinsics = {calibration_.fx, calibration_.fy, calibration_.cx, calibration_.cy};
    options.imu_init_keyframes = 4;
    options.imu_init_max_keyframes = 6;
    options.mono_init_min_matches = 50;
    adjust(options);
    options_ = options;
    auto mapper = Mapper::create(options, *camera_, nullptr, T_s_c_, SE3d());
    ASSERT_TRUE(mapper.ok()) << mapper.error().toString();
    mapper_ = std::move(mapper.value());
    message_ = std::make_unique<KeyframeMessage>();
    snapshot_ = std::make_unique<MapSnapshotMessage>();
  }

  virtual void adjust(MapperOptions& /*options*/) {}

  // The camera looks along world z; keyframe k sits at x = 0.25 k, with a small yaw. `scale` scales the
  // camera's position (a monocular map is the scene up to scale about camera 0).
  [[nodiscard]] SE3d truePose(int k, double scale = 1.0) const {
    const SE3d T_w_c(SO3d::exp(Vector3d(0.0, 0.02 * k, 0.0)), scale * Vector3d(step_m_ * k, 0.02 * k, 0.0));
    return T_w_c * T_s_c_.inverse();
  }

  // A keyframe message seeing the scene from keyframe k's true pose; tracking's matches where `match_ids`
  // names a map point for a scene point.
  const KeyframeMessage& keyframe(int k, KeyframeKind kind, const SE3d& T_w_s_estimate,
                                  const std::vector<MapPointId>* match_ids = nullptr,
                                  const std::vector<bool>* detected = nullptr) {
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
      if (detected != nullptr && !(*detected)[i]) continue;
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
  double step_m_ = 0.25;  // sideways between keyframes k and k + 1
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

class MapperWithPlaceKeyframesTest : public MapperTest {
  void adjust(MapperOptions& options) override { options.retention.place_keyframes = 3; }
};

// Past the newest N (6), three older keyframes stay for their places: the map holds nine own keyframes at most,
// the first of them among them (no older keyframe covers its place), and the snapshot tracking gets holds them
// all.
TEST_F(MapperWithPlaceKeyframesTest, OlderKeyframesStayBesideTheNewestUpToTheirNumber) {
  ASSERT_TRUE(mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_).ok());
  auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_);
  ASSERT_TRUE(r2.ok());
  ASSERT_TRUE(r2->mono_initialised_now) << r2->note;
  // The map's scale: keyframe 2's distance from keyframe 0 in the map against the truth.
  double scale = 0.0;
  for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) {
    if (snapshot_->keyframes[i].id.counter != 2) continue;
    const SE3d T_w_s_0 = truePose(0);
    scale = (fromMsg(snapshot_->keyframes[i].T_w_s).translation() - T_w_s_0.translation()).norm() /
            (truePose(2).translation() - T_w_s_0.translation()).norm();
  }
  ASSERT_GT(scale, 0.0);
  std::size_t most = 0;
  for (int k = 3; k < 16; ++k) {
    ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale)), *snapshot_).ok());
    most = std::max(most, mapper_->map().keyframes().size());
  }
  EXPECT_EQ(most, 9u);
  EXPECT_EQ(snapshot_->keyframe_count, 9u);
  bool first_held = false;
  mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { first_held |= kf.id.counter == 0; });
  EXPECT_TRUE(first_held);
}

// Keyframes 5 cm apart, each detecting a random 60 % of the scene (a corner is not found in every image): the first
// ones lack the parallax, so the reference's keypoints are followed through them, each from the last keyframe
// that found it. The start comes once there is parallax; the keyframes between stay, placed on its points.
TEST_F(MapperTest, MonocularStartFollowsTheReferencesKeypointsAndKeepsTheKeyframesBetween) {
  step_m_ = 0.05;
  // Room for the keyframes that wait for the start (half the own keyframes).
  MapperOptions options = options_;
  options.max_keyframes = 12;
  auto mapper = Mapper::create(options, *camera_, nullptr, T_s_c_, SE3d());
  ASSERT_TRUE(mapper.ok());
  mapper_ = std::move(mapper.value());
  std::mt19937_64 rng(11);
  std::bernoulli_distribution found(0.6);
  std::vector<std::vector<bool>> detected(6, std::vector<bool>(scene_.p_w.size(), true));
  for (std::size_t k = 1; k < detected.size(); ++k) {
    for (std::size_t i = 0; i < scene_.p_w.size(); ++i) detected[k][i] = found(rng);
  }
  auto r0 = mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_);
  ASSERT_TRUE(r0.ok());
  const std::size_t visible = keypoint_point_.size();
  int started_at = -1;
  int created = 0;
  for (int k = 1; k < 6 && started_at < 0; ++k) {
    auto r = mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(0), nullptr, &detected[k]), *snapshot_);
    ASSERT_TRUE(r.ok());
    std::printf("keyframe %d: %s\n", k, r->note.c_str());
    if (r->mono_initialised_now) {
      started_at = k;
      created = r->triangulated;
    }
  }
  ASSERT_GE(started_at, 3) << "5 cm per keyframe: not enough parallax before keyframe 3";
  // A keypoint of the reference is among the start's points when the start's keyframe found it (60 %) and the
  // keyframes before did not all miss it for too long; followed only from the keyframe just before, it would take
  // being found in every one (0.6^k).
  EXPECT_GT(created, static_cast<int>(0.45 * static_cast<double>(visible)));

  // Every keyframe from the reference on is in the map, placed where the scene says (in the map's scale), with
  // observations of the start's points.
  ASSERT_EQ(snapshot_->keyframe_count, static_cast<std::uint32_t>(started_at + 1));
  const SE3d T_w_c0 = truePose(0) * T_s_c_;
  const Vector3d c_n = (T_w_c0.inverse() * truePose(started_at) * T_s_c_).translation();
  double scale = 0.0;
  for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) {
    const KeyframeStateMsg& kf = snapshot_->keyframes[i];
    if (kf.id.counter != static_cast<std::uint32_t>(started_at)) continue;
    scale = (T_w_c0.inverse() * fromMsg(kf.T_w_s) * T_s_c_).translation().norm() / c_n.norm();
  }
  ASSERT_GT(scale, 0.0);
  for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) {
    const KeyframeStateMsg& kf = snapshot_->keyframes[i];
    const int k = static_cast<int>(kf.id.counter);
    const SE3d T_c0_c = T_w_c0.inverse() * fromMsg(kf.T_w_s) * T_s_c_;
    const SE3d T_c0_c_true = T_w_c0.inverse() * truePose(k) * T_s_c_;
    EXPECT_LT((T_c0_c.translation() - scale * T_c0_c_true.translation()).norm(), 0.02 * scale * step_m_ * started_at)
        << "keyframe " << k;
    EXPECT_LT((T_c0_c.so3().inverse() * T_c0_c_true.so3()).log().norm(), 1e-3) << "keyframe " << k;
    int observations = 0;
    const KeyframeData* data = nullptr;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& d) {
      if (d.id == kf.id) data = &d;
    });
    ASSERT_NE(data, nullptr);
    for (std::uint16_t j = 0; j < data->keypoint_count; ++j) observations += data->has_map_point[j] ? 1 : 0;
    EXPECT_GT(observations, 50) << "keyframe " << k;
  }
}

// The two-phase path the agent takes by default: insert() hands the keyframe to the link before its local BA,
// refine() the refined map after it. Together they must build the same map as process() and tell the link the
// same things, only sooner: the first delta carries the keyframe in full with tracking's estimate, the second
// the states the BA moved.
TEST_F(MapperTest, InsertThenRefineSendsTheKeyframeBeforeItsLocalBaAndBuildsTheSameMapAsProcess) {
  auto split_mapper = Mapper::create(options_, *camera_, nullptr, T_s_c_, SE3d());
  ASSERT_TRUE(split_mapper.ok());
  Mapper& split = **split_mapper;
  auto split_snapshot = std::make_unique<MapSnapshotMessage>();
  auto whole = std::make_unique<MapDeltaMessage>();
  auto first = std::make_unique<MapDeltaMessage>();
  auto second = std::make_unique<MapDeltaMessage>();

  const auto both = [&](const KeyframeMessage& m) {
    auto one = mapper_->process(m, *snapshot_, whole.get());
    ASSERT_TRUE(one.ok()) << one.error().toString();
    auto inserted = split.insert(m, first.get());
    ASSERT_TRUE(inserted.ok()) << inserted.error().toString();
    split.refine(m, *inserted, *split_snapshot, second.get());
    EXPECT_EQ(inserted->ba_ran, one->ba_ran);
    EXPECT_EQ(inserted->triangulated, one->triangulated);
  };
  both(keyframe(0, KeyframeKind::kNewMap, truePose(0)));
  both(keyframe(2, KeyframeKind::kTracked, truePose(0)));
  ASSERT_EQ(snapshot_->keyframe_count, 2u);
  const Vector3d t0(snapshot_->keyframes[0].T_w_s.p[0], snapshot_->keyframes[0].T_w_s.p[1],
                    snapshot_->keyframes[0].T_w_s.p[2]);
  const Vector3d t2(snapshot_->keyframes[1].T_w_s.p[0], snapshot_->keyframes[1].T_w_s.p[1],
                    snapshot_->keyframes[1].T_w_s.p[2]);
  const double scale = (t2 - t0).norm() / (truePose(2).translation() - truePose(0).translation()).norm();

  const auto stateOf = [](const MapDeltaMessage& d, std::uint32_t counter) -> const KeyframeStateMsg* {
    for (std::uint16_t i = 0; i < d.keyframe_count; ++i) {
      if (d.keyframes[i].id.counter == counter) return &d.keyframes[i];
    }
    return nullptr;
  };
  const auto position = [](const PoseMsg& T) { return Vector3d(T.p[0], T.p[1], T.p[2]); };
  for (int k = 3; k < 10; ++k) {
    SCOPED_TRACE(k);
    // Tracking's estimate is 2 cm off (in the map's scale): the BA moves it.
    SE3d estimate = truePose(k, scale);
    estimate.translation() += Vector3d(0.02, -0.01, 0.015) * scale;
    both(keyframe(k, KeyframeKind::kTracked, estimate));
    const auto counter = static_cast<std::uint32_t>(k);

    // First delta: the keyframe whole, as tracking estimated it, with the points made with it.
    ASSERT_EQ(first->has_keyframe, 1);
    EXPECT_EQ(first->keyframe_before_local_ba, 1);  // the link tells the server that a refined state follows
    EXPECT_EQ(whole->keyframe_before_local_ba, 0);
    EXPECT_EQ(first->keyframe.id.counter, counter);
    EXPECT_LT((position(first->keyframe.T_w_s) - estimate.translation()).norm(), 1e-9);
    ASSERT_EQ(first->keypoint_count, whole->keypoint_count);
    for (std::uint16_t i = 0; i < whole->keypoint_count; ++i) {
      ASSERT_EQ(first->has_observation[i], whole->has_observation[i]) << i;
      if (whole->has_observation[i] != 0) {
        EXPECT_EQ(first->observation[i], whole->observation[i]) << i;
      }
    }
    ASSERT_EQ(first->new_point_count, whole->new_point_count);
    for (std::uint16_t i = 0; i < whole->new_point_count; ++i)
      EXPECT_EQ(first->new_points[i].id, whole->new_points[i].id);

    // Second delta: not the keyframe again, nothing new, but the refined states; every structural change of the
    // keyframe is in one of the two, in order.
    EXPECT_EQ(second->has_keyframe, 0);
    EXPECT_EQ(second->new_point_count, 0);
    ASSERT_EQ(first->event_count + second->event_count, whole->event_count);
    for (std::uint16_t i = 0; i < whole->event_count; ++i) {
      const MapEvent& e = i < first->event_count ? first->events[i] : second->events[i - first->event_count];
      EXPECT_EQ(e.type, whole->events[i].type) << i;
      EXPECT_EQ(e.point, whole->events[i].point) << i;
      EXPECT_EQ(e.keyframe, whole->events[i].keyframe) << i;
    }
    const KeyframeStateMsg* refined = stateOf(*second, counter);
    const KeyframeStateMsg* refined_whole = stateOf(*whole, counter);
    ASSERT_NE(refined, nullptr);
    ASSERT_NE(refined_whole, nullptr);
    EXPECT_GT((position(refined->T_w_s) - estimate.translation()).norm(), 0.002 * scale) << "the BA moved it";

    // The same map either way: the last delta's states and positions, and the snapshot for tracking.
    ASSERT_EQ(second->keyframe_count, whole->keyframe_count);
    for (std::uint16_t i = 0; i < whole->keyframe_count; ++i) {
      EXPECT_EQ(second->keyframes[i].id, whole->keyframes[i].id);
      EXPECT_LT((position(second->keyframes[i].T_w_s) - position(whole->keyframes[i].T_w_s)).norm(), 1e-9);
    }
    ASSERT_EQ(second->point_count, whole->point_count);
    for (std::uint32_t i = 0; i < whole->point_count; ++i) {
      EXPECT_EQ(second->points[i].id, whole->points[i].id);
      EXPECT_EQ(second->points[i].p_w, whole->points[i].p_w);
    }
    ASSERT_EQ(split_snapshot->point_count, snapshot_->point_count);
    ASSERT_EQ(split_snapshot->keyframe_count, snapshot_->keyframe_count);
  }
}

// Mapping behind tracking: with the next keyframe waiting, a keyframe's local BA is skipped, and one that is
// running stops when the next keyframe arrives; the keyframe itself is still taken into the map. Without the
// option, the waiting keyframe changes nothing.
TEST_F(MapperTest, AWaitingKeyframeSkipsOrCutsShortLocalBa) {
  const auto waiting = [] { return true; };
  ASSERT_TRUE(mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_).ok());
  auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_, nullptr, waiting);
  ASSERT_TRUE(r2.ok());
  ASSERT_TRUE(r2->mono_initialised_now) << r2->note;
  EXPECT_FALSE(r2->ba_skipped) << "the keyframe that makes the monocular map keeps its BA";
  EXPECT_TRUE(r2->ba_ran);
  double scale = 0.0;  // the map's, from the distance of keyframes 0 and 2 (0.25 m apart per step in truth)
  {
    std::vector<geometry::SE3d> poses;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { poses.push_back(kf.T_w_s); });
    ASSERT_EQ(poses.size(), 2U);
    scale = (poses[0].translation() - poses[1].translation()).norm() /
            (truePose(0).translation() - truePose(2).translation()).norm();
  }
  const std::uint32_t points_before = snapshot_->point_count;

  auto r3 = mapper_->process(keyframe(3, KeyframeKind::kTracked, truePose(3, scale)), *snapshot_, nullptr, waiting);
  ASSERT_TRUE(r3.ok()) << r3.error().toString();
  EXPECT_TRUE(r3->ba_skipped);
  EXPECT_FALSE(r3->ba_ran);
  EXPECT_EQ(mapper_->map().keyframes().size(), 3U) << "the keyframe itself must still be taken";
  EXPECT_GE(snapshot_->point_count, points_before);

  // Never two skipped in a row: with the next keyframe waiting again, keyframe 4's BA runs, for one iteration
  // (the first one is always taken; it is asked after each).
  int asked = 0;
  const auto still_waiting = [&asked] {
    ++asked;
    return true;
  };
  auto r4 =
      mapper_->process(keyframe(4, KeyframeKind::kTracked, truePose(4, scale)), *snapshot_, nullptr, still_waiting);
  ASSERT_TRUE(r4.ok()) << r4.error().toString();
  EXPECT_FALSE(r4->ba_skipped);
  ASSERT_TRUE(r4->ba_ran);
  EXPECT_TRUE(r4->ba.stopped_early);
  EXPECT_EQ(asked, 1);
  EXPECT_EQ(r4->ba.iterations, 1);

  // Arrives during the BA of keyframe 5 (the first ask is the skip check, the second after iteration 1).
  asked = 0;
  const auto arrives = [&asked] { return ++asked >= 3; };
  auto r5 = mapper_->process(keyframe(5, KeyframeKind::kTracked, truePose(5, scale)), *snapshot_, nullptr, arrives);
  ASSERT_TRUE(r5.ok()) << r5.error().toString();
  EXPECT_FALSE(r5->ba_skipped);
  ASSERT_TRUE(r5->ba_ran);
  EXPECT_TRUE(r5->ba.stopped_early);
  EXPECT_EQ(asked, 3);
  EXPECT_EQ(r5->ba.iterations, 2);
}

TEST_F(MapperTest, AWaitingKeyframeChangesNothingWithTheOptionOff) {
  options_.yield_to_waiting_keyframes = false;
  auto mapper = Mapper::create(options_, *camera_, nullptr, T_s_c_, SE3d());
  ASSERT_TRUE(mapper.ok()) << mapper.error().toString();
  mapper_ = std::move(mapper.value());
  ASSERT_TRUE(mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_).ok());
  int asked = 0;
  const auto waiting = [&asked] {
    ++asked;
    return true;
  };
  auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_, nullptr, waiting);
  ASSERT_TRUE(r2.ok());
  ASSERT_TRUE(r2->mono_initialised_now) << r2->note;
  EXPECT_FALSE(r2->ba_skipped);
  EXPECT_TRUE(r2->ba_ran);
  EXPECT_FALSE(r2->ba.stopped_early);
  EXPECT_EQ(asked, 0);
}

TEST_F(MapperTest, RefusesAnOversizedMessage) {
  KeyframeMessage& m = *message_;
  m = KeyframeMessage{};
  m.keypoint_count = static_cast<std::uint16_t>(kMaxKeypointsPerKeyframe + 1);
  auto r = mapper_->process(m, *snapshot_);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message().find("capacity"), std::string::npos);
}

// ---- The downlink: the server's covisible map as anchors, and corrections of the agent's own keyframes ----

// Another agent's keyframes and points as the server sends them: in this agent's world frame (here the scene
// in the monocular map's scale), observations in normalised coordinates, point ids of agent 7.
class MapperDownlinkTest : public MapperTest {
 protected:
  void adjust(MapperOptions& options) override { options.downlink.apply_corrections = true; }
  void SetUp() override {
    MapperTest::SetUp();
    downlink_ = std::make_unique<AnchorMessage>();
    ASSERT_TRUE(mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_).ok());
    auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_);
    ASSERT_TRUE(r2.ok() && r2->mono_initialised_now);
    // The map's scale: keyframe 2's distance from keyframe 0 against the truth's.
    const auto& kfs = mapper_->map().keyframes();
    std::vector<SE3d> poses;
    kfs.forEach([&](PoolHandle, const KeyframeData& kf) { poses.push_back(kf.T_w_s); });
    ASSERT_EQ(poses.size(), 2u);
    scale_ = (poses[1].translation() - poses[0].translation()).norm() /
             (truePose(2).translation() - truePose(0).translation()).norm();
    for (int k = 3; k <= 4; ++k)
      ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_).ok());
  }

  static MapPointId serverPoint(std::size_t j) { return MapPointId{7, static_cast<std::uint32_t>(j)}; }

  // Agent 7's keyframe at the pose of keyframe k of this agent's path, observing every scene point it sees.
  void addAnchor(AnchorMessage& m, int k, std::uint32_t counter, bool with_points = true) {
    AnchorKeyframeMsg& a = m.keyframes[m.keyframe_count++];
    a.id = KeyframeId{7, counter};
    a.t_ns = 1'000'000'000LL * (k + 1);
    const SE3d T_w_c = truePose(k, scale_) * T_s_c_;
    a.T_w_c = toMsg(T_w_c);
    a.observation_count = 0;
    const SE3d T_c_w_true = (truePose(k) * T_s_c_).inverse();
    for (std::size_t j = 0; j < scene_.p_w.size() && a.observation_count < kMaxKeypointsPerKeyframe; ++j) {
      const Vector3d p_c = T_c_w_true * scene_.p_w[j];
      const auto px = camera_->project(p_c);
      if (p_c.z() < 0.5 || !px || px->x() < 20 || px->y() < 20 || px->x() > 730 || px->y() > 460) continue;
      a.observations[a.observation_count++] = AnchorObservationMsg{
          static_cast<float>(p_c.x() / p_c.z()), static_cast<float>(p_c.y() / p_c.z()), serverPoint(j), 0};
      if (!with_points) continue;
      bool listed = false;
      for (std::uint32_t i = 0; i < m.point_count && !listed; ++i) listed = m.points[i].id == serverPoint(j);
      if (listed) continue;
      AnchorPointMsg& p = m.points[m.point_count++];
      p.id = serverPoint(j);
      const Vector3d p_w = scale_ * scene_.p_w[j];
      p.p_w = {p_w.x(), p_w.y(), p_w.z()};
      p.descriptor = scene_.descriptors[j];
    }
    m.selected[m.selected_count++] = a.id;
  }

  AnchorMessage& message(std::uint32_t stream, std::uint64_t sequence) {
    AnchorMessage& m = *downlink_;
    m = AnchorMessage{};
    m.stream = stream;
    m.sequence = sequence;
    m.has_covisible = 1;
    m.agent_map = 1;  // the map the fixture's keyframe 0 started
    return m;
  }

  [[nodiscard]] int anchorsHeld() const {
    int n = 0;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { n += kf.anchor ? 1 : 0; });
    return n;
  }
  [[nodiscard]] int serverPointsHeld() const {
    int n = 0;
    mapper_->map().mapPoints().forEach([&](PoolHandle, const MapPointData& p) { n += p.from_server ? 1 : 0; });
    return n;
  }
  [[nodiscard]] const KeyframeData* keyframeById(const KeyframeId& id) const {
    const KeyframeData* found = nullptr;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
      if (kf.id == id) found = &kf;
    });
    return found;
  }

  double scale_ = 1.0;
  std::unique_ptr<AnchorMessage> downlink_;
};

TEST_F(MapperDownlinkTest, AnAnchorFromAnotherAgentTakesPartInLocalBaWithoutMovingAndStaysOffTheUplink) {
  AnchorMessage& m = message(1, 1);
  addAnchor(m, 5, 100);
  addAnchor(m, 6, 101);
  auto applied = mapper_->applyDownlink(m);
  ASSERT_TRUE(applied.ok()) << applied.error().toString();
  EXPECT_EQ(applied->anchors_added, 2);
  EXPECT_EQ(applied->anchors_held, 2);
  EXPECT_GT(applied->points_added, 150);
  EXPECT_EQ(applied->unknown_references, 0);
  const SE3d anchor_before = keyframeById(KeyframeId{7, 100})->T_w_s;

  // The agent's next keyframe sees the same place: mapping finds the server's points in it, and local BA holds
  // the anchors fixed while their observations constrain the window. The estimate handed in is off by 3 cm.
  auto delta = std::make_unique<MapDeltaMessage>();
  SE3d estimate = truePose(5, scale_);
  estimate.translation() += Vector3d(0.03, -0.02, 0.01) * scale_;
  auto r5 = mapper_->process(keyframe(5, KeyframeKind::kTracked, estimate), *snapshot_, delta.get());
  ASSERT_TRUE(r5.ok()) << r5.error().toString();
  ASSERT_TRUE(r5->ba_ran);
  std::printf(
      "with anchors: fused %d, merged %d; BA %d window + %d fixed (%d anchors), %d factors of which %d by "
      "anchors\n",
      r5->fused, r5->merged, r5->ba.window_keyframes, r5->ba.fixed_keyframes, r5->ba.anchor_keyframes,
      r5->ba.reprojection_factors, r5->ba.anchor_factors);
  EXPECT_EQ(r5->ba.anchor_keyframes, 2);
  EXPECT_GT(r5->ba.anchor_factors, 100) << "the anchors' observations are residuals of local BA";
  const KeyframeData* anchor = keyframeById(KeyframeId{7, 100});
  ASSERT_NE(anchor, nullptr);
  // Held fixed by local BA. Not compared bit for bit: the frame bookkeeping re-expresses anchors with a change
  // that is the identity up to rounding, and on aarch64 (fused multiply-adds) that leaves 1e-19 m.
  EXPECT_LT((anchor->T_w_s.translation() - anchor_before.translation()).norm(), 1e-12) << "held fixed";
  EXPECT_LT((anchor->T_w_s.so3().inverse() * anchor_before.so3()).log().norm(), 1e-12);
  const KeyframeData* own = keyframeById(KeyframeId{0, 5});
  ASSERT_NE(own, nullptr);
  EXPECT_LT((own->T_w_s.translation() - truePose(5, scale_).translation()).norm(), 0.005 * scale_)
      << "the window keyframe is pulled onto the anchors' map";

  // The server's points that duplicated the agent's went into the agent's (the anchors observe those now); the
  // rest are in the snapshot, for tracking to match.
  EXPECT_GT(r5->merged, 150);
  int server_in_snapshot = 0;
  for (std::uint32_t i = 0; i < snapshot_->point_count; ++i) server_in_snapshot += snapshot_->points[i].id.agent == 7;
  EXPECT_GT(server_in_snapshot, 0);
  EXPECT_EQ(server_in_snapshot, serverPointsHeld());
  // The snapshot marks the anchors, so that nothing records them as this agent's keyframes (their counters are
  // another agent's).
  int anchors_marked = 0;
  for (std::uint16_t i = 0; i < snapshot_->keyframe_count; ++i) {
    EXPECT_EQ(snapshot_->keyframe_is_anchor[i] != 0, snapshot_->keyframes[i].id.agent == 7) << i;
    anchors_marked += snapshot_->keyframe_is_anchor[i];
  }
  EXPECT_EQ(anchors_marked, 2);

  // Nothing of the server's goes back up: no anchor state, no server point, no event or observation of one.
  for (std::uint16_t i = 0; i < delta->keyframe_count; ++i) EXPECT_EQ(delta->keyframes[i].id.agent, 0) << i;
  for (std::uint32_t i = 0; i < delta->point_count; ++i) EXPECT_EQ(delta->points[i].id.agent, 0) << i;
  for (std::uint16_t i = 0; i < delta->event_count; ++i) {
    EXPECT_EQ(delta->events[i].keyframe.agent, 0) << i;
    EXPECT_EQ(delta->events[i].point.agent, 0) << i;
    EXPECT_EQ(delta->events[i].other.agent, 0) << i;
  }
  ASSERT_EQ(delta->has_keyframe, 1);
  for (std::uint16_t k = 0; k < delta->keypoint_count; ++k) {
    if (delta->has_observation[k] != 0) {
      EXPECT_EQ(delta->observation[k].agent, 0) << k;
    }
  }
}

class MapperDownlinkWithPlaceKeyframesTest : public MapperDownlinkTest {
  void adjust(MapperOptions& options) override { options.retention.place_keyframes = 3; }
};

// Alone, the map keeps three older keyframes for their places beside the newest six; once the server's covisible
// map is held, it keeps the newest six only, and the oldest go.
TEST_F(MapperDownlinkWithPlaceKeyframesTest, TheServersMapTakesThePlaceOfTheOlderKeyframes) {
  const auto own = [&] {
    int n = 0;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { n += kf.anchor ? 0 : 1; });
    return n;
  };
  for (int k = 5; k <= 12; ++k) {
    ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_).ok());
  }
  ASSERT_EQ(own(), 9);
  ASSERT_NE(keyframeById(KeyframeId{0, 0}), nullptr);  // no older keyframe covers the first one's place
  AnchorMessage& m = message(1, 1);
  addAnchor(m, 12, 100);
  ASSERT_TRUE(mapper_->applyDownlink(m).ok());
  ASSERT_EQ(anchorsHeld(), 1);
  auto r13 = mapper_->process(keyframe(13, KeyframeKind::kTracked, truePose(13, scale_)), *snapshot_);
  ASSERT_TRUE(r13.ok());
  EXPECT_EQ(r13->evicted, 4);  // room for the new keyframe among the newest six
  EXPECT_EQ(own(), 6);
  EXPECT_EQ(keyframeById(KeyframeId{0, 0}), nullptr);
  EXPECT_NE(keyframeById(KeyframeId{0, 8}), nullptr);  // the newest six: 8-13
}

TEST_F(MapperDownlinkTest, MessagesTwiceOutOfOrderOrReferringToWhatTheAgentLetGoAreHandled) {
  AnchorMessage& m = message(1, 5);
  addAnchor(m, 5, 100);
  ASSERT_TRUE(mapper_->applyDownlink(m).ok());
  const int points = serverPointsHeld();
  ASSERT_GT(points, 100);

  // The same message again: stale, nothing changes.
  auto twice = mapper_->applyDownlink(m);
  ASSERT_TRUE(twice.ok());
  EXPECT_TRUE(twice->stale);
  // Its content again under a newer sequence (a resend): the anchor is held already, nothing is added twice.
  m.sequence = 6;
  auto resent = mapper_->applyDownlink(m);
  ASSERT_TRUE(resent.ok());
  EXPECT_FALSE(resent->stale);
  EXPECT_EQ(resent->anchors_added, 0);
  EXPECT_EQ(serverPointsHeld(), points);
  // An older one arriving late: ignored.
  AnchorMessage& late = message(1, 4);
  addAnchor(late, 6, 200);
  auto older = mapper_->applyDownlink(late);
  ASSERT_TRUE(older.ok());
  EXPECT_TRUE(older->stale);
  EXPECT_EQ(anchorsHeld(), 1);

  // Updates of a keyframe and points the agent does not hold, and a keyframe observing points that are in
  // neither the message nor the map (the agent let them go): skipped, counted, the rest applied.
  AnchorMessage& next = message(1, 7);
  next.selected[next.selected_count++] = KeyframeId{7, 100};
  addAnchor(next, 6, 201, /*with_points=*/false);
  next.keyframe_updates[next.keyframe_update_count++] = AnchorPoseUpdateMsg{KeyframeId{7, 999}, toMsg(SE3d())};
  next.point_updates[next.point_update_count++] = AnchorPointUpdateMsg{MapPointId{7, 99999}, {1.0, 2.0, 3.0}};
  auto partial = mapper_->applyDownlink(next);
  ASSERT_TRUE(partial.ok());
  EXPECT_EQ(partial->anchors_added, 1);
  EXPECT_GE(partial->unknown_references, 2);
  EXPECT_GT(partial->points_linked, 50) << "the new anchor's points held already are linked to it";
  EXPECT_EQ(anchorsHeld(), 2);

  // A new stream (the link reconnected) starts its sequences again; its selection drops keyframe 100, which
  // leaves with the points only it observed.
  AnchorMessage& reconnected = message(2, 1);
  reconnected.selected[reconnected.selected_count++] = KeyframeId{7, 201};
  auto after = mapper_->applyDownlink(reconnected);
  ASSERT_TRUE(after.ok());
  EXPECT_FALSE(after->stale);
  EXPECT_EQ(after->anchors_released, 1);
  EXPECT_EQ(anchorsHeld(), 1);
  EXPECT_LT(serverPointsHeld(), points);
  EXPECT_GT(serverPointsHeld(), 0) << "points keyframe 201 observes stay";

  // A covisible map in another agent map's frame is not used.
  AnchorMessage& other_map = message(2, 2);
  other_map.agent_map = 5;
  addAnchor(other_map, 6, 300);
  auto skipped = mapper_->applyDownlink(other_map);
  ASSERT_TRUE(skipped.ok());
  EXPECT_NE(skipped->skipped.find("agent map 5"), std::string::npos) << skipped->skipped;
  EXPECT_EQ(anchorsHeld(), 1);

  // Counts beyond the message's capacities (a corrupt chunk): refused, nothing applied.
  AnchorMessage& corrupt = message(2, 3);
  corrupt.point_count = static_cast<std::uint32_t>(kMaxAnchorPointsPerMessage + 1);
  EXPECT_FALSE(mapper_->applyDownlink(corrupt).ok());
  EXPECT_EQ(anchorsHeld(), 1);

  // The local map's next keyframe is processed as before.
  auto r = mapper_->process(keyframe(5, KeyframeKind::kTracked, truePose(5, scale_)), *snapshot_);
  ASSERT_TRUE(r.ok());
  EXPECT_GT(r->fused, 50);
}

TEST_F(MapperDownlinkTest, CorrectionsMoveOwnKeyframesOutsideTheLocalWindowAndTheNextKeyframesGoOn) {
  for (int k = 5; k <= 6; ++k) {
    ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_).ok());
  }
  // Own keyframes 0, 2, 3, 4, 5, 6 (6 = N); the window (4) is 3..6, so 0 and 2 are outside it. The server
  // removed drift that grows with age (none at the newest), and its frame for this agent is 5 cm off the
  // agent's (a merge's error): the offset is taken out, the drift is applied.
  AnchorMessage& m = message(1, 1);
  m.has_covisible = 0;
  const Vector3d drift = Vector3d(0.02, 0.0, -0.01) * scale_;  // at keyframe 0
  const Vector3d offset(0.05, -0.03, 0.01);
  const auto drift_at = [&](std::uint32_t k) { return drift * (6.0 - k) / 6.0; };
  for (std::uint32_t k : {0U, 2U, 3U, 4U, 5U, 6U, 77U}) {
    const KeyframeData* kf = keyframeById(KeyframeId{0, k});
    KeyframeStateMsg& c = m.corrections[m.correction_count++];
    c.id = KeyframeId{0, k};
    SE3d T = kf != nullptr ? kf->T_w_s : SE3d();
    T.translation() += drift_at(k) + offset;
    c.T_w_s = toMsg(T);
  }
  const SE3d before_3 = keyframeById(KeyframeId{0, 3})->T_w_s;
  const SE3d before_0 = keyframeById(KeyframeId{0, 0})->T_w_s;
  auto applied = mapper_->applyDownlink(m);
  ASSERT_TRUE(applied.ok());
  EXPECT_EQ(applied->corrections_applied, 2);
  EXPECT_EQ(applied->corrections_deferred, 4) << "in the window";
  EXPECT_EQ(applied->corrections_skipped, 1) << "no longer in the map";
  EXPECT_NEAR(applied->frame_change_m, offset.norm(), 1e-9) << "the newest corrected keyframe keeps its pose";
  EXPECT_NEAR(applied->largest_correction_m, drift.norm(), 1e-9);
  EXPECT_NEAR((keyframeById(KeyframeId{0, 0})->T_w_s.translation() - before_0.translation() - drift).norm(), 0.0,
              1e-12);
  EXPECT_EQ((keyframeById(KeyframeId{0, 3})->T_w_s.translation() - before_3.translation()).norm(), 0.0)
      << "the window keeps its own states while it is the window";

  // The next keyframes are processed against the corrected map: points found, local BA converging.
  for (int k = 7; k <= 8; ++k) {
    auto r = mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_);
    ASSERT_TRUE(r.ok()) << r.error().toString();
    EXPECT_GT(r->fused, 50) << k;
    EXPECT_TRUE(r->ba_ran);
    EXPECT_LE(r->ba.final_cost, r->ba.initial_cost);
    if (k == 7) {
      EXPECT_NEAR((keyframeById(KeyframeId{0, 3})->T_w_s.translation() - before_3.translation() - drift_at(3)).norm(),
                  0.0, 1e-12)
          << "keyframe 3 left the window and took the server's state, held fixed since";
    }
  }
}

TEST(MapperOptions, NamesBadValues) {
  MapperOptions o;
  o.max_keyframes = 1;
  EXPECT_NE(o.validate().error().message().find("max_keyframes"), std::string::npos);
  o = MapperOptions{};
  o.ba.window = 30;
  EXPECT_NE(o.validate().error().message().find("window"), std::string::npos);
  o = MapperOptions{};
  EXPECT_TRUE(o.downlink.use_anchors);
  EXPECT_FALSE(o.downlink.apply_corrections) << "corrections are opt-in (docs/agent.md: when they help)";
  o.downlink.max_anchor_keyframes = 1000;
  EXPECT_NE(o.validate().error().message().find("max_anchor_keyframes"), std::string::npos);
  o = MapperOptions{};
  o.downlink.max_anchor_points = -1;
  EXPECT_NE(o.validate().error().message().find("max_anchor_points"), std::string::npos);
  o = MapperOptions{};
  o.imu_init_full_window_keyframes = -1;
  EXPECT_NE(o.validate().error().message().find("imu_init_full_window_keyframes"), std::string::npos);
  o = MapperOptions{};
  o.mono_init_search_radius_px = 0.0;
  EXPECT_NE(o.validate().error().message().find("mono_init_search_radius_px"), std::string::npos);
  o = MapperOptions{};
  o.mono_init_ratio = 1.5;
  EXPECT_NE(o.validate().error().message().find("mono_init_ratio"), std::string::npos);
  o = MapperOptions{};
  o.mono_init_max_distance = 300;
  EXPECT_NE(o.validate().error().message().find("mono_init_max_distance"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::agent
