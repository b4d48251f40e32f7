// Motion-only visual-inertial BA: the IMU residual's Jacobian against central differences, recovery of a
// perturbed pose and velocity with wrong matches, the IMU term's pull when vision is weak, and no heap
// allocation (this binary counts operator new).
#include "agent_rt/tracking/inertial_pose_optimizer.hpp"

#include <cmath>
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

}  // namespace
}  // namespace cvislam::agent
