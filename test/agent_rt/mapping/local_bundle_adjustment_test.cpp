// Local BA on a local map built from the synthetic visual-inertial scene: the window converges to the truth,
// keyframes outside it that share enough points stay fixed, and bad options are named.
#include "agent_rt/mapping/local_bundle_adjustment.hpp"

#include <cmath>
#include <cstdio>
#include <memory>
#include <optional>
#include <vector>

#include <gtest/gtest.h>

#include "common/factors/manifolds.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;

struct Fixture {
  test::ViScenario scenario;
  std::unique_ptr<LocalMap> map;
  std::vector<PoolHandle> keyframes;
  std::vector<PoolHandle> points;
};

// The scene as a local map, keyframes in time order, every state but the first perturbed.
Fixture makeMap(bool perturb) {
  Fixture f;
  test::ViScenarioOptions options;
  options.keyframes = 8;
  options.points = 300;
  options.bias.gyro = Vector3d(0.004, -0.003, 0.002);
  options.bias.accel = Vector3d(0.03, -0.02, 0.04);
  f.scenario = test::makeViScenario(options);
  test::ViBaState state = test::trueViBaState(f.scenario);
  if (perturb) test::perturbViBaState(state, 0.1, 2.0 * M_PI / 180.0, 3);
  f.map = std::make_unique<LocalMap>(f.scenario.T_s_c);
  IdCounter<KeyframeId> keyframe_ids(0);
  IdCounter<MapPointId> point_ids(0);

  // Keypoints: each keyframe's observations in scene order.
  std::vector<std::vector<const test::ViObservation*>> per_keyframe(f.scenario.keyframe_states.size());
  for (const auto& o : f.scenario.observations) per_keyframe[static_cast<std::size_t>(o.keyframe)].push_back(&o);
  for (std::size_t k = 0; k < f.scenario.keyframe_states.size(); ++k) {
    auto kf = std::make_unique<KeyframeData>();
    kf->id = keyframe_ids.next();
    kf->t_ns = f.scenario.keyframe_t_ns[k];
    kf->T_w_s = factors::poseFromBlock(state.poses[k].data());
    kf->v_w = state.velocities[k];
    kf->keypoint_count = static_cast<std::uint16_t>(per_keyframe[k].size());
    for (std::size_t i = 0; i < per_keyframe[k].size(); ++i) {
      kf->undistorted_px[i] = per_keyframe[k][i]->keypoint_px;
      kf->keypoints[i].px = per_keyframe[k][i]->keypoint_px.cast<float>();
    }
    if (k > 0) {
      kf->has_preintegration = true;
      kf->preintegration_from = f.map->keyframes().get(f.keyframes.back())->id;
      kf->preintegration = f.scenario.preintegrations[k - 1];
    }
    f.keyframes.push_back(*f.map->insertKeyframe(*kf));
  }
  f.points.resize(f.scenario.points.size());
  for (std::size_t k = 0; k < per_keyframe.size(); ++k) {
    for (std::size_t i = 0; i < per_keyframe[k].size(); ++i) {
      const auto j = static_cast<std::size_t>(per_keyframe[k][i]->point);
      const auto keypoint = static_cast<std::uint16_t>(i);
      if (f.scenario.points[j].reference_keyframe == static_cast<int>(k)) {
        f.points[j] = *f.map->createMapPoint(f.keyframes[k], keypoint, state.bearings[j], 1.0 / state.inverse_depths[j],
                                             point_ids.next());
      }
    }
  }
  for (std::size_t k = 0; k < per_keyframe.size(); ++k) {
    for (std::size_t i = 0; i < per_keyframe[k].size(); ++i) {
      const auto j = static_cast<std::size_t>(per_keyframe[k][i]->point);
      if (f.scenario.points[j].reference_keyframe != static_cast<int>(k)) {
        EXPECT_TRUE(f.map->addObservation(f.keyframes[k], static_cast<std::uint16_t>(i), f.points[j]).ok());
      }
    }
  }
  return f;
}

LocalBundleAdjustmentOptions baOptions(const test::ViScenario& s, int window) {
  LocalBundleAdjustmentOptions options;
  options.window = window;
  options.intrinsics = s.intrinsics;
  options.noise = s.noise;
  options.max_iterations = 50;
  return options;
}

TEST(LocalBundleAdjustment, TheWholeWindowConvergesToTheTruth) {
  Fixture f = makeMap(true);
  auto summary = runLocalBundleAdjustment(*f.map, baOptions(f.scenario, 8));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  std::printf("window %d, fixed %d, points %d, reprojection %d, imu %d: cost %.3e -> %.3e in %d iterations\n",
              summary->window_keyframes, summary->fixed_keyframes, summary->map_points, summary->reprojection_factors,
              summary->imu_factors, summary->initial_cost, summary->final_cost, summary->iterations);
  EXPECT_EQ(summary->window_keyframes, 8);
  EXPECT_FALSE(summary->oldest_fixed_sequence.has_value());  // nothing held
  EXPECT_EQ(summary->imu_factors, 7);
  for (std::size_t k = 0; k < f.keyframes.size(); ++k) {
    const KeyframeData& kf = *f.map->keyframes().get(f.keyframes[k]);
    const SE3d& truth = f.scenario.keyframe_states[k].T_w_s;
    EXPECT_LT((kf.T_w_s.translation() - truth.translation()).norm(), 1e-3) << "keyframe " << k;
    EXPECT_LT((truth.so3().inverse() * kf.T_w_s.so3()).log().norm(), 1e-4) << "keyframe " << k;
    EXPECT_LT((kf.v_w - f.scenario.keyframe_states[k].v_w).norm(), 1e-3) << "keyframe " << k;
  }
  for (std::size_t j = 0; j < f.points.size(); ++j) {
    const Vector3d p_w = *f.map->pointInWorld(f.points[j]);
    EXPECT_LT((p_w - f.scenario.points[j].p_w).norm(), 5e-3) << "point " << j;
  }
}

// Local BA holds each point as one (a, b, rho) block, converted from the map's bearing and inverse distance
// and back. With the map at the truth the BA has nothing to move, so every point must come back where it was.
TEST(LocalBundleAdjustment, PointsComeBackAsTheSamePointsWhenNothingMoves) {
  Fixture f = makeMap(false);
  std::vector<Vector3d> before;
  for (PoolHandle h : f.points) before.push_back(*f.map->pointInWorld(h));
  auto summary = runLocalBundleAdjustment(*f.map, baOptions(f.scenario, 8));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_EQ(summary->map_points, static_cast<int>(f.points.size()));
  EXPECT_EQ(summary->map_points_left_out, 0);
  for (std::size_t j = 0; j < f.points.size(); ++j) {
    const MapPointData& mp = *f.map->mapPoints().get(f.points[j]);
    EXPECT_NEAR(mp.bearing_c.norm(), 1.0, 1e-12) << "point " << j;
    EXPECT_LT((*f.map->pointInWorld(f.points[j]) - before[j]).norm(), 1e-4) << "point " << j;
  }
}

// A point whose stored bearing lies almost in its reference camera's image plane (corrupt: no pinhole image saw
// it) has no inverse-depth point. It is left out of the BA, unchanged, with its observations; the rest converges.
TEST(LocalBundleAdjustment, APointWithNoInverseDepthPointIsLeftOutAndTheRestConverges) {
  Fixture f = makeMap(true);
  MapPointData& corrupt = *f.map->mapPoints().get(f.points[7]);
  corrupt.bearing_c = Vector3d(1.0, 0.0, 0.05).normalized();
  const Vector3d corrupt_bearing = corrupt.bearing_c;
  const double corrupt_inverse_depth = corrupt.inverse_depth;
  auto summary = runLocalBundleAdjustment(*f.map, baOptions(f.scenario, 8));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_EQ(summary->map_points_left_out, 1);
  EXPECT_EQ(summary->map_points, static_cast<int>(f.points.size()) - 1);
  const MapPointData& after = *f.map->mapPoints().get(f.points[7]);
  EXPECT_EQ(after.bearing_c, corrupt_bearing);
  EXPECT_EQ(after.inverse_depth, corrupt_inverse_depth);
  for (std::size_t k = 0; k < f.keyframes.size(); ++k) {
    const KeyframeData& kf = *f.map->keyframes().get(f.keyframes[k]);
    const SE3d& truth = f.scenario.keyframe_states[k].T_w_s;
    EXPECT_LT((kf.T_w_s.translation() - truth.translation()).norm(), 1e-3) << "keyframe " << k;
    EXPECT_LT((truth.so3().inverse() * kf.T_w_s.so3()).log().norm(), 1e-4) << "keyframe " << k;
  }
  for (std::size_t j = 0; j < f.points.size(); ++j) {
    if (j == 7) continue;
    EXPECT_LT((*f.map->pointInWorld(f.points[j]) - f.scenario.points[j].p_w).norm(), 5e-3) << "point " << j;
  }
}

TEST(LocalBundleAdjustment, CovisibleKeyframesOutsideTheWindowAreHeldFixed) {
  Fixture f = makeMap(false);
  // Shift the five older keyframes (and with them the points they hold) by 10 cm, and perturb the newest
  // three. Held fixed, the older ones define where the map is: the window must converge to the truth shifted
  // by the same 10 cm. Were they free, the window's own first pose would be held instead (the gauge), and the
  // window would not move by the shift.
  const Vector3d shift(0.1, 0.0, 0.0);
  for (std::size_t k = 0; k < 5; ++k) f.map->keyframes().get(f.keyframes[k])->T_w_s.translation() += shift;
  for (std::size_t k = 5; k < 8; ++k) {
    KeyframeData& kf = *f.map->keyframes().get(f.keyframes[k]);
    kf.T_w_s = SE3d(kf.T_w_s.so3() * geometry::SO3d::exp(Vector3d(0.01, -0.02, 0.015)),
                    kf.T_w_s.translation() + Vector3d(0.05, -0.04, 0.03));
  }
  auto summary = runLocalBundleAdjustment(*f.map, baOptions(f.scenario, 3));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_EQ(summary->window_keyframes, 3);
  EXPECT_EQ(summary->fixed_keyframes, 5);
  EXPECT_EQ(summary->newest_sequence, 7u);
  EXPECT_EQ(summary->oldest_fixed_sequence, std::optional<std::uint64_t>(0));  // keyframe 0
  for (std::size_t k = 5; k < 8; ++k) {
    const Vector3d expected = f.scenario.keyframe_states[k].T_w_s.translation() + shift;
    EXPECT_LT((f.map->keyframes().get(f.keyframes[k])->T_w_s.translation() - expected).norm(), 1e-3) << k;
  }
}

TEST(LocalBundleAdjustment, AnImuLinkThatSkipsARemovedKeyframeIsNotUsed) {
  Fixture f = makeMap(false);
  ASSERT_TRUE(f.map->removeKeyframe(f.keyframes[3]).ok());  // keyframe 4's IMU now starts at a missing keyframe
  auto summary = runLocalBundleAdjustment(*f.map, baOptions(f.scenario, 8));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_EQ(summary->window_keyframes, 7);
  EXPECT_EQ(summary->imu_factors, 5);  // 0-1, 1-2, 4-5, 5-6, 6-7: not 2-4, whose IMU covers only 3-4
}

// ---------------------------------------------------------------------------------------------- stereo
// A rig like EuRoC's: cam1 11 cm to the side of cam0, turned a little, same pinhole.
const SE3d kT_c1_c0(geometry::SO3d::exp(Vector3d(0.003, -0.01, 0.002)), Vector3d(-0.110, 0.0004, -0.0009));

// Every keypoint gets its exact cam1 observation, from the true point and the true keyframe pose.
void addSecondCamera(Fixture& f) {
  std::vector<int> next(f.keyframes.size(), 0);
  for (const auto& o : f.scenario.observations) {
    const auto k = static_cast<std::size_t>(o.keyframe);
    KeyframeData& kf = *f.map->keyframes().get(f.keyframes[k]);
    const auto i = static_cast<std::size_t>(next[k]++);
    const SE3d T_w_c0 = f.scenario.keyframe_states[k].T_w_s * f.scenario.T_s_c;
    const Vector3d p_c1 = kT_c1_c0 * (T_w_c0.inverse() * f.scenario.points[static_cast<std::size_t>(o.point)].p_w);
    const factors::PinholeIntrinsics& K = f.scenario.intrinsics;
    kf.has_right[i] = true;
    kf.right_undistorted_px[i] = {K.fx * p_c1.x() / p_c1.z() + K.cx, K.fy * p_c1.y() / p_c1.z() + K.cy};
    kf.right_octave[i] = 0;
  }
}

// The whole map 20 % too large about the first keyframe, as a monocular map could be: consistent for cam0.
void scaleMap(Fixture& f, double scale) {
  const Vector3d p0 = f.map->keyframes().get(f.keyframes[0])->T_w_s.translation();
  for (PoolHandle h : f.keyframes) {
    KeyframeData& kf = *f.map->keyframes().get(h);
    kf.T_w_s.translation() = p0 + scale * (kf.T_w_s.translation() - p0);
  }
  for (PoolHandle h : f.points) f.map->mapPoints().get(h)->inverse_depth /= scale;
}

double mapScale(const Fixture& f) {
  const auto position = [&](std::size_t k) { return f.map->keyframes().get(f.keyframes[k])->T_w_s.translation(); };
  const auto truth = [&](std::size_t k) { return f.scenario.keyframe_states[k].T_w_s.translation(); };
  const std::size_t last = f.keyframes.size() - 1;
  return (position(last) - position(0)).norm() / (truth(last) - truth(0)).norm();
}

LocalBundleAdjustmentOptions stereoOptions(const test::ViScenario& s) {
  LocalBundleAdjustmentOptions options = baOptions(s, 8);
  options.use_imu = false;  // vision alone: only the baseline can give the scale
  options.use_second_camera = true;
  options.second_intrinsics = s.intrinsics;
  options.T_c1_c0 = kT_c1_c0;
  return options;
}

TEST(LocalBundleAdjustment, SecondCameraObservationsGiveAWronglyScaledMapItsMetricScale) {
  Fixture mono = makeMap(false);
  scaleMap(mono, 1.2);
  auto mono_summary = runLocalBundleAdjustment(*mono.map, stereoOptions(mono.scenario));
  ASSERT_TRUE(mono_summary.ok()) << mono_summary.error().toString();
  EXPECT_EQ(mono_summary->second_camera_factors, 0);  // no keypoint has a cam1 match
  EXPECT_GT(std::abs(mapScale(mono) - 1.0), 0.15) << "without cam1 nothing should pull the scale back";

  Fixture stereo = makeMap(false);
  addSecondCamera(stereo);
  scaleMap(stereo, 1.2);
  auto summary = runLocalBundleAdjustment(*stereo.map, stereoOptions(stereo.scenario));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  std::printf("stereo: %d factors, %d from cam1, %d left out; cost %.3e -> %.3e; scale %.5f (mono %.5f)\n",
              summary->reprojection_factors, summary->second_camera_factors, summary->second_camera_rejected,
              summary->initial_cost, summary->final_cost, mapScale(stereo), mapScale(mono));
  EXPECT_EQ(summary->second_camera_factors, static_cast<int>(stereo.scenario.observations.size()));
  EXPECT_EQ(summary->reprojection_factors, 2 * static_cast<int>(stereo.scenario.observations.size()));
  EXPECT_LT(std::abs(mapScale(stereo) - 1.0), 0.005);
  for (std::size_t j = 0; j < stereo.points.size(); ++j) {
    EXPECT_LT((*stereo.map->pointInWorld(stereo.points[j]) - stereo.scenario.points[j].p_w).norm(), 0.01) << j;
  }
}

TEST(LocalBundleAdjustment, AStereoMismatchIsLeftOut) {
  Fixture f = makeMap(false);
  addSecondCamera(f);
  KeyframeData& kf = *f.map->keyframes().get(f.keyframes[4]);
  kf.right_undistorted_px[3].x() += 25.0;  // a wrong cam1 match on the epipolar line
  auto summary = runLocalBundleAdjustment(*f.map, stereoOptions(f.scenario));
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_EQ(summary->second_camera_rejected, 1);
  EXPECT_EQ(summary->second_camera_factors, static_cast<int>(f.scenario.observations.size()) - 1);
}

// Mapping stops a local BA when the next keyframe arrives (MapperOptions::yield_to_waiting_keyframes): the solve
// ends after the iteration in which it was asked to, and what the iterations so far gained is written back.
TEST(LocalBundleAdjustment, AStopRequestEndsTheSolveAndKeepsWhatItGained) {
  Fixture full_map = makeMap(true);
  auto full = runLocalBundleAdjustment(*full_map.map, baOptions(full_map.scenario, 8), [] { return false; });
  ASSERT_TRUE(full.ok()) << full.error().toString();
  EXPECT_FALSE(full->stopped_early);
  ASSERT_GE(full->iterations, 3) << "too easy a problem to see a stop";

  Fixture f = makeMap(true);
  const KeyframeData& last = *f.map->keyframes().get(f.keyframes.back());
  const SE3d before = last.T_w_s;
  int asked = 0;
  auto stopped = runLocalBundleAdjustment(*f.map, baOptions(f.scenario, 8), [&asked] { return ++asked >= 2; });
  ASSERT_TRUE(stopped.ok()) << stopped.error().toString();
  std::printf("full: %d iterations, cost %.3e; stopped when asked the 2nd time: %d iterations, cost %.3e -> %.3e\n",
              full->iterations, full->final_cost, stopped->iterations, stopped->initial_cost, stopped->final_cost);
  EXPECT_TRUE(stopped->stopped_early);
  EXPECT_EQ(asked, 2) << "the solve went on after it was asked to stop";
  EXPECT_EQ(stopped->iterations, 2) << "asked after iterations 1 and 2, not after the initial evaluation";
  EXPECT_LT(stopped->iterations, full->iterations);
  EXPECT_LT(stopped->final_cost, stopped->initial_cost);
  EXPECT_GT(stopped->final_cost, full->final_cost);
  // Written back: the newest keyframe moved towards the truth.
  const SE3d& truth = f.scenario.keyframe_states.back().T_w_s;
  const SE3d after = f.map->keyframes().get(f.keyframes.back())->T_w_s;
  EXPECT_LT((after.translation() - truth.translation()).norm(), (before.translation() - truth.translation()).norm());
}

TEST(LocalBundleAdjustmentOptions, ValidateNamesTheBadField) {
  LocalBundleAdjustmentOptions options;
  EXPECT_TRUE(options.validate().ok());
  options.window = 0;
  const Status status = options.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message().find("window"), std::string::npos);
  LocalBundleAdjustmentOptions stereo;
  stereo.use_second_camera = true;
  stereo.second_intrinsics.fx = 0.0;
  ASSERT_FALSE(stereo.validate().ok());
  EXPECT_NE(stereo.validate().error().message().find("second camera"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::agent
