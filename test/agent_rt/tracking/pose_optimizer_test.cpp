// Motion-only pose optimisation: Jacobian against numeric differentiation, recovery of a perturbed pose
// with noise and 20 % wrong matches, and no heap allocation (this binary counts operator new).
#include "agent_rt/tracking/pose_optimizer.hpp"

#include <cmath>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "test/agent_rt/tracking/tracking_case.hpp"
#include "test/support/allocation_counter.hpp"
#include "test/support/numeric_diff.hpp"

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;
using Vec6 = Eigen::Matrix<double, 6, 1>;

SE3d plus(const SE3d& T, const Vec6& d) {
  return {T.so3() * SO3d::exp(d.tail<3>()), T.translation() + d.head<3>()};
}

TEST(PoseOptimizer, ResidualJacobianMatchesNumeric) {
  const TrackingCase c = makeTrackingCase(0.0, 1);
  const SE3d T = plus(c.truePose(), (Vec6() << 0.05, -0.03, 0.02, 0.01, -0.02, 0.015).finished());
  for (std::size_t i = 0; i < c.observations.size(); i += 7) {
    Eigen::Vector2d r;
    Eigen::Matrix<double, 2, 6> J;
    ASSERT_TRUE(poseReprojectionResidual(c.observations[i], T, c.scenario.T_s_c, c.scenario.intrinsics, r, &J));
    const auto f = [&](const Vec6& d) {
      Eigen::Vector2d rd;
      EXPECT_TRUE(poseReprojectionResidual(c.observations[i], plus(T, d), c.scenario.T_s_c, c.scenario.intrinsics, rd,
                                           nullptr));
      return rd;
    };
    const Eigen::Matrix<double, 2, 6> J_numeric = test::numericJacobian<2, 6>(f, Vec6::Zero());
    EXPECT_LT((J - J_numeric).cwiseAbs().maxCoeff(), 1e-5 * std::max(1.0, J_numeric.cwiseAbs().maxCoeff()));
  }
}

TEST(PoseOptimizer, RecoversThePoseAndFindsTheWrongMatches) {
  for (const std::uint64_t seed : {1U, 2U, 3U}) {
    const TrackingCase c = makeTrackingCase(0.2, seed);
    ASSERT_GT(c.observations.size(), 100u);
    const SE3d initial = plus(c.truePose(), (Vec6() << 0.05, -0.04, 0.03, 0.02, -0.025, 0.03).finished());
    std::vector<std::uint8_t> outlier(c.observations.size());
    auto sut = optimizePose(c.observations, initial, c.scenario.T_s_c, c.scenario.intrinsics, {}, outlier);
    ASSERT_TRUE(sut.ok()) << sut.error().toString();
    const double position_error = (sut->T_w_s.translation() - c.truePose().translation()).norm();
    const double rotation_deg = (c.truePose().so3().inverse() * sut->T_w_s.so3()).log().norm() * 180.0 / M_PI;
    int caught = 0;
    int corrupted = 0;
    int false_alarms = 0;
    for (std::size_t i = 0; i < outlier.size(); ++i) {
      corrupted += c.corrupted[i];
      caught += c.corrupted[i] != 0 && outlier[i] != 0 ? 1 : 0;
      false_alarms += c.corrupted[i] == 0 && outlier[i] != 0 ? 1 : 0;
    }
    std::printf(
        "seed %llu: %zu observations, %d wrong: error %.2f mm %.4f deg, caught %d, false alarms %d, %d iterations\n",
        static_cast<unsigned long long>(seed), c.observations.size(), corrupted, 1e3 * position_error, rotation_deg,
        caught, false_alarms, sut->iterations);
    EXPECT_LT(position_error, 0.01);
    EXPECT_LT(rotation_deg, 0.1);
    EXPECT_GE(caught, corrupted * 95 / 100);
    // 0.5 px noise against a 95 % chi-square bound: about 5 % of the good ones fall outside by chance.
    EXPECT_LE(false_alarms, static_cast<int>(0.1 * static_cast<double>(c.observations.size() - corrupted)));
  }
}

// Points 3 to 4.5 m ahead: a sideways step and a small turn move them almost alike, so the pose has a flat
// valley. One wrong match of a point 0.4 m away, found where the prediction put it, has the leverage to drag the
// pose along that valley until it fits, and every match is then an inlier. Seen in tracking when a frame had
// waited for the first map: no velocity yet, so the prediction was 4 cm behind, and the frame was tracked 4 cm
// off. The same point with a right match must still count.
struct ValleyCase {
  std::vector<PoseObservation> observations;  // the near point last
  SE3d T_true;
  SE3d predicted;  // 4 cm behind, the orientation right
};

ValleyCase makeValleyCase(const TrackingCase& base, std::uint64_t seed, bool near_match_right) {
  const SE3d& T_s_c = base.scenario.T_s_c;
  const factors::PinholeIntrinsics& K = base.scenario.intrinsics;
  ValleyCase c;
  c.T_true = base.truePose();
  const Vector3d step_w = (c.T_true.so3() * T_s_c.so3()) * Vector3d(0.04, 0.0, 0.0);  // along the image x axis
  c.predicted = SE3d(c.T_true.so3(), c.T_true.translation() - step_w);
  const auto project = [&](const SE3d& T_w_s, const Vector3d& p_w) {
    const Vector3d p_c = (T_w_s * T_s_c).inverse() * p_w;
    return Eigen::Vector2d(K.fx * p_c.x() / p_c.z() + K.cx, K.fy * p_c.y() / p_c.z() + K.cy);
  };
  const auto point = [&](const Eigen::Vector2d& px, double depth) {
    return c.T_true * (T_s_c * Vector3d(depth * (px.x() - K.cx) / K.fx, depth * (px.y() - K.cy) / K.fy, depth));
  };
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.5);
  for (int i = 0; i < 60; ++i) {
    const Eigen::Vector2d px(40.0 + 672.0 * u(rng), 40.0 + 400.0 * u(rng));
    PoseObservation o;
    o.p_w = point(px, 3.0 + 1.5 * u(rng));
    o.keypoint_px = px + Eigen::Vector2d(noise(rng), noise(rng));
    c.observations.push_back(o);
  }
  PoseObservation near;
  const Eigen::Vector2d near_px(300.0 + 150.0 * u(rng), 200.0 + 80.0 * u(rng));
  near.p_w = point(near_px, 0.4);
  // A wrong match sits where the prediction put the point, 40 px from where the point is.
  near.keypoint_px =
      near_match_right ? near_px + Eigen::Vector2d(noise(rng), noise(rng)) : project(c.predicted, near.p_w);
  c.observations.push_back(near);
  return c;
}

TEST(PoseOptimizer, AWrongMatchThatTheFitCannotCheckSitsOutAndIsFound) {
  const TrackingCase base = makeTrackingCase(0.0, 6);
  for (const std::uint64_t seed : {1U, 2U, 3U, 4U}) {
    const ValleyCase c = makeValleyCase(base, seed, false);
    std::vector<std::uint8_t> outlier(c.observations.size());
    PoseOptimizerOptions without;
    without.max_leverage = 1.0;
    auto dragged =
        optimizePose(c.observations, c.predicted, base.scenario.T_s_c, base.scenario.intrinsics, without, outlier);
    ASSERT_TRUE(dragged.ok()) << dragged.error().toString();
    const bool dragged_kept_it = outlier.back() == 0;
    auto sut = optimizePose(c.observations, c.predicted, base.scenario.T_s_c, base.scenario.intrinsics, {}, outlier);
    ASSERT_TRUE(sut.ok()) << sut.error().toString();
    const double dragged_cm = 100.0 * (dragged->T_w_s.translation() - c.T_true.translation()).norm();
    const double sut_cm = 100.0 * (sut->T_w_s.translation() - c.T_true.translation()).norm();
    std::printf(
        "seed %llu: without the leverage check %.2f cm off (wrong match %s), with it %.2f cm (%d held out, "
        "wrong match %s)\n",
        static_cast<unsigned long long>(seed), dragged_cm, dragged_kept_it ? "kept" : "caught", sut_cm, sut->held_out,
        outlier.back() != 0 ? "caught" : "kept");
    EXPECT_GT(dragged_cm, 2.0) << "the case no longer shows the valley";
    EXPECT_TRUE(dragged_kept_it);
    EXPECT_LT(sut_cm, 1.0);
    EXPECT_GE(sut->held_out, 1);
    EXPECT_NE(outlier.back(), 0) << "the wrong match of the near point was kept";
  }
}

TEST(PoseOptimizer, ARightMatchThatSatOutForItsLeverageComesBack) {
  const TrackingCase base = makeTrackingCase(0.0, 6);
  for (const std::uint64_t seed : {1U, 2U, 3U, 4U}) {
    const ValleyCase c = makeValleyCase(base, seed, true);
    std::vector<std::uint8_t> outlier(c.observations.size());
    auto sut = optimizePose(c.observations, c.predicted, base.scenario.T_s_c, base.scenario.intrinsics, {}, outlier);
    ASSERT_TRUE(sut.ok()) << sut.error().toString();
    const double sut_cm = 100.0 * (sut->T_w_s.translation() - c.T_true.translation()).norm();
    std::printf("seed %llu: %.2f cm off, %d held out, the near point %s\n", static_cast<unsigned long long>(seed),
                sut_cm, sut->held_out, outlier.back() != 0 ? "left out" : "back in");
    EXPECT_LT(sut_cm, 0.5);
    EXPECT_EQ(outlier.back(), 0) << "a right match was lost";
  }
}

TEST(PoseOptimizer, TooFewGoodMatchesIsReportedAsLostTracking) {
  const TrackingCase c = makeTrackingCase(0.0, 4);
  const std::vector<PoseObservation> few(c.observations.begin(), c.observations.begin() + 5);
  std::vector<std::uint8_t> outlier(few.size());
  auto sut = optimizePose(few, c.truePose(), c.scenario.T_s_c, c.scenario.intrinsics, {}, outlier);
  ASSERT_FALSE(sut.ok());
  EXPECT_EQ(sut.error().code(), ErrorCode::kDegenerate) << sut.error().toString();
  EXPECT_EQ(sut.error().message(), "few inliers");
}

TEST(PoseOptimizer, DoesNotAllocate) {
  const TrackingCase c = makeTrackingCase(0.2, 5);
  std::vector<std::uint8_t> outlier(c.observations.size());
  const SE3d initial = plus(c.truePose(), (Vec6() << 0.02, 0.0, 0.01, 0.01, 0.0, 0.0).finished());
  const PoseOptimizerOptions options;
  const long before = test::allocationCount();
  auto sut = optimizePose(c.observations, initial, c.scenario.T_s_c, c.scenario.intrinsics, options, outlier);
  const long after = test::allocationCount();
  ASSERT_TRUE(sut.ok());
  EXPECT_EQ(after - before, 0);
}

}  // namespace
}  // namespace cvislam::agent
