#include "common/geometry/triangulation.hpp"

#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace cvislam::geometry {
namespace {

// Cameras on a short arc looking along +z at points about 4 m ahead.
std::vector<SE3d> cameraPoses_w_c(int n) {
  std::vector<SE3d> poses;
  for (int i = 0; i < n; ++i) {
    const double a = 0.05 * i;
    poses.emplace_back(SO3d::exp(Eigen::Vector3d(0.0, -a, 0.0)), Eigen::Vector3d(0.3 * i, 0.02 * i, 0.0));
  }
  return poses;
}

TEST(TriangulateLinear, RecoversPointsFromExactBearings) {
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const auto T_w_c = cameraPoses_w_c(4);
  std::vector<SE3d> T_c_w;
  for (const auto& T : T_w_c) T_c_w.push_back(T.inverse());
  for (int k = 0; k < 50; ++k) {
    const Eigen::Vector3d p_w(u(rng), u(rng), 4.0 + u(rng));
    std::vector<Eigen::Vector3d> bearings;
    for (const auto& T : T_c_w) bearings.emplace_back((T * p_w) * 3.0);  // length is irrelevant
    const auto result = triangulateLinear(T_c_w, bearings);
    ASSERT_TRUE(result.ok()) << result.error().toString();
    EXPECT_LT((*result - p_w).norm(), 1e-9);
  }
}

TEST(TriangulateLinear, RejectsPointsBehindTheCameraAndWithoutParallax) {
  const auto T_w_c = cameraPoses_w_c(2);
  const std::vector<SE3d> T_c_w = {T_w_c[0].inverse(), T_w_c[1].inverse()};
  const Eigen::Vector3d behind(0.1, 0.0, -4.0);
  const std::vector<Eigen::Vector3d> bearings_behind = {-(T_c_w[0] * behind), -(T_c_w[1] * behind)};
  EXPECT_EQ(triangulateLinear(T_c_w, bearings_behind).error().code(), ErrorCode::kDegenerate);

  const Eigen::Vector3d far(0.0, 0.0, 1e5);
  const std::vector<Eigen::Vector3d> bearings_far = {T_c_w[0] * far, T_c_w[1] * far};
  EXPECT_FALSE(triangulateLinear(T_c_w, bearings_far).ok());

  EXPECT_EQ(
      triangulateLinear(std::span<const SE3d>(T_c_w).first(1), std::span<const Eigen::Vector3d>(bearings_far).first(1))
          .error()
          .code(),
      ErrorCode::kDegenerate);
}

TEST(TriangulateLinear, RejectsAnInconsistentBearing) {
  const auto T_w_c = cameraPoses_w_c(3);
  std::vector<SE3d> T_c_w;
  for (const auto& T : T_w_c) T_c_w.push_back(T.inverse());
  const Eigen::Vector3d p_w(0.2, 0.1, 4.0);
  std::vector<Eigen::Vector3d> bearings;
  for (const auto& T : T_c_w) bearings.push_back(T * p_w);
  bearings[2] = SO3d::exp(Eigen::Vector3d(0.0, 0.2, 0.0)) * bearings[2];  // 11 degrees off
  EXPECT_FALSE(triangulateLinear(T_c_w, bearings).ok());
}

TEST(TriangulateMidpoint, RecoversAPointAndRejectsParallelRays) {
  const auto T_w_c = cameraPoses_w_c(2);
  const Eigen::Vector3d p_w(-0.4, 0.3, 3.5);
  const auto result = triangulateMidpoint(T_w_c[0], T_w_c[0].inverse() * p_w, T_w_c[1], T_w_c[1].inverse() * p_w);
  ASSERT_TRUE(result.ok());
  EXPECT_LT((*result - p_w).norm(), 1e-12);
  const SE3d shifted(SO3d(), Eigen::Vector3d(1.0, 0.0, 0.0));
  EXPECT_FALSE(triangulateMidpoint(SE3d(), Eigen::Vector3d::UnitZ(), shifted, Eigen::Vector3d::UnitZ()).ok());
}

TEST(RayAngle, IsAccurateForTinyAngles) {
  EXPECT_NEAR(rayAngle(Eigen::Vector3d(1, 0, 0), Eigen::Vector3d(1, 1e-9, 0)), 1e-9, 1e-20);
  EXPECT_NEAR(rayAngle(Eigen::Vector3d(1, 0, 0), Eigen::Vector3d(-1, 0, 0)), 3.14159265358979323846, 1e-15);
}

TEST(TriangulationOptions, ValidateNamesTheBadField) {
  TriangulationOptions options;
  options.max_bearing_error_rad = 0.0;
  const Status st = options.validate();
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.error().message().find("max_bearing_error_rad"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::geometry
