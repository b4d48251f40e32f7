// The server's world-point reprojection factor (common/factors/world_point_factor): its Jacobians through Ceres'
// ambient interface and through its tangent-space entry point, against numeric differences on the manifold.
#include <cmath>
#include <vector>

#include <gtest/gtest.h>

#include "common/factors/manifolds.hpp"
#include "common/factors/world_point_factor.hpp"
#include "test/common/factors/jacobian_check.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::factors {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the factor tests' shared checks

// ------------------------------------------------------------------------------ world-point reprojection
class WorldPointFactorTest : public ::testing::Test {
 protected:
  PoseManifold pose_manifold_;
  PinholeIntrinsics intrinsics_;
  Random random_{43};
  SE3d T_s_c_ = test::makeViScenario({}).T_s_c;

  // A random body pose and a point `depth` metres in front of its camera.
  std::vector<Block> randomCase(double depth, double rotation_scale) {
    const SE3d T_w_s(SO3d::exp(random_.vector3(rotation_scale)), random_.vector3(2.0));
    const Vector3d X_c = depth * (Vector3d(0, 0, 1) + random_.vector3(0.3)).normalized();
    return {poseBlock(T_w_s, pose_manifold_), vectorBlock(VectorXd(T_w_s * T_s_c_ * X_c))};
  }
};

TEST_F(WorldPointFactorTest, JacobiansMatchNumericAtRandomStatesTinyRotationsAndNearPi) {
  for (int trial = 0; trial < 20; ++trial) {
    const WorldPointReprojectionFactor sut(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5, T_s_c_.inverse());
    expectJacobiansMatchNumeric(sut, randomCase(random_.uniform(1.0, 10.0), M_PI / std::sqrt(3.0)));
  }
  const WorldPointReprojectionFactor tiny(Eigen::Vector2d(400.0, 250.0), intrinsics_, 1.0, T_s_c_.inverse());
  expectJacobiansMatchNumeric(tiny, randomCase(3.0, 1e-9));
  const SE3d T_w_s(SO3d::exp(Vector3d(0.0, 0.0, M_PI - 1e-7)), Vector3d(1.0, -2.0, 0.5));
  const Vector3d p_w = T_w_s * T_s_c_ * Vector3d(0.2, -0.1, 4.0);
  expectJacobiansMatchNumeric(tiny, {poseBlock(T_w_s, pose_manifold_), vectorBlock(VectorXd(p_w))});
}

// The tangent-space entry point (the server's Schur solver): its pose Jacobian against central differences
// of the residual along PoseManifold::Plus, its point Jacobian against differences in p_w, its residual the
// Ceres one.
TEST_F(WorldPointFactorTest, TangentJacobiansMatchNumericAlongThePoseManifold) {
  constexpr double kStep = 1e-6;
  for (int trial = 0; trial < 20; ++trial) {
    const WorldPointReprojectionFactor sut(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5, T_s_c_.inverse());
    const std::vector<Block> blocks = randomCase(random_.uniform(1.0, 10.0), M_PI / std::sqrt(3.0));
    const double* pose = blocks[0].value.data();
    const double* p_w = blocks[1].value.data();
    Eigen::Vector2d r;
    Eigen::Matrix<double, 2, 6> J_pose;
    Eigen::Matrix<double, 2, 3> J_point;
    ASSERT_TRUE(sut.evaluateTangent(pose, p_w, r, &J_pose, &J_point));
    EXPECT_LT((r - evaluate(sut, blocks)).norm(), 1e-12);
    Eigen::Matrix<double, 2, 6> numeric_pose;
    for (int k = 0; k < 6; ++k) {
      Eigen::Matrix<double, 6, 1> delta = Eigen::Matrix<double, 6, 1>::Zero();
      Eigen::Matrix<double, 7, 1> plus;
      Eigen::Matrix<double, 7, 1> minus;
      delta[k] = kStep;
      pose_manifold_.Plus(pose, delta.data(), plus.data());
      delta[k] = -kStep;
      pose_manifold_.Plus(pose, delta.data(), minus.data());
      Eigen::Vector2d r_plus;
      Eigen::Vector2d r_minus;
      ASSERT_TRUE(sut.evaluateTangent(plus.data(), p_w, r_plus, nullptr, nullptr));
      ASSERT_TRUE(sut.evaluateTangent(minus.data(), p_w, r_minus, nullptr, nullptr));
      numeric_pose.col(k) = (r_plus - r_minus) / (2.0 * kStep);
    }
    Eigen::Matrix<double, 2, 3> numeric_point;
    for (int k = 0; k < 3; ++k) {
      Vector3d plus(p_w[0], p_w[1], p_w[2]);
      Vector3d minus = plus;
      plus[k] += kStep;
      minus[k] -= kStep;
      Eigen::Vector2d r_plus;
      Eigen::Vector2d r_minus;
      ASSERT_TRUE(sut.evaluateTangent(pose, plus.data(), r_plus, nullptr, nullptr));
      ASSERT_TRUE(sut.evaluateTangent(pose, minus.data(), r_minus, nullptr, nullptr));
      numeric_point.col(k) = (r_plus - r_minus) / (2.0 * kStep);
    }
    EXPECT_LT((J_pose - numeric_pose).cwiseAbs().maxCoeff(), 1e-4 * std::max(1.0, J_pose.cwiseAbs().maxCoeff()));
    EXPECT_LT((J_point - numeric_point).cwiseAbs().maxCoeff(), 1e-4 * std::max(1.0, J_point.cwiseAbs().maxCoeff()));
  }
}

TEST_F(WorldPointFactorTest, SecondCameraJacobiansMatchNumericAndAFarPointStillConstrainsRotation) {
  const SE3d T_c1_c0(SO3d::exp(Vector3d(0.001, -0.002, 0.003)), Vector3d(-0.11, 0.001, 0.0005));
  const SE3d T_c1_s = T_c1_c0 * T_s_c_.inverse();
  for (int trial = 0; trial < 10; ++trial) {
    const WorldPointReprojectionFactor sut(Eigen::Vector2d(320.0, 240.0), intrinsics_, 1.2, T_c1_s);
    expectJacobiansMatchNumeric(sut, randomCase(random_.uniform(0.5, 20.0), 1.0));
  }
  // 10 km away: the point Jacobian vanishes, the rotation Jacobian does not.
  const WorldPointReprojectionFactor far(Eigen::Vector2d(320.0, 240.0), intrinsics_, 1.0, T_s_c_.inverse());
  std::vector<Block> blocks = randomCase(1e4, 0.5);
  expectJacobiansMatchNumeric(far, blocks, 1e-5, 1e-4);
  std::vector<const double*> parameters{blocks[0].value.data(), blocks[1].value.data()};
  MatrixXdRowMajor J_pose(2, 7);
  MatrixXdRowMajor J_point(2, 3);
  std::vector<double*> jacobians{J_pose.data(), J_point.data()};
  Eigen::Vector2d residual;
  ASSERT_TRUE(far.Evaluate(parameters.data(), residual.data(), jacobians.data()));
  EXPECT_GT(J_pose.rightCols<4>().norm(), 100.0);
  EXPECT_LT(J_point.norm(), 0.1);
}

TEST_F(WorldPointFactorTest, ResidualIsTheWhitenedPixelErrorAndBehindTheCameraIsNotEvaluable) {
  const SE3d T_w_s(SO3d::exp(Vector3d(0.1, 0.2, -0.3)), Vector3d(1.0, 2.0, 3.0));
  const Vector3d X_c(0.5, -0.25, 2.0);
  const Eigen::Vector2d px(intrinsics_.fx * 0.25 + intrinsics_.cx, intrinsics_.fy * -0.125 + intrinsics_.cy);
  const WorldPointReprojectionFactor sut(px + Eigen::Vector2d(3.0, -4.0), intrinsics_, 2.0, T_s_c_.inverse());
  bool ok = false;
  const VectorXd r =
      evaluate(sut, {poseBlock(T_w_s, pose_manifold_), vectorBlock(VectorXd(T_w_s * T_s_c_ * X_c))}, &ok);
  ASSERT_TRUE(ok);
  EXPECT_NEAR(r(0), -1.5, 1e-9);
  EXPECT_NEAR(r(1), 2.0, 1e-9);
  (void)evaluate(sut, {poseBlock(T_w_s, pose_manifold_), vectorBlock(VectorXd(T_w_s * T_s_c_ * -X_c))}, &ok);
  EXPECT_FALSE(ok);
}

}  // namespace
}  // namespace cvislam::factors
