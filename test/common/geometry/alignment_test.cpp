#include "common/geometry/alignment.hpp"

#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace cvislam::geometry {
namespace {

std::vector<Eigen::Vector3d> randomPoints(std::mt19937& rng, int n) {
  std::uniform_real_distribution<double> u(-5.0, 5.0);
  std::vector<Eigen::Vector3d> pts;
  for (int i = 0; i < n; ++i) pts.emplace_back(u(rng), u(rng), 0.3 * u(rng));
  return pts;
}

std::vector<Eigen::Vector3d> transform(const Sim3d& S, const std::vector<Eigen::Vector3d>& pts) {
  std::vector<Eigen::Vector3d> out;
  for (const auto& p : pts) out.push_back(S * p);
  return out;
}

TEST(AlignSim3, RecoversAKnownSimilarityExactly) {
  std::mt19937 rng(3);
  const auto src = randomPoints(rng, 50);
  const Sim3d truth(1.37, SO3d::exp(Eigen::Vector3d(0.3, -2.0, 0.7)), Eigen::Vector3d(4.0, -1.0, 2.0));
  const auto result = alignSim3(src, transform(truth, src));
  ASSERT_TRUE(result.ok()) << result.error().toString();
  EXPECT_NEAR(result->scale(), 1.37, 1e-12);
  EXPECT_LT((result->matrix() - truth.matrix()).cwiseAbs().maxCoeff(), 1e-11);
}

TEST(AlignSE3, RecoversAKnownRigidTransformAndIgnoresScale) {
  std::mt19937 rng(4);
  const auto src = randomPoints(rng, 30);
  const SE3d truth(SO3d::exp(Eigen::Vector3d(-1.0, 0.5, 2.9)), Eigen::Vector3d(-3.0, 0.0, 1.0));
  const auto result = alignSE3(src, transform(Sim3d(truth), src));
  ASSERT_TRUE(result.ok());
  EXPECT_LT((result->matrix() - truth.matrix()).cwiseAbs().maxCoeff(), 1e-11);
}

TEST(AlignSE3, HandlesAReflectionFreeSolutionWithNoise) {
  // With noise, the SE3 solution minimises the squared error: perturbing it cannot do better.
  std::mt19937 rng(5);
  std::normal_distribution<double> noise(0.0, 0.05);
  const auto src = randomPoints(rng, 100);
  auto dst = transform(Sim3d(SE3d(SO3d::exp(Eigen::Vector3d(0.0, 0.0, 2.0)), Eigen::Vector3d(1, 2, 3))), src);
  for (auto& p : dst) p += Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
  const auto T = alignSE3(src, dst);
  ASSERT_TRUE(T.ok());
  EXPECT_GT(T->rotationMatrix().determinant(), 0.0);
  const auto cost = [&](const SE3d& X) {
    double c = 0.0;
    for (std::size_t i = 0; i < src.size(); ++i) c += (dst[i] - X * src[i]).squaredNorm();
    return c;
  };
  const double best = cost(*T);
  for (int k = 0; k < 12; ++k) {
    SE3d::Tangent d = SE3d::Tangent::Zero();
    d(k % 6) = (k < 6 ? 1e-3 : -1e-3);
    EXPECT_GT(cost(*T * SE3d::exp(d)), best);
  }
}

TEST(AlignPositionYaw, RecoversYawAndTranslation) {
  std::mt19937 rng(6);
  const auto src = randomPoints(rng, 20);
  const SE3d truth(rotationAboutZ(-2.4), Eigen::Vector3d(0.5, 7.0, -1.0));
  const auto result = alignPositionYaw(src, transform(Sim3d(truth), src));
  ASSERT_TRUE(result.ok());
  EXPECT_LT((result->matrix() - truth.matrix()).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(AlignPositionYaw, KeepsRollAndPitchOfTheEstimate) {
  // A tilted truth cannot be explained by yaw alone: the result is still a pure rotation about z.
  std::mt19937 rng(8);
  const auto src = randomPoints(rng, 20);
  const SE3d tilted(SO3d::exp(Eigen::Vector3d(0.2, 0.1, 1.0)), Eigen::Vector3d::Zero());
  const auto result = alignPositionYaw(src, transform(Sim3d(tilted), src));
  ASSERT_TRUE(result.ok());
  const Eigen::Vector3d axis_angle = result->so3().log();
  EXPECT_NEAR(axis_angle.x(), 0.0, 1e-15);
  EXPECT_NEAR(axis_angle.y(), 0.0, 1e-15);
}

TEST(Alignment, DegenerateInputsAreReportedNotReturnedAsGarbage) {
  const std::vector<Eigen::Vector3d> line = {{0, 0, 0}, {1, 0, 0}, {2, 0, 0}, {3, 0, 0}};
  const auto collinear = alignSE3(line, line);
  ASSERT_FALSE(collinear.ok());
  EXPECT_EQ(collinear.error().code(), ErrorCode::kDegenerate);
  EXPECT_FALSE(alignSim3(std::vector<Eigen::Vector3d>(2), std::vector<Eigen::Vector3d>(2)).ok());
  EXPECT_EQ(alignSim3(line, std::vector<Eigen::Vector3d>(3)).error().code(), ErrorCode::kInvalidArgument);
  const std::vector<Eigen::Vector3d> vertical = {{0, 0, 0}, {0, 0, 1}, {0, 0, 2}};
  EXPECT_EQ(alignPositionYaw(vertical, vertical).error().code(), ErrorCode::kDegenerate);
}

}  // namespace
}  // namespace cvislam::geometry
