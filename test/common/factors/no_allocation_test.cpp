// Counts heap allocations (this binary replaces global operator new) while the factors evaluate with
// Jacobians and while the preintegration integrates samples: the agent calls both on its hot paths.
#include <vector>

#include <gtest/gtest.h>

#include "common/factors/imu_factor.hpp"
#include "common/factors/inverse_depth_point_factor.hpp"
#include "common/factors/prior_factor.hpp"
#include "common/factors/reprojection_factor.hpp"
#include "test/support/allocation_counter.hpp"
#include "test/support/cost_evaluation.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::factors {
namespace {

// Evaluates `cost` with every Jacobian `repeats` times; returns the allocations counted meanwhile.
long allocationsDuringEvaluate(const ceres::CostFunction& cost, const std::vector<const double*>& blocks, int repeats) {
  test::CostEvaluation evaluation(cost, blocks);
  const long before = test::allocationCount();
  for (int k = 0; k < repeats; ++k) EXPECT_TRUE(evaluation.evaluate());
  return test::allocationCount() - before;
}

TEST(NoAllocation, TheCounterSeesAnAllocation) {
  const long before = test::allocationCount();
  std::vector<int> v(100);
  const volatile int first = v[0];  // keeps the allocation from being optimised away
  (void)first;
  EXPECT_GE(test::allocationCount() - before, 1);
}

TEST(NoAllocation, FactorsEvaluateWithoutHeapAllocation) {
  const test::ViScenario s = test::makeViScenario({});
  test::ViBaState x = test::trueViBaState(s);
  const ImuFactor imu_factor(s.preintegrations[1]);
  EXPECT_EQ(allocationsDuringEvaluate(imu_factor,
                                      {x.poses[1].data(), x.velocities[1].data(), x.biases[1].data(), x.poses[2].data(),
                                       x.velocities[2].data()},
                                      1000),
            0);
  const BiasRandomWalkFactor walk(s.noise, 0.5);
  EXPECT_EQ(allocationsDuringEvaluate(walk, {x.biases[1].data(), x.biases[2].data()}, 1000), 0);

  const test::ViObservation* o = nullptr;
  for (const auto& candidate : s.observations) {
    if (candidate.keyframe != s.points[static_cast<std::size_t>(candidate.point)].reference_keyframe) {
      o = &candidate;
      break;
    }
  }
  ASSERT_NE(o, nullptr);
  const auto j = static_cast<std::size_t>(o->point);
  const ReprojectionFactor reprojection(o->keypoint_px, s.intrinsics, 1.0);
  EXPECT_EQ(allocationsDuringEvaluate(reprojection,
                                      {x.poses[static_cast<std::size_t>(o->keyframe)].data(),
                                       x.poses[static_cast<std::size_t>(s.points[j].reference_keyframe)].data(),
                                       x.extrinsics.data(), x.bearings[j].data(), &x.inverse_depths[j]},
                                      1000),
            0);
  const ReprojectionHostFactor host(o->keypoint_px, s.intrinsics, 1.0);
  EXPECT_EQ(allocationsDuringEvaluate(host, {x.bearings[j].data()}, 1000), 0);
  std::vector<Eigen::Vector3d> points = test::inverseDepthPoints(x);
  const InverseDepthPointFactor point_factor(o->keypoint_px, s.intrinsics, 1.0);
  EXPECT_EQ(allocationsDuringEvaluate(point_factor,
                                      {x.poses[static_cast<std::size_t>(o->keyframe)].data(),
                                       x.poses[static_cast<std::size_t>(s.points[j].reference_keyframe)].data(),
                                       x.extrinsics.data(), points[j].data()},
                                      1000),
            0);
  const InverseDepthPointHostFactor point_host(o->keypoint_px, s.intrinsics, 1.0);
  EXPECT_EQ(allocationsDuringEvaluate(point_host, {points[j].data()}, 1000), 0);
  const InverseDepthPointSecondCameraHostFactor point_host1(
      o->keypoint_px, s.intrinsics, 1.0, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(-0.11, 0, 0)));
  EXPECT_EQ(allocationsDuringEvaluate(point_host1, {points[j].data()}, 1000), 0);
  const PosePriorFactor pose_prior(poseFromBlock(x.poses[0].data()), Eigen::Matrix<double, 6, 6>::Identity());
  EXPECT_EQ(allocationsDuringEvaluate(pose_prior, {x.poses[1].data()}, 1000), 0);
  const BearingPriorFactor bearing_prior(x.bearings[0], Eigen::Matrix2d::Identity());
  EXPECT_EQ(allocationsDuringEvaluate(bearing_prior, {x.bearings[1].data()}, 1000), 0);
}

TEST(NoAllocation, PreintegrationIntegratesWithoutHeapAllocation) {
  const test::ViScenario s = test::makeViScenario({});
  imu::Preintegration pre(imu::ImuBias{}, s.noise);
  const long before = test::allocationCount();
  for (const auto& sample : s.imu) pre.integrate(0.001, sample.gyro_s, sample.accel_s);
  const Status status = pre.integrateInterval(s.imu, s.keyframe_t_ns[1], s.keyframe_t_ns[2]);
  EXPECT_TRUE(status.ok());
  EXPECT_EQ(test::allocationCount() - before, 0);
}

}  // namespace
}  // namespace cvislam::factors
