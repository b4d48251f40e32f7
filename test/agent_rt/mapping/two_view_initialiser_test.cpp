// The two-view start on exact bearings of a synthetic scene: the relative pose, and which points it keeps. A short
// baseline (a hand-held start) sees most of the scene with little parallax; the points between the per-point
// bound and 50 baselines away must stay, and far points must not make it choose a wrong decomposition of E.
#include "agent_rt/mapping/two_view_initialiser.hpp"

#include <cmath>
#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

struct TwoViews {
  SE3d T_c0_c1;
  std::vector<Vector3d> p_c0;
  std::vector<Vector3d> b0;
  std::vector<Vector3d> b1;
};

// Points in front of camera 0 at depths drawn from [near_m, far_m], seen from both cameras.
TwoViews makeViews(const SE3d& T_c0_c1, int points, double near_m, double far_m, std::uint64_t seed) {
  TwoViews v;
  v.T_c0_c1 = T_c0_c1;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> lateral(-0.5, 0.5);
  std::uniform_real_distribution<double> depth(near_m, far_m);
  while (static_cast<int>(v.p_c0.size()) < points) {
    const double z = depth(rng);
    const Vector3d p_c0(lateral(rng) * z, 0.7 * lateral(rng) * z, z);
    const Vector3d p_c1 = T_c0_c1.inverse() * p_c0;
    if (p_c1.z() <= 0.1) continue;
    v.p_c0.push_back(p_c0);
    v.b0.push_back(p_c0.normalized());
    v.b1.push_back(p_c1.normalized());
  }
  return v;
}

double rotationError(const SE3d& estimate, const SE3d& truth) {
  return (estimate.so3().inverse() * truth.so3()).log().norm();
}

double directionError(const SE3d& estimate, const SE3d& truth) {
  return std::acos(std::clamp(estimate.translation().normalized().dot(truth.translation().normalized()), -1.0, 1.0));
}

TEST(TwoViewInitialiser, KeepsEveryPointAboveTheParallaxBoundOnAShortBaseline) {
  // 20 cm sideways and 2 deg of yaw; depths 3-15 m: parallax 3.8 deg down to 0.8 deg, about 40 % of the points
  // farther than 50 baselines.
  const SE3d T_c0_c1(SO3d::exp(Vector3d(0.0, 0.035, 0.0)), Vector3d(0.2, 0.0, 0.0));
  const TwoViews v = makeViews(T_c0_c1, 300, 3.0, 15.0, 5);
  TwoViewOptions options;
  options.min_inliers = 50;
  auto result = initialiseTwoView(v.b0, v.b1, options);
  ASSERT_TRUE(result.ok()) << result.error().toString();
  EXPECT_LT(rotationError(result->T_c0_c1, T_c0_c1), 1e-4);
  EXPECT_LT(directionError(result->T_c0_c1, T_c0_c1), 1e-3);
  int far_kept = 0;
  for (std::size_t i = 0; i < v.p_c0.size(); ++i) {
    ASSERT_EQ(result->inlier[i], 1) << "point " << i << " at " << v.p_c0[i].z() << " m";
    // |t| = 1 in the result: the scene in units of the 0.2 m baseline.
    EXPECT_LT((result->p_c0[i] * 0.2 - v.p_c0[i]).norm(), 1e-3 * v.p_c0[i].norm()) << "point " << i;
    far_kept += v.p_c0[i].z() > 50 * 0.2 ? 1 : 0;
  }
  EXPECT_GT(far_kept, 60);
  EXPECT_GT(result->median_parallax_deg, 1.0);
}

TEST(TwoViewInitialiser, FarPointsDoNotChooseTheDecompositionOfE) {
  // 5 cm forward-sideways; 80 near points at 1-3 m, 220 at 40-200 m, whose bearings barely move: they are in front
  // of both cameras under more than one decomposition.
  const SE3d T_c0_c1(SO3d::exp(Vector3d(0.01, -0.02, 0.005)), Vector3d(0.04, 0.01, 0.03));
  TwoViews v = makeViews(T_c0_c1, 80, 1.0, 3.0, 7);
  const TwoViews far = makeViews(T_c0_c1, 220, 40.0, 200.0, 8);
  v.p_c0.insert(v.p_c0.end(), far.p_c0.begin(), far.p_c0.end());
  v.b0.insert(v.b0.end(), far.b0.begin(), far.b0.end());
  v.b1.insert(v.b1.end(), far.b1.begin(), far.b1.end());
  TwoViewOptions options;
  options.min_inliers = 50;
  options.min_median_parallax_deg = 0.0;  // the pose and the points are the test here, not the start's condition
  auto result = initialiseTwoView(v.b0, v.b1, options);
  ASSERT_TRUE(result.ok()) << result.error().toString();
  EXPECT_LT(rotationError(result->T_c0_c1, T_c0_c1), 1e-4);
  EXPECT_LT(directionError(result->T_c0_c1, T_c0_c1), 1e-3);
  int near_kept = 0;
  for (std::size_t i = 0; i < 80; ++i) near_kept += result->inlier[i];
  EXPECT_EQ(near_kept, 80);
}

}  // namespace
}  // namespace cvislam::agent
