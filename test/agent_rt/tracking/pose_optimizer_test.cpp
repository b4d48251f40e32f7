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
