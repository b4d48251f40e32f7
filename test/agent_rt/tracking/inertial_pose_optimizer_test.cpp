// Motion-only visual-inertial BA: the IMU residual's Jacobians against central differences, recovery of a
// perturbed pose and velocity with wrong matches, the IMU term's pull when vision is weak, the window over
// the newest n keyframes, and no heap allocation (this binary counts operator new).
#include "agent_rt/tracking/inertial_pose_optimizer.hpp"

#include <cmath>
#include <limits>
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
using Vec9 = Eigen::Matrix<double, 9, 1>;

SE3d plus(const SE3d& T, const Vec9& d) {
  return {T.so3() * SO3d::exp(d.segment<3>(3)), T.translation() + d.head<3>()};
}

// The tracking case of keyframe 3 plus the IMU: keyframe 2, with its true state and biases, is the anchor.
struct InertialCase {
  TrackingCase base;
  imu::NavState truth;
  InertialAnchor anchor;
};

InertialCase makeCase(double outlier_fraction, std::uint64_t seed) {
  InertialCase c;
  imu::ImuBias bias;
  bias.gyro = Vector3d(0.002, -0.001, 0.003);
  bias.accel = Vector3d(0.05, -0.02, 0.03);
  c.base = makeTrackingCase(outlier_fraction, seed, bias);
  const test::ViScenario& s = c.base.scenario;
  c.truth = s.keyframe_states[3];
  c.anchor.T_w_s = s.keyframe_states[2].T_w_s;
  c.anchor.v_w = s.keyframe_states[2].v_w;
  c.anchor.bias = bias;
  c.anchor.preintegration = &s.preintegrations[2];
  return c;
}

TEST(InertialPoseOptimizer, ImuJacobianMatchesNumericDifferentiation) {
  const InertialCase c = makeCase(0.0, 1);
  for (const Vec9& offset :
       {Vec9::Zero().eval(), (Vec9() << 0.1, -0.2, 0.05, 0.2, -0.3, 0.25, 0.3, -0.1, 0.2).finished()}) {
    const SE3d T = plus(c.truth.T_w_s, offset);
    const Vector3d v = c.truth.v_w + offset.tail<3>();
    Eigen::Matrix<double, 9, 9> J;
    (void)inertialResidual(c.anchor, T, v, &J);
    const auto f = [&](const Vec9& d) { return inertialResidual(c.anchor, plus(T, d), v + d.tail<3>(), nullptr); };
    const Eigen::Matrix<double, 9, 9> J_numeric = test::numericJacobian<9, 9>(f, Vec9::Zero());
    EXPECT_LT((J - J_numeric).cwiseAbs().maxCoeff(), 1e-6) << "analytic\n" << J << "\nnumeric\n" << J_numeric;
  }
}

TEST(InertialPoseOptimizer, ResidualVanishesAtTheTruth) {
  const InertialCase c = makeCase(0.0, 2);
  const Vec9 r = inertialResidual(c.anchor, c.truth.T_w_s, c.truth.v_w, nullptr);
  EXPECT_LT(r.head<3>().norm(), 1e-4);      // rad
  EXPECT_LT(r.segment<3>(3).norm(), 1e-3);  // m/s
  EXPECT_LT(r.tail<3>().norm(), 1e-3);      // m
}

TEST(InertialPoseOptimizer, RecoversPoseAndVelocityWithWrongMatches) {
  for (const std::uint64_t seed : {3U, 4U, 5U}) {
    const InertialCase c = makeCase(0.2, seed);
    const SE3d initial = plus(c.truth.T_w_s, (Vec9() << 0.05, -0.04, 0.03, 0.02, -0.025, 0.03, 0, 0, 0).finished());
    const Vector3d v_initial = c.truth.v_w + Vector3d(0.3, -0.2, 0.1);
    std::vector<std::uint8_t> outlier(c.base.observations.size());
    auto sut = optimizePoseInertial(c.base.observations, initial, v_initial, c.anchor, c.base.scenario.T_s_c,
                                    c.base.scenario.intrinsics, {}, outlier);
    ASSERT_TRUE(sut.ok()) << sut.error().toString();
    const double position_error = (sut->T_w_s.translation() - c.truth.T_w_s.translation()).norm();
    const double rotation_deg = (c.truth.T_w_s.so3().inverse() * sut->T_w_s.so3()).log().norm() * 180.0 / M_PI;
    const double velocity_error = (sut->v_w - c.truth.v_w).norm();
    std::printf("seed %llu: error %.2f mm %.4f deg %.2f mm/s, IMU chi2 %.2f\n", static_cast<unsigned long long>(seed),
                1e3 * position_error, rotation_deg, 1e3 * velocity_error, sut->imu_chi2);
    EXPECT_LT(position_error, 0.005);
    EXPECT_LT(rotation_deg, 0.05);
    EXPECT_LT(velocity_error, 0.01);  // vision alone gives no velocity: this is the IMU term's work
  }
}

TEST(InertialPoseOptimizer, ImuHoldsThePoseWhenVisionIsWeak) {
  // Twelve observations in one corner of the image constrain the pose poorly; the IMU keeps it close.
  const InertialCase c = makeCase(0.0, 6);
  std::vector<PoseObservation> few(c.base.observations.begin(), c.base.observations.begin() + 12);
  std::vector<std::uint8_t> outlier(few.size());
  auto visual = optimizePose(few, c.truth.T_w_s, c.base.scenario.T_s_c, c.base.scenario.intrinsics, {}, outlier);
  auto inertial = optimizePoseInertial(few, c.truth.T_w_s, c.truth.v_w, c.anchor, c.base.scenario.T_s_c,
                                       c.base.scenario.intrinsics, {}, outlier);
  ASSERT_TRUE(visual.ok());
  ASSERT_TRUE(inertial.ok());
  const double visual_error = (visual->T_w_s.translation() - c.truth.T_w_s.translation()).norm();
  const double inertial_error = (inertial->T_w_s.translation() - c.truth.T_w_s.translation()).norm();
  std::printf("12 observations: visual %.2f mm, visual-inertial %.2f mm\n", 1e3 * visual_error, 1e3 * inertial_error);
  EXPECT_LE(inertial_error, visual_error + 1e-4);
  EXPECT_LT(inertial_error, 0.005);
}

TEST(InertialPoseOptimizer, RefusesAnAnchorWithoutImu) {
  InertialCase c = makeCase(0.0, 7);
  const imu::Preintegration empty;
  c.anchor.preintegration = &empty;
  std::vector<std::uint8_t> outlier(c.base.observations.size());
  auto sut = optimizePoseInertial(c.base.observations, c.truth.T_w_s, c.truth.v_w, c.anchor, c.base.scenario.T_s_c,
                                  c.base.scenario.intrinsics, {}, outlier);
  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("no IMU"), std::string::npos);
}

TEST(InertialPoseOptimizer, DoesNotAllocate) {
  const InertialCase c = makeCase(0.2, 8);
  std::vector<std::uint8_t> outlier(c.base.observations.size());
  const PoseOptimizerOptions options;
  const long before = test::allocationCount();
  auto sut = optimizePoseInertial(c.base.observations, c.truth.T_w_s, c.truth.v_w, c.anchor, c.base.scenario.T_s_c,
                                  c.base.scenario.intrinsics, options, outlier);
  const long after = test::allocationCount();
  ASSERT_TRUE(sut.ok());
  EXPECT_EQ(after - before, 0);
}

TEST(InertialPoseOptimizer, ImuJacobianWrtTheStartStateMatchesNumericDifferentiation) {
  const InertialCase c = makeCase(0.0, 11);
  for (const Vec9& offset :
       {Vec9::Zero().eval(), (Vec9() << -0.2, 0.1, 0.15, -0.25, 0.2, 0.3, 0.2, 0.3, -0.1).finished()}) {
    InertialAnchor start = c.anchor;
    start.T_w_s = plus(c.anchor.T_w_s, offset);
    start.v_w = c.anchor.v_w + offset.tail<3>();
    Eigen::Matrix<double, 9, 9> J_i;
    Eigen::Matrix<double, 9, 9> J_j;
    (void)inertialResidualBetween(start, c.truth.T_w_s, c.truth.v_w, &J_i, &J_j);
    const auto f = [&](const Vec9& d) {
      InertialAnchor moved = start;
      moved.T_w_s = plus(start.T_w_s, d);
      moved.v_w = start.v_w + d.tail<3>();
      return inertialResidualBetween(moved, c.truth.T_w_s, c.truth.v_w, nullptr, nullptr);
    };
    const Eigen::Matrix<double, 9, 9> J_numeric = test::numericJacobian<9, 9>(f, Vec9::Zero());
    EXPECT_LT((J_i - J_numeric).cwiseAbs().maxCoeff(), 1e-6) << "analytic\n" << J_i << "\nnumeric\n" << J_numeric;
    Eigen::Matrix<double, 9, 9> J_frame;
    (void)inertialResidual(start, c.truth.T_w_s, c.truth.v_w, &J_frame);
    EXPECT_LT((J_j - J_frame).cwiseAbs().maxCoeff(), 1e-12);
  }
}

// ------------------------------------------------------------------------------- the window over n keyframes
// Keyframes 1 and 2 of the scene with their observations (0.5 px noise), the IMU 1 -> 2 -> frame (keyframe 3).
struct WindowCase {
  InertialCase c;
  std::vector<std::vector<PoseObservation>> observations;  // per window keyframe
  std::vector<std::vector<std::uint8_t>> outliers;
  std::vector<MotionWindowKeyframe> window;
};

WindowCase makeWindowCase(std::uint64_t seed) {
  WindowCase w;
  w.c = makeCase(0.2, seed);
  const test::ViScenario& s = w.c.base.scenario;
  for (const int k : {1, 2}) {
    std::vector<PoseObservation> obs;
    for (const test::ViObservation& o : s.observations) {
      if (o.keyframe != k) continue;
      PoseObservation p;
      p.p_w = s.points[static_cast<std::size_t>(o.point)].p_w;
      p.keypoint_px = o.keypoint_px;
      p.sigma_px = 0.5;
      obs.push_back(p);
    }
    w.observations.push_back(obs);
    w.outliers.emplace_back(obs.size());
  }
  for (std::size_t i = 0; i < 2; ++i) {
    const auto k = i + 1;
    MotionWindowKeyframe kf;
    kf.T_w_s = s.keyframe_states[k].T_w_s;
    kf.v_w = s.keyframe_states[k].v_w;
    kf.bias = w.c.anchor.bias;
    kf.observations = w.observations[i];
    kf.is_outlier = w.outliers[i];
    kf.to_next = &s.preintegrations[k];
    w.window.push_back(kf);
  }
  return w;
}

double velocityError(const Vector3d& v, const imu::NavState& truth) {
  return (v - truth.v_w).norm();
}

TEST(MotionWindow, ANewestKeyframeOffItsTruthIsCorrectedInsteadOfMisleadingTheFrame) {
  // Local BA has not caught up: the newest keyframe's velocity is 0.3 m/s off and its position 2 cm. Held
  // alone (n = 1) it drags the frame's velocity; in the window (n = 2, keyframe 1 held) its own observations
  // and the IMU from keyframe 1 put it back, and the frame follows.
  for (const std::uint64_t seed : {21U, 22U, 23U}) {
    WindowCase w = makeWindowCase(seed);
    const test::ViScenario& s = w.c.base.scenario;
    w.window[1].v_w += Vector3d(0.3, -0.2, 0.1);
    w.window[1].T_w_s.translation() += Vector3d(0.02, -0.01, 0.015);
    const SE3d initial = plus(w.c.truth.T_w_s, (Vec9() << 0.03, -0.02, 0.02, 0.01, -0.02, 0.015, 0, 0, 0).finished());
    const Vector3d v_initial = w.c.truth.v_w + Vector3d(0.2, 0.1, -0.1);
    std::vector<std::uint8_t> outlier(w.c.base.observations.size());

    InertialAnchor fixed{w.window[1].T_w_s, w.window[1].v_w, w.window[1].bias, w.window[1].to_next};
    auto held =
        optimizePoseInertial(w.c.base.observations, initial, v_initial, fixed, s.T_s_c, s.intrinsics, {}, outlier);
    auto windowed =
        optimizeMotionWindow(w.window, w.c.base.observations, initial, v_initial, s.T_s_c, s.intrinsics, {}, outlier);
    ASSERT_TRUE(windowed.ok()) << windowed.error().toString();
    // Held fixed, the wrong anchor either drags the frame or pulls it so far that vision refuses it.
    const double held_v = held.ok() ? velocityError(held->v_w, w.c.truth) : std::numeric_limits<double>::infinity();
    const double window_v = velocityError(windowed->v_w, w.c.truth);
    const double window_p = (windowed->T_w_s.translation() - w.c.truth.T_w_s.translation()).norm();
    std::printf(
        "seed %llu: frame velocity error n=1 %.1f mm/s%s, n=2 %.1f mm/s; n=2 position %.2f mm, %d+%d "
        "inliers, %d iterations\n",
        static_cast<unsigned long long>(seed), 1e3 * held_v, held.ok() ? "" : " (refused)", 1e3 * window_v,
        1e3 * window_p, windowed->inliers, windowed->keyframe_inliers, windowed->iterations);
    EXPECT_LT(window_v, 0.01);
    EXPECT_LT(window_p, 0.005);
    EXPECT_GT(held_v, 3.0 * window_v);
    EXPECT_LT(windowed->inliers, static_cast<int>(w.c.base.observations.size()));  // the wrong matches went
  }
}

TEST(MotionWindow, AKeyframeMappingHasNotReturnedIsCarriedByItsImuLinks) {
  WindowCase w = makeWindowCase(24);
  const test::ViScenario& s = w.c.base.scenario;
  w.window[1].observations = {};  // tracking published it; mapping has not sent it back
  w.window[1].is_outlier = {};
  w.window[1].T_w_s.translation() += Vector3d(0.02, 0.0, -0.01);
  std::vector<std::uint8_t> outlier(w.c.base.observations.size());
  auto sut = optimizeMotionWindow(w.window, w.c.base.observations, w.c.truth.T_w_s, w.c.truth.v_w, s.T_s_c,
                                  s.intrinsics, {}, outlier);
  ASSERT_TRUE(sut.ok()) << sut.error().toString();
  EXPECT_LT((sut->T_w_s.translation() - w.c.truth.T_w_s.translation()).norm(), 0.005);
  EXPECT_LT(velocityError(sut->v_w, w.c.truth), 0.02);
}

TEST(MotionWindow, RefusesAnEmptyWindowAndAMissingImuLink) {
  WindowCase w = makeWindowCase(25);
  const test::ViScenario& s = w.c.base.scenario;
  std::vector<std::uint8_t> outlier(w.c.base.observations.size());
  auto empty = optimizeMotionWindow({}, w.c.base.observations, w.c.truth.T_w_s, w.c.truth.v_w, s.T_s_c, s.intrinsics,
                                    {}, outlier);
  ASSERT_FALSE(empty.ok());
  EXPECT_NE(empty.error().message().find("0 keyframes"), std::string::npos);
  w.window[0].to_next = nullptr;
  auto unlinked = optimizeMotionWindow(w.window, w.c.base.observations, w.c.truth.T_w_s, w.c.truth.v_w, s.T_s_c,
                                       s.intrinsics, {}, outlier);
  ASSERT_FALSE(unlinked.ok());
  EXPECT_NE(unlinked.error().message().find("no IMU"), std::string::npos);
}

TEST(MotionWindow, DoesNotAllocate) {
  WindowCase w = makeWindowCase(26);
  const test::ViScenario& s = w.c.base.scenario;
  std::vector<std::uint8_t> outlier(w.c.base.observations.size());
  const PoseOptimizerOptions options;
  const long before = test::allocationCount();
  auto sut = optimizeMotionWindow(w.window, w.c.base.observations, w.c.truth.T_w_s, w.c.truth.v_w, s.T_s_c,
                                  s.intrinsics, options, outlier);
  const long after = test::allocationCount();
  ASSERT_TRUE(sut.ok());
  EXPECT_EQ(after - before, 0);
}

}  // namespace
}  // namespace cvislam::agent
