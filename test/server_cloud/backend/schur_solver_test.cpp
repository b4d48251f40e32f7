// The server's own bundle-adjustment solver (server_cloud/backend/schur_solver): the gradient it assembles
// against central differences of its cost, and the optimum it reaches against the one Ceres reaches on the same
// visual-inertial map, whole and windowed. Real factors and real CHOLMOD factorisations; no mocks.
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "common/factors/imu_factor.hpp"
#include "common/factors/manifolds.hpp"
#include "common/factors/prior_factor.hpp"
#include "common/factors/world_point_factor.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/backend/schur_solver.hpp"
#include "test/server_cloud/backend/backend_test_maps.hpp"

namespace cvislam::server::backend {
namespace {

using namespace test_maps;  // NOLINT(google-build-using-namespace): the tests' shared maps

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

class Gaussian {
 public:
  explicit Gaussian(std::uint64_t seed) : rng_(seed) {}
  Vector3d vector(double sigma) {
    const double x = noise_(rng_);
    const double y = noise_(rng_);
    const double z = noise_(rng_);
    return sigma * Vector3d(x, y, z);
  }

 private:
  std::mt19937_64 rng_;
  std::normal_distribution<double> noise_{0.0, 1.0};
};

// Three poses (the first held), velocity and biases on the second and third, nine points (the last held), a few
// observations 30 px off so that the Cauchy loss works in its bend, and one of each keyframe factor.
TEST(SchurSolver, TheGradientItAssemblesMatchesCentralDifferencesOfItsCost) {
  Gaussian gaussian(31);
  const factors::PinholeIntrinsics K{400.0, 410.0, 320.0, 240.0};
  const SE3d T_c_s(SO3d::exp(Vector3d(0.01, -0.02, 0.03)), Vector3d(0.05, 0.0, 0.01));
  std::vector<factors::PoseBlock> poses;
  std::vector<SE3d> truth;
  for (int i = 0; i < 3; ++i) {
    truth.emplace_back(SO3d::exp(gaussian.vector(0.05)), Vector3d(0.3 * i, 0.0, 0.0) + gaussian.vector(0.05));
    poses.push_back(factors::poseToBlock(truth.back()));
  }
  std::vector<Vector3d> points;
  for (int p = 0; p < 9; ++p)
    points.push_back(Vector3d(-1.0 + 0.25 * p, 0.3 * std::sin(p), 4.0) + gaussian.vector(0.2));
  std::vector<Vector3d> velocities{gaussian.vector(0.5), gaussian.vector(0.5)};
  std::vector<Eigen::Matrix<double, 6, 1>> biases(2);
  // The random walk between the two biases is tight (sqrt information ~1e4): keep them close, so that the cost
  // stays small enough for central differences.
  biases[0] << gaussian.vector(0.01), gaussian.vector(0.1);
  biases[1] = biases[0];
  biases[1].head<3>() += gaussian.vector(1e-4);
  biases[1].tail<3>() += gaussian.vector(1e-2);

  SchurProblem problem;
  std::vector<int> pose_block;
  for (auto& pose : poses) pose_block.push_back(problem.addPose(pose.data()));
  const int velocity = problem.addVector(velocities[0].data(), 3);
  const int bias1 = problem.addVector(biases[0].data(), 6);
  const int bias2 = problem.addVector(biases[1].data(), 6);
  problem.addVector(velocities[1].data(), 3);  // a free block no factor touches: its gradient is zero
  std::vector<int> point_index;
  for (auto& p : points) point_index.push_back(problem.addPoint(p.data()));
  problem.setKeyframeBlockHeld(pose_block[0], true);
  problem.setPointHeld(point_index.back(), true);
  int observation = 0;
  for (int i = 0; i < 3; ++i) {
    for (std::size_t p = 0; p < points.size(); ++p) {
      const Vector3d X_c = T_c_s * (truth[static_cast<std::size_t>(i)].inverse() * points[p]);
      Eigen::Vector2d px(K.fx * X_c.x() / X_c.z() + K.cx, K.fy * X_c.y() / X_c.z() + K.cy);
      px += gaussian.vector(2.0).head<2>();
      if (++observation % 7 == 0) px.x() += 30.0;
      problem.addReprojection(std::make_unique<factors::WorldPointReprojectionFactor>(px, K, 1.5, T_c_s),
                              pose_block[static_cast<std::size_t>(i)], point_index[p], 1.0);
    }
  }
  Eigen::Matrix<double, 6, 6> prior_information = 10.0 * Eigen::Matrix<double, 6, 6>::Identity();
  prior_information(0, 4) = 2.0;
  problem.addKeyframeFactor(std::make_unique<factors::PosePriorFactor>(
                                SE3d(SO3d::exp(Vector3d(0.1, 0.0, -0.1)), Vector3d(0.4, 0.1, 0.0)), prior_information),
                            {pose_block[1]});
  problem.addKeyframeFactor(
      std::make_unique<factors::VectorPriorFactor<3>>(Vector3d(1.0, 0.0, 0.0), 3.0 * Eigen::Matrix3d::Identity()),
      {velocity});
  // Listed second-before-first, so that the pair's orientation in the reduced matrix is exercised.
  problem.addKeyframeFactor(std::make_unique<factors::BiasRandomWalkFactor>(imu::ImuNoise{}, 0.5), {bias2, bias1});

  const Eigen::VectorXd gradient = problem.gradient();
  // Free blocks: poses 1 and 2 (6 each), velocity 3, biases 6 + 6, the untouched velocity 3, eight points.
  ASSERT_EQ(gradient.size(), 12 + 3 + 12 + 3 + 8 * 3);

  const factors::PoseManifold manifold;
  constexpr double kStep = 1e-6;
  const auto costAt = [&]() {
    double c = 0.0;
    EXPECT_TRUE(problem.cost(c));
    return c;
  };
  // d cost / d x_k along the block's own plus: PoseManifold's for a pose (7 values), addition otherwise.
  const auto difference = [&](double* x, int size, int k) {
    const bool pose = size == 7;
    const std::vector<double> saved(x, x + size);
    double values[2];
    for (int side = 0; side < 2; ++side) {
      const double h = side == 0 ? kStep : -kStep;
      if (pose) {
        Eigen::Matrix<double, 6, 1> delta = Eigen::Matrix<double, 6, 1>::Zero();
        delta[k] = h;
        factors::PoseBlock moved;
        manifold.Plus(saved.data(), delta.data(), moved.data());
        std::copy_n(moved.data(), 7, x);
      } else {
        x[k] = saved[static_cast<std::size_t>(k)] + h;
      }
      values[side] = costAt();
      std::copy(saved.begin(), saved.end(), x);
    }
    return (values[0] - values[1]) / (2.0 * kStep);
  };
  Eigen::VectorXd numeric(gradient.size());
  int row = 0;
  for (int i = 1; i < 3; ++i) {
    for (int k = 0; k < 6; ++k) numeric[row++] = difference(poses[static_cast<std::size_t>(i)].data(), 7, k);
  }
  for (int k = 0; k < 3; ++k) numeric[row++] = difference(velocities[0].data(), 3, k);
  for (int k = 0; k < 6; ++k) numeric[row++] = difference(biases[0].data(), 6, k);
  for (int k = 0; k < 6; ++k) numeric[row++] = difference(biases[1].data(), 6, k);
  for (int k = 0; k < 3; ++k) numeric[row++] = difference(velocities[1].data(), 3, k);
  for (std::size_t p = 0; p + 1 < points.size(); ++p) {
    for (int k = 0; k < 3; ++k) numeric[row++] = difference(points[p].data(), 3, k);
  }
  ASSERT_EQ(row, gradient.size());
  EXPECT_GT(gradient.norm(), 1.0);  // far from an optimum: the comparison means something
  for (Eigen::Index k = 0; k < gradient.size(); ++k) {
    EXPECT_NEAR(gradient[k], numeric[k], 1e-5 * std::max(1.0, std::abs(numeric[k]))) << "entry " << k;
  }
  EXPECT_EQ(gradient.segment<3>(27).norm(), 0.0);
}

// Both solvers run to the optimum (tolerances far below the server's) from the same snapshot.
void expectSameOptimum(const GbaSnapshot& start) {
  GlobalBaOptions options;
  options.full_iterations = 60;
  options.function_tolerance = 1e-12;
  GbaSnapshot by_ceres = start;
  GbaSnapshot by_schur = start;
  options.solver = GlobalBaOptions::Solver::kCeres;
  const Result<GlobalBaSummary> ceres = runGlobalBa(by_ceres, options);
  options.solver = GlobalBaOptions::Solver::kSchur;
  const Result<GlobalBaSummary> schur = runGlobalBa(by_schur, options);
  ASSERT_TRUE(ceres.ok() && schur.ok());
  EXPECT_EQ(schur->reprojection_factors, ceres->reprojection_factors);
  EXPECT_NEAR(schur->initial_cost, ceres->initial_cost, 1e-9 * ceres->initial_cost);
  EXPECT_LT(schur->final_cost, 0.2 * schur->initial_cost);
  EXPECT_NEAR(schur->final_cost, ceres->final_cost, 1e-6 * ceres->final_cost);
  for (std::size_t k = 0; k < start.keyframes.size(); ++k) {
    const GbaKeyframe& a = by_schur.keyframes[k];
    const GbaKeyframe& b = by_ceres.keyframes[k];
    EXPECT_LT((a.T_w_s.translation() - b.T_w_s.translation()).norm(), 1e-5) << a.id.toString();
    EXPECT_LT((a.T_w_s.so3().inverse() * b.T_w_s.so3()).log().norm(), 1e-6) << a.id.toString();
    EXPECT_LT((a.v_w - b.v_w).norm(), 1e-4) << a.id.toString();
    EXPECT_LT((a.bias.accel - b.bias.accel).norm(), 1e-4) << a.id.toString();
    if (start.keyframes[k].held) {
      // Held: only the round trip through the parameter block's quaternion.
      EXPECT_LT((a.T_w_s.matrix() - start.keyframes[k].T_w_s.matrix()).cwiseAbs().maxCoeff(), 1e-12)
          << a.id.toString() << " is held";
      EXPECT_EQ(a.v_w, start.keyframes[k].v_w) << a.id.toString() << " is held";
    }
  }
  double worst_point = 0.0;
  for (std::size_t p = 0; p < start.points.size(); ++p) {
    worst_point = std::max(worst_point, (by_schur.points[p].p_w - by_ceres.points[p].p_w).norm());
  }
  EXPECT_LT(worst_point, 1e-4);
}

TEST(SchurSolver, ReachesTheOptimumCeresReachesOnAVisualInertialMapWholeAndWindowed) {
  const test::ViScenario s = scenario(16, 0.5, 0.5);
  MapContent map(0);
  buildTwoAgentsFusedMap(map, s);
  if (HasFatalFailure()) return;
  perturbAllButTheGauge(map, 5);
  const AgentSensorsMap sensors{{1, sensorsOf(s)}, {2, sensorsOf(s)}};
  Result<GbaSnapshot> whole = makeGbaSnapshot(map, sensors);
  ASSERT_TRUE(whole.ok());
  {
    SCOPED_TRACE("whole map");
    expectSameOptimum(*whole);
  }
  // Agent 2's keyframes free, agent 1's that see their points or link to them by IMU held.
  GbaWindow window;
  for (const auto& [id, kf] : map.keyframes()) {
    if (id.agent == 2) window.free.insert(id);
  }
  Result<GbaSnapshot> windowed = makeGbaSnapshot(map, sensors, &window);
  ASSERT_TRUE(windowed.ok());
  ASSERT_TRUE(std::any_of(windowed->keyframes.begin(), windowed->keyframes.end(),
                          [](const GbaKeyframe& kf) { return kf.held; }));
  SCOPED_TRACE("windowed");
  expectSameOptimum(*windowed);
}

TEST(GbaSolverOption, ParsesBothNamesAndNamesThemInItsError) {
  EXPECT_EQ(*parseGbaSolver("schur"), GlobalBaOptions::Solver::kSchur);
  EXPECT_EQ(*parseGbaSolver("ceres"), GlobalBaOptions::Solver::kCeres);
  const Result<GlobalBaOptions::Solver> bad = parseGbaSolver("cholmod");
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.error().toString().find("'cholmod'"), std::string::npos);
  EXPECT_NE(bad.error().toString().find("schur or ceres"), std::string::npos);
  EXPECT_STREQ(toString(GlobalBaOptions{}.solver), "schur");
}

}  // namespace
}  // namespace cvislam::server::backend
