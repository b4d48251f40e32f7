// Mapping's keyframe pipeline on the synthetic scene of mapper_fixture.hpp: the monocular two-view start, linking
// of tracking's matches, fusion of existing points by projection, triangulation of new points, culling, the bound
// on own keyframes and the older ones kept for their places, mapping that yields, and bad options. What the server
// sends down: mapper_downlink_test.cpp.
#include <cmath>
#include <cstdio>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "test/agent_rt/mapping/mapper_fixture.hpp"

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

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
 protected:
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

// The camera goes 2.5 m sideways (keyframes 0-10) and comes back (11-20). The scene's points are in three sets, and
// each keyframe detects some of them: A at the start (0-6) and again on the way back (15-20), B in between (4-9),
// C from 7 on. So the windows of keyframes 10-14 hold fixed keyframes from 4 on (B and C) at the oldest; keyframe
// 0, kept for its place, sees A only. At keyframe 15 A is found again: the window holds keyframe 0, 2 x N = 12
// keyframes or more before it, where the last one held nothing older than keyframe 8. That BA reports the return, and
// the next three (return_full_window_keyframes) take all N = 6 newest keyframes instead of the window's M = 4.
class MapperReturnToPlaceTest : public MapperWithPlaceKeyframesTest {
  void adjust(MapperOptions& options) override {
    MapperWithPlaceKeyframesTest::adjust(options);
    options.return_full_window_keyframes = return_bas_;
  }

 protected:
  // Per keyframe from 3 on: the BA's window, the age of its oldest fixed keyframe, and whether it reported a return.
  struct Step {
    int window = 0;
    std::uint64_t oldest_fixed_age = 0;
    bool returned = false;
  };
  // `out_of_view`: the sets above; otherwise every keyframe detects every point, and keyframe 0 is never out of view.
  std::vector<Step> flyOutAndBack(bool out_of_view) {
    for (int k = 0; k <= 10; ++k) x_m_.push_back(0.25 * k);
    for (int k = 11; k <= 20; ++k) x_m_.push_back(0.25 * (20 - k));
    const auto detects = [&](int k) {
      std::vector<bool> d(scene_.p_w.size(), true);
      if (!out_of_view) return d;
      for (std::size_t i = 0; i < d.size(); ++i) {
        const std::size_t set = i % 3;  // A, B, C
        d[i] = (set == 0 && (k <= 6 || k >= 15)) || (set == 1 && k >= 4 && k <= 9) || (set == 2 && k >= 7);
      }
      return d;
    };
    std::vector<bool> d = detects(0);
    EXPECT_TRUE(mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0), nullptr, &d), *snapshot_).ok());
    d = detects(2);
    auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0), nullptr, &d), *snapshot_);
    EXPECT_TRUE(r2.ok() && r2->mono_initialised_now);
    double scale = 0.0;  // the map's: keyframe 2's distance from keyframe 0 in the map against the truth
    for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) {
      if (snapshot_->keyframes[i].id.counter != 2) continue;
      scale = (fromMsg(snapshot_->keyframes[i].T_w_s).translation() - truePose(0).translation()).norm() /
              (truePose(2).translation() - truePose(0).translation()).norm();
    }
    EXPECT_GT(scale, 0.0);
    std::vector<Step> steps;
    for (int k = 3; k <= 20; ++k) {
      d = detects(k);
      auto r = mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale), nullptr, &d), *snapshot_);
      EXPECT_TRUE(r.ok()) << "keyframe " << k;
      if (!r.ok()) break;
      EXPECT_TRUE(r->ba_ran) << "keyframe " << k;
      const std::optional<std::uint64_t>& oldest = r->ba.oldest_fixed_sequence;
      steps.push_back({r->ba.window_keyframes, oldest ? r->ba.newest_sequence - *oldest : 0, r->returned_to_place});
      std::printf("keyframe %2d: window %d, oldest fixed %llu keyframes back%s\n", k, steps.back().window,
                  static_cast<unsigned long long>(steps.back().oldest_fixed_age),
                  r->returned_to_place ? ", return" : "");
    }
    return steps;
  }
  int return_bas_ = 3;
};

TEST_F(MapperReturnToPlaceTest, AKeyframeFromLongAgoBackInViewMakesTheNextBasTakeTheNewestMap) {
  const std::vector<Step> steps = flyOutAndBack(true);
  ASSERT_EQ(steps.size(), 18u);
  const auto at = [&](int k) { return steps[static_cast<std::size_t>(k - 3)]; };
  for (int k = 10; k <= 14; ++k) {
    EXPECT_LT(at(k).oldest_fixed_age, 12u) << "keyframe " << k << ": nothing from long ago";
  }
  int returns = 0;
  for (const Step& step : steps) returns += step.returned ? 1 : 0;
  EXPECT_EQ(returns, 1);
  EXPECT_TRUE(at(15).returned);
  EXPECT_GE(at(15).oldest_fixed_age, 12u);
  EXPECT_EQ(at(15).window, 4) << "the BA that finds the return is a window's";
  for (int k = 16; k <= 18; ++k) EXPECT_EQ(at(k).window, 6) << "keyframe " << k;
  for (int k = 19; k <= 20; ++k) EXPECT_EQ(at(k).window, 4) << "keyframe " << k;
}

// Keyframe 0 never leaves the view: from keyframe 13 on the window holds it, 12 keyframes back and more, but only
// because it ages. No return, and every BA is the window's.
TEST_F(MapperReturnToPlaceTest, AKeyframeThatNeverLeftTheViewOnlyAges) {
  const std::vector<Step> steps = flyOutAndBack(false);
  ASSERT_EQ(steps.size(), 18u);
  EXPECT_GE(steps.back().oldest_fixed_age, 12u);
  for (const Step& step : steps) {
    EXPECT_LE(step.window, 4);
    EXPECT_FALSE(step.returned);
  }
}

class MapperReturnToPlaceOffTest : public MapperReturnToPlaceTest {
 protected:
  MapperReturnToPlaceOffTest() { return_bas_ = 0; }
};

TEST_F(MapperReturnToPlaceOffTest, WithTheOptionOffEveryBaIsTheWindows) {
  for (const Step& step : flyOutAndBack(true)) {
    EXPECT_LE(step.window, 4);
    EXPECT_FALSE(step.returned);
  }
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

TEST_F(MapperTest, MonocularStartFromAKeyframeAfterTheReferenceWhenTheCameraCameBackNearIt) {
  // Sideways 0, -0.1, +0.1 m: each keyframe is 0.1 m from the reference, a median parallax of about 0.75 deg, too
  // little for the start (1 deg), but the last two are 0.2 m apart.
  x_m_ = {0.0, -0.1, 0.1};
  auto r0 = mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_);
  ASSERT_TRUE(r0.ok());
  auto r1 = mapper_->process(keyframe(1, KeyframeKind::kTracked, truePose(0)), *snapshot_);
  ASSERT_TRUE(r1.ok());
  ASSERT_FALSE(r1->mono_initialised_now) << r1->note;
  auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_);
  ASSERT_TRUE(r2.ok());
  ASSERT_TRUE(r2->mono_initialised_now) << r2->note;
  EXPECT_NE(r2->note.find("the first 1 after the reference"), std::string::npos) << r2->note;
  EXPECT_GT(r2->triangulated, 200);

  // All three keyframes are in the map, the reference placed on the start's points: the IMU chain starts there.
  // Positions about keyframe 1's camera (the map's first view) agree with the truth up to the map's one scale.
  ASSERT_EQ(snapshot_->keyframe_count, 3u);
  std::vector<SE3d> T_w_c(3);
  for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) {
    const KeyframeStateMsg& kf = snapshot_->keyframes[i];
    T_w_c[kf.id.counter] = fromMsg(kf.T_w_s) * T_s_c_;
  }
  const auto relative = [&](int k) { return T_w_c[1].inverse() * T_w_c[static_cast<std::size_t>(k)]; };
  const auto relative_true = [&](int k) { return (truePose(1) * T_s_c_).inverse() * truePose(k) * T_s_c_; };
  const double scale = relative(2).translation().norm() / relative_true(2).translation().norm();
  for (int k : {0, 2}) {
    EXPECT_LT((relative(k).translation() - scale * relative_true(k).translation()).norm(), 0.02 * scale * 0.2)
        << "keyframe " << k;
    EXPECT_LT((relative(k).so3().inverse() * relative_true(k).so3()).log().norm(), 1e-3) << "keyframe " << k;
  }
}

// A slow start (5 cm a keyframe) whose keyframe 2 finds only an eighth of the reference's keypoints, fewer than
// the 50 a start needs, so that it becomes the reference; keyframes 0 and 1 saw that eighth too. Each keyframe's
// mapper note in `notes`; returns the keyframe that started the map, -1 none by keyframe 7.
class MapperNewReferenceTest : public MapperTest {
 protected:
  int run(int max_keyframes, std::vector<std::string>& notes) {
    step_m_ = 0.05;
    MapperOptions options = options_;
    options.max_keyframes = max_keyframes;  // twice the keyframes that may wait for the start
    auto mapper = Mapper::create(options, *camera_, nullptr, T_s_c_, SE3d());
    EXPECT_TRUE(mapper.ok());
    if (!mapper.ok()) return -1;
    mapper_ = std::move(mapper.value());
    const std::size_t n = scene_.p_w.size();
    std::vector<std::vector<bool>> detected(8, std::vector<bool>(n, true));
    for (std::size_t i = 0; i < n; ++i) {
      detected[0][i] = i % 4 != 0;
      detected[2][i] = i % 4 == 0 || i % 8 == 1;  // the eighth i % 8 == 1 shared with keyframe 0
    }
    for (int k = 0; k < 8; ++k) {
      const KeyframeKind kind = k == 0 ? KeyframeKind::kNewMap : KeyframeKind::kTracked;
      auto r =
          mapper_->process(keyframe(k, kind, truePose(0), nullptr, &detected[static_cast<std::size_t>(k)]), *snapshot_);
      EXPECT_TRUE(r.ok());
      if (!r.ok()) return -1;
      std::printf("keyframe %d: %s\n", k, r->note.c_str());
      notes.push_back(r->note);
      if (r->mono_initialised_now) return k;
    }
    return -1;
  }
};

TEST_F(MapperNewReferenceTest, KeepsTheKeyframesBeforeItThatShareEnoughOfItsKeypoints) {
  std::vector<std::string> notes;
  const int started_at = run(16, notes);
  ASSERT_GT(started_at, 2);
  EXPECT_NE(notes[2].find("this keyframe is the reference now, 2 keyframes before it kept"), std::string::npos)
      << notes[2];

  // Every keyframe from 0 on is in the map, placed as the scene says up to the map's one scale, about keyframe 2's
  // camera (the map's first view).
  ASSERT_EQ(snapshot_->keyframe_count, static_cast<std::uint32_t>(started_at + 1));
  std::vector<SE3d> T_w_c(static_cast<std::size_t>(started_at + 1));
  for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) {
    const KeyframeStateMsg& kf = snapshot_->keyframes[i];
    T_w_c[kf.id.counter] = fromMsg(kf.T_w_s) * T_s_c_;
  }
  const auto relative = [&](int k) { return T_w_c[2].inverse() * T_w_c[static_cast<std::size_t>(k)]; };
  const auto relative_true = [&](int k) { return (truePose(2) * T_s_c_).inverse() * truePose(k) * T_s_c_; };
  const double scale = relative(started_at).translation().norm() / relative_true(started_at).translation().norm();
  for (int k = 0; k <= started_at; ++k) {
    EXPECT_LT((relative(k).translation() - scale * relative_true(k).translation()).norm(), 0.02 * scale * 0.1)
        << "keyframe " << k;
    EXPECT_LT((relative(k).so3().inverse() * relative_true(k).so3()).log().norm(), 1e-3) << "keyframe " << k;
  }
}

TEST_F(MapperNewReferenceTest, TheKeyframesKeptFromBeforeItGoFirstWhenTheWaitingOnesFillTheirShare) {
  // At most 4 keyframes wait (half of 8): keyframe 3 makes 4 with the two kept, keyframe 4 again.
  std::vector<std::string> notes;
  const int started_at = run(8, notes);
  ASSERT_EQ(started_at, 5) << "the reference (keyframe 2) starts the map with keyframe 5, as with room to wait";
  for (int k : {3, 4}) {
    EXPECT_NE(notes[static_cast<std::size_t>(k)].find("the 1 oldest keyframes kept from before the reference go"),
              std::string::npos)
        << notes[static_cast<std::size_t>(k)];
  }
  ASSERT_EQ(snapshot_->keyframe_count, 4u);
  for (std::uint32_t i = 0; i < snapshot_->keyframe_count; ++i) EXPECT_GE(snapshot_->keyframes[i].id.counter, 2u);
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
  o.return_full_window_keyframes = -1;
  EXPECT_NE(o.validate().error().message().find("return_full_window_keyframes"), std::string::npos);
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
