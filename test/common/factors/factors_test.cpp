// Manifold invariants, and every factor's analytic Jacobian against numeric differentiation on the manifold
// (jacobian_check.hpp), at random states and at the edge cases: tiny rotations, rotations near pi, points near
// infinity. The server's world-point factor has its own file (world_point_factor_test.cpp).
#include <cmath>
#include <memory>
#include <random>
#include <vector>

#include <ceres/manifold_test_utils.h>
#include <gtest/gtest.h>

#include "common/factors/imu_factor.hpp"
#include "common/factors/inverse_depth_point_factor.hpp"
#include "common/factors/manifolds.hpp"
#include "common/factors/prior_factor.hpp"
#include "common/factors/reprojection_factor.hpp"
#include "common/factors/time_offset_point_factor.hpp"
#include "test/common/factors/jacobian_check.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::factors {
namespace {

using namespace test_support;  // NOLINT(google-build-using-namespace): the factor tests' shared checks

// ------------------------------------------------------------------------------------------- manifolds
// Ceres' invariant macro names its matchers unqualified, as if used inside namespace ceres.
void expectManifoldInvariants(const ceres::Manifold& manifold, const VectorXd& x, const VectorXd& delta,
                              const VectorXd& y, double tolerance) {
  using ceres::HasCorrectMinusJacobianAt;
  using ceres::HasCorrectPlusJacobianAt;
  using ceres::HasCorrectRightMultiplyByPlusJacobianAt;
  using ceres::MinusPlusIsIdentityAt;
  using ceres::MinusPlusJacobianIsIdentityAt;
  using ceres::PlusMinusIsIdentityAt;
  using ceres::Vector;
  using ceres::XMinusXIsZeroAt;
  using ceres::XPlusZeroIsXAt;
  EXPECT_THAT_MANIFOLD_INVARIANTS_HOLD(manifold, x, delta, y, tolerance);
}

TEST(PoseManifold, InvariantsHoldAtRandomPointsTinyAndLargeSteps) {
  const PoseManifold sut;
  Random random(11);
  for (int trial = 0; trial < 20; ++trial) {
    const VectorXd x = poseToBlock(random.pose(5.0));
    VectorXd y = poseToBlock(random.pose(5.0));
    // q and -q are one rotation; Plus(x, Minus(y, x)) returns the sign nearer x, so compare with that one.
    if (x.tail<4>().dot(y.tail<4>()) < 0.0) y.tail<4>() = -y.tail<4>();
    for (const double step : {1e-4, 0.3, 3.0}) {
      Eigen::Matrix<double, 6, 1> delta;
      delta << random.vector3(step), random.vector3(step) / std::sqrt(3.0);
      expectManifoldInvariants(sut, x, VectorXd(delta), y, 1e-9);
    }
  }
}

TEST(UnitBearingManifold, InvariantsHoldAtRandomPointsAndOnTheAxes) {
  const UnitBearingManifold sut;
  Random random(12);
  std::vector<Vector3d> points = {Vector3d::UnitX(), Vector3d::UnitY(), Vector3d::UnitZ(), -Vector3d::UnitZ()};
  for (int i = 0; i < 16; ++i) points.push_back(random.unitVector());
  for (const Vector3d& x : points) {
    for (const double step : {1e-4, 0.2, 2.0}) {
      const Eigen::Vector2d delta(step * random.uniform(-1, 1), step * random.uniform(-1, 1));
      const Vector3d y = random.unitVector();
      expectManifoldInvariants(sut, VectorXd(x), VectorXd(delta), VectorXd(y), 1e-9);
    }
  }
}

// ------------------------------------------------------------------------------------------ IMU factors
class ImuFactorTest : public ::testing::Test {
 protected:
  void SetUp() override {
    test::ViScenarioOptions options;
    options.imu_rate_hz = 200.0;
    scenario_ = test::makeViScenario(options);
  }
  test::ViScenario scenario_;
  PoseManifold pose_manifold_;
};

TEST_F(ImuFactorTest, JacobiansMatchNumericAtPerturbedStates) {
  const ImuFactor sut(scenario_.preintegrations[2]);
  Random random(21);
  for (int trial = 0; trial < 10; ++trial) {
    const imu::NavState& si = scenario_.keyframe_states[2];
    const imu::NavState& sj = scenario_.keyframe_states[3];
    const SE3d T_i =
        si.T_w_s * SE3d::exp((Eigen::Matrix<double, 6, 1>() << random.vector3(0.2), random.vector3(0.2)).finished());
    const SE3d T_j =
        sj.T_w_s * SE3d::exp((Eigen::Matrix<double, 6, 1>() << random.vector3(0.2), random.vector3(0.2)).finished());
    Eigen::Matrix<double, 6, 1> bias;
    bias << random.vector3(0.05), random.vector3(0.3);
    expectJacobiansMatchNumeric(
        sut, {poseBlock(T_i, pose_manifold_), vectorBlock(si.v_w + random.vector3(0.3)), vectorBlock(bias),
              poseBlock(T_j, pose_manifold_), vectorBlock(sj.v_w + random.vector3(0.3))});
  }
}

TEST_F(ImuFactorTest, JacobiansMatchNumericAtTheTruthWhereTheRotationResidualIsTiny) {
  const ImuFactor sut(scenario_.preintegrations[0]);
  const imu::NavState& si = scenario_.keyframe_states[0];
  const imu::NavState& sj = scenario_.keyframe_states[1];
  const std::vector<Block> blocks = {poseBlock(si.T_w_s, pose_manifold_), vectorBlock(si.v_w),
                                     vectorBlock(VectorXd::Zero(6)), poseBlock(sj.T_w_s, pose_manifold_),
                                     vectorBlock(sj.v_w)};
  EXPECT_LT(evaluate(sut, blocks).norm(), 0.1);  // the truth fits the noise-free preintegration
  expectJacobiansMatchNumeric(sut, blocks);
}

TEST_F(ImuFactorTest, JacobiansMatchNumericWhenTheRotationResidualIsNearPi) {
  const ImuFactor sut(scenario_.preintegrations[1]);
  const imu::NavState& si = scenario_.keyframe_states[1];
  const imu::NavState& sj = scenario_.keyframe_states[2];
  // Keyframe j turned by nearly pi about an axis: r_dR is near pi, where Jr^-1 is largest.
  const SE3d T_j(sj.T_w_s.so3() * SO3d::exp(Vector3d(0.3, -0.2, 0.93).normalized() * (M_PI - 1e-3)),
                 sj.T_w_s.translation());
  expectJacobiansMatchNumeric(sut,
                              {poseBlock(si.T_w_s, pose_manifold_), vectorBlock(si.v_w), vectorBlock(VectorXd::Zero(6)),
                               poseBlock(T_j, pose_manifold_), vectorBlock(sj.v_w)},
                              1e-5);
}

TEST(BiasRandomWalkFactor, JacobiansMatchNumericAndWhitenByTheRandomWalk) {
  const imu::ImuNoise noise;
  const BiasRandomWalkFactor sut(noise, 0.5);
  Random random(31);
  VectorXd b_i(6);
  VectorXd b_j(6);
  b_i << random.vector3(0.1), random.vector3(0.1);
  b_j << random.vector3(0.1), random.vector3(0.1);
  expectJacobiansMatchNumeric(sut, {vectorBlock(b_i), vectorBlock(b_j)});
  VectorXd b_step = b_i;
  b_step(0) += noise.gyro_random_walk * std::sqrt(0.5);  // one sigma of drift over 0.5 s
  EXPECT_NEAR(evaluate(sut, {vectorBlock(b_i), vectorBlock(b_step)}).norm(), 1.0, 1e-9);
}

// ----------------------------------------------------------------------------------- reprojection
class ReprojectionFactorTest : public ::testing::Test {
 protected:
  PoseManifold pose_manifold_;
  UnitBearingManifold bearing_manifold_;
  PinholeIntrinsics intrinsics_;
  Random random_{41};
  SE3d T_s_c_ = test::makeViScenario({}).T_s_c;

  // A random reference and observing pose that both see a point at `depth` along a random bearing.
  std::vector<Block> randomCase(double inverse_depth, double rotation_scale) {
    const Vector3d bearing = (Vector3d(0, 0, 1) + random_.vector3(0.3)).normalized();
    const SE3d T_w_sr(SO3d::exp(random_.vector3(rotation_scale)), random_.vector3(2.0));
    // The observing camera: moved a little and turned a little, so the point stays in front.
    const SE3d T_w_cr = T_w_sr * T_s_c_;
    const SE3d T_w_ci = T_w_cr * SE3d(SO3d::exp(random_.vector3(0.1)), random_.vector3(0.3));
    const SE3d T_w_si = T_w_ci * T_s_c_.inverse();
    return {poseBlock(T_w_si, pose_manifold_),
            poseBlock(T_w_sr, pose_manifold_),
            poseBlock(T_s_c_, pose_manifold_),
            {VectorXd(bearing), &bearing_manifold_},
            vectorBlock(VectorXd::Constant(1, inverse_depth))};
  }
};

TEST_F(ReprojectionFactorTest, JacobiansMatchNumericAtRandomStates) {
  for (int trial = 0; trial < 20; ++trial) {
    const ReprojectionFactor sut(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5);
    expectJacobiansMatchNumeric(sut, randomCase(random_.uniform(0.1, 1.0), M_PI / std::sqrt(3.0)));
  }
}

TEST_F(ReprojectionFactorTest, JacobiansMatchNumericWithTinyRotations) {
  const ReprojectionFactor sut(Eigen::Vector2d(400.0, 250.0), intrinsics_, 1.0);
  expectJacobiansMatchNumeric(sut, randomCase(0.25, 1e-9));
}

TEST_F(ReprojectionFactorTest, JacobiansMatchNumericWithRotationsNearPi) {
  const ReprojectionFactor sut(Eigen::Vector2d(400.0, 250.0), intrinsics_, 1.0);
  std::vector<Block> blocks = randomCase(0.25, 0.0);
  // Both keyframes turned by nearly pi about the same world axis: their absolute rotations are near pi.
  const SO3d turn = SO3d::exp(Vector3d(0.2, 0.9, -0.3).normalized() * (M_PI - 1e-4));
  for (int k : {0, 1}) {
    const SE3d T = poseFromBlock(blocks[static_cast<std::size_t>(k)].value.data());
    blocks[static_cast<std::size_t>(k)].value = poseToBlock(SE3d(turn, Vector3d::Zero()) * T);
  }
  expectJacobiansMatchNumeric(sut, blocks);
}

TEST_F(ReprojectionFactorTest, APointNearInfinityStillConstrainsRotation) {
  const ReprojectionFactor sut(Eigen::Vector2d(380.0, 240.0), intrinsics_, 1.0);
  const std::vector<Block> blocks = randomCase(1e-9, 0.5);  // a billion metres away
  expectJacobiansMatchNumeric(sut, blocks, 1e-6, 1e-7);
  std::vector<Block> at_infinity = blocks;
  at_infinity[4].value(0) = 0.0;
  bool ok = false;
  const VectorXd r = evaluate(sut, at_infinity, &ok);
  ASSERT_TRUE(ok);
  EXPECT_TRUE(r.allFinite());
  EXPECT_LT((r - evaluate(sut, blocks)).norm(), 1e-6);
}

TEST_F(ReprojectionFactorTest, ResidualIsTheWhitenedPixelErrorAndBehindTheCameraIsNotEvaluable) {
  const std::vector<Block> blocks = randomCase(0.2, 0.3);
  // Project the point by hand with the SE3 types, independently of the factor's algebra.
  const SE3d T_w_si = poseFromBlock(blocks[0].value.data());
  const SE3d T_w_sr = poseFromBlock(blocks[1].value.data());
  const Vector3d p_cr = blocks[3].value / blocks[4].value(0);
  const Vector3d p_ci = (T_w_si * T_s_c_).inverse() * (T_w_sr * T_s_c_ * p_cr);
  const Eigen::Vector2d px(intrinsics_.fx * p_ci.x() / p_ci.z() + intrinsics_.cx,
                           intrinsics_.fy * p_ci.y() / p_ci.z() + intrinsics_.cy);
  const ReprojectionFactor sut(px + Eigen::Vector2d(3.0, -4.0), intrinsics_, 2.0);
  EXPECT_LT((evaluate(sut, blocks) - Eigen::Vector2d(-1.5, 2.0)).norm(), 1e-9);

  std::vector<Block> behind = blocks;
  behind[3].value = -behind[3].value;
  bool ok = true;
  evaluate(sut, behind, &ok);
  EXPECT_FALSE(ok);
}

TEST_F(ReprojectionFactorTest, HostObservationJacobianMatchesNumeric) {
  const ReprojectionHostFactor sut(Eigen::Vector2d(350.0, 260.0), intrinsics_, 1.0);
  for (int trial = 0; trial < 10; ++trial) {
    const Vector3d bearing = (Vector3d(0, 0, 1) + random_.vector3(0.4)).normalized();
    expectJacobiansMatchNumeric(sut, {{VectorXd(bearing), &bearing_manifold_}});
  }
}

// cam1 of a stereo rig: EuRoC's 11 cm baseline with a small relative rotation, and cam1's own intrinsics.
SE3d stereoOffsetT_c1_c0() {
  return SE3d(SO3d::exp(Vector3d(0.003, -0.01, 0.002)), Vector3d(-0.110, 0.0004, -0.0009));
}

TEST_F(ReprojectionFactorTest, SecondCameraJacobiansMatchNumericAtRandomStatesAndNearInfinity) {
  const PinholeIntrinsics cam1{457.587, 456.134, 379.999, 255.238};
  for (int trial = 0; trial < 20; ++trial) {
    const ReprojectionFactor sut(Eigen::Vector2d(320.0, 210.0), cam1, 1.2, stereoOffsetT_c1_c0());
    expectJacobiansMatchNumeric(sut, randomCase(random_.uniform(0.1, 1.0), M_PI / std::sqrt(3.0)));
  }
  const ReprojectionFactor far(Eigen::Vector2d(320.0, 210.0), cam1, 1.0, stereoOffsetT_c1_c0());
  expectJacobiansMatchNumeric(far, randomCase(1e-9, 0.5), 1e-6, 1e-7);
}

TEST_F(ReprojectionFactorTest, SecondCameraResidualIsCam1sPixelErrorAndIdentityOffsetIsCam0) {
  const std::vector<Block> blocks = randomCase(0.3, 0.4);
  const SE3d T_w_si = poseFromBlock(blocks[0].value.data());
  const SE3d T_w_sr = poseFromBlock(blocks[1].value.data());
  const Vector3d p_cr = blocks[3].value / blocks[4].value(0);
  const SE3d T_c1_c0 = stereoOffsetT_c1_c0();
  const Vector3d p_c1 = T_c1_c0 * ((T_w_si * T_s_c_).inverse() * (T_w_sr * T_s_c_ * p_cr));
  const PinholeIntrinsics cam1{457.587, 456.134, 379.999, 255.238};
  const Eigen::Vector2d px(cam1.fx * p_c1.x() / p_c1.z() + cam1.cx, cam1.fy * p_c1.y() / p_c1.z() + cam1.cy);
  const ReprojectionFactor sut(px + Eigen::Vector2d(-2.0, 1.0), cam1, 0.5, T_c1_c0);
  EXPECT_LT((evaluate(sut, blocks) - Eigen::Vector2d(4.0, -2.0)).norm(), 1e-8);
  // With the identity offset and cam0's intrinsics it is exactly the cam0 factor.
  const ReprojectionFactor as_cam0(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5, SE3d());
  const ReprojectionFactor cam0(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5);
  EXPECT_LT((evaluate(as_cam0, blocks) - evaluate(cam0, blocks)).norm(), 1e-12);
}

TEST_F(ReprojectionFactorTest, SecondCameraHostObservationFixesDepthAndItsJacobianMatchesNumeric) {
  const PinholeIntrinsics cam1{457.587, 456.134, 379.999, 255.238};
  const SE3d T_c1_c0 = stereoOffsetT_c1_c0();
  for (int trial = 0; trial < 10; ++trial) {
    const Vector3d bearing = (Vector3d(0, 0, 1) + random_.vector3(0.4)).normalized();
    const SecondCameraHostFactor sut(Eigen::Vector2d(350.0, 260.0), cam1, 1.0, T_c1_c0);
    expectJacobiansMatchNumeric(
        sut, {{VectorXd(bearing), &bearing_manifold_}, vectorBlock(VectorXd::Constant(1, random_.uniform(0.05, 2.0)))});
  }
  // The residual is zero at the true depth and grows with a wrong one: the baseline makes depth observable.
  const Vector3d bearing = Vector3d(0.1, -0.05, 1.0).normalized();
  const double depth = 4.0;
  const Vector3d p_c1 = T_c1_c0 * (bearing * depth);
  const Eigen::Vector2d px(cam1.fx * p_c1.x() / p_c1.z() + cam1.cx, cam1.fy * p_c1.y() / p_c1.z() + cam1.cy);
  const SecondCameraHostFactor sut(px, cam1, 1.0, T_c1_c0);
  const Block b{VectorXd(bearing), &bearing_manifold_};
  EXPECT_LT(evaluate(sut, {b, vectorBlock(VectorXd::Constant(1, 1.0 / depth))}).norm(), 1e-9);
  // 10 % off in depth at 4 m moves the cam1 projection by f * B * (1/3.6 - 1/4) ~ 1.4 px.
  EXPECT_GT(evaluate(sut, {b, vectorBlock(VectorXd::Constant(1, 1.0 / (0.9 * depth)))}).norm(), 1.2);
}

// ------------------------------------------------------------------- one-block inverse-depth points
// The same random geometry as ReprojectionFactorTest, with the point as (a, b, rho): the observing pose, the
// reference pose, the extrinsics and the point block, plus the bearing form of the same point for comparisons.
class InverseDepthPointFactorTest : public ReprojectionFactorTest {
 protected:
  // blocks[3] (bearing) and blocks[4] (inverse distance) of a bearing case as one (a, b, rho) block.
  static std::vector<Block> asPointBlocks(const std::vector<Block>& bearing_blocks) {
    Vector3d point;
    EXPECT_TRUE(inverseDepthPointFromBearing(bearing_blocks[3].value, bearing_blocks[4].value(0), point));
    return {bearing_blocks[0], bearing_blocks[1], bearing_blocks[2], vectorBlock(point)};
  }
  std::vector<Block> randomPointCase(double inverse_distance, double rotation_scale) {
    return asPointBlocks(randomCase(inverse_distance, rotation_scale));
  }
  const PinholeIntrinsics cam1_{457.587, 456.134, 379.999, 255.238};
};

TEST_F(InverseDepthPointFactorTest, ConversionRoundTripsAndKeepsThePoint) {
  for (int trial = 0; trial < 200; ++trial) {
    // Bearings up to ~80 degrees off the optical axis, distances from 5 cm to a billion metres, and infinity.
    const Vector3d bearing = (Vector3d(0, 0, 1) + random_.vector3(2.5)).normalized();
    if (bearing.z() < 0.2) continue;
    const double inverse_distance = trial % 10 == 0 ? 0.0 : std::pow(10.0, random_.uniform(-9.0, 1.3));
    Vector3d point;
    ASSERT_TRUE(inverseDepthPointFromBearing(bearing, inverse_distance, point));
    EXPECT_GE(point.z(), 0.0);
    Vector3d bearing_back;
    double inverse_distance_back = -1.0;
    bearingFromInverseDepthPoint(point, bearing_back, inverse_distance_back);
    EXPECT_LT((bearing_back - bearing).norm(), 1e-14);
    EXPECT_NEAR(inverse_distance_back, inverse_distance, 1e-14 * std::max(1.0, inverse_distance));
    if (inverse_distance > 0.0) {  // the same 3D point: X = bearing / r = (a, b, 1) / rho
      const Vector3d X = bearing / inverse_distance;
      EXPECT_LT((inverseDepthPointInCamera(point) - X).norm(), 1e-12 * X.norm());
    }
    Vector3d point_again;  // and from the point side: (a, b, rho) -> bearing -> (a, b, rho)
    ASSERT_TRUE(inverseDepthPointFromBearing(bearing_back, inverse_distance_back, point_again));
    EXPECT_LT((point_again - point).norm(), 1e-12 * std::max(1.0, point.norm()));
  }
  // A hand-made case: the point (1, 2, 2) m, 3 m away; a = 0.5, b = 1, rho = 0.5.
  Vector3d point;
  ASSERT_TRUE(inverseDepthPointFromBearing(Vector3d(1, 2, 2) / 3.0, 1.0 / 3.0, point));
  EXPECT_LT((point - Vector3d(0.5, 1.0, 0.5)).norm(), 1e-15);
}

TEST_F(InverseDepthPointFactorTest, ABearingNearOrBehindTheReferenceImagePlaneHasNoPoint) {
  const Vector3d untouched(7.0, 8.0, 9.0);
  for (const Vector3d& bearing : {Vector3d(1, 0, 0), Vector3d(0.999, 0.0, 0.05).normalized(),
                                  Vector3d(0.3, 0.2, -0.9).normalized(), Vector3d(0, 0, -1)}) {
    Vector3d point = untouched;
    EXPECT_FALSE(inverseDepthPointFromBearing(bearing, 0.5, point)) << bearing.transpose();
    EXPECT_EQ(point, untouched);
  }
  Vector3d point = untouched;
  EXPECT_FALSE(inverseDepthPointFromBearing(Vector3d(0, 0, 1), std::nan(""), point));
  EXPECT_FALSE(inverseDepthPointFromBearing(Vector3d(std::nan(""), 0, 1), 0.5, point));
  EXPECT_FALSE(inverseDepthPointFromBearing(Vector3d::Zero(), 0.5, point));
  EXPECT_EQ(point, untouched);
  // Just inside the limit it converts.
  const double z = kMinInverseDepthPointBearingZ + 1e-6;
  EXPECT_TRUE(inverseDepthPointFromBearing(Vector3d(std::sqrt(1.0 - z * z), 0.0, z), 0.5, point));
}

TEST_F(InverseDepthPointFactorTest, JacobiansMatchNumericAtRandomStates) {
  for (int trial = 0; trial < 20; ++trial) {
    const InverseDepthPointFactor sut(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5);
    expectJacobiansMatchNumeric(sut, randomPointCase(random_.uniform(0.1, 1.0), M_PI / std::sqrt(3.0)));
  }
}

TEST_F(InverseDepthPointFactorTest, JacobiansMatchNumericWithTinyRotationsAndRotationsNearPi) {
  const InverseDepthPointFactor sut(Eigen::Vector2d(400.0, 250.0), intrinsics_, 1.0);
  expectJacobiansMatchNumeric(sut, randomPointCase(0.25, 1e-9));
  std::vector<Block> blocks = randomPointCase(0.25, 0.0);
  const SO3d turn = SO3d::exp(Vector3d(0.2, 0.9, -0.3).normalized() * (M_PI - 1e-4));
  for (int k : {0, 1}) {
    const SE3d T = poseFromBlock(blocks[static_cast<std::size_t>(k)].value.data());
    blocks[static_cast<std::size_t>(k)].value = poseToBlock(SE3d(turn, Vector3d::Zero()) * T);
  }
  expectJacobiansMatchNumeric(sut, blocks);
}

TEST_F(InverseDepthPointFactorTest, APointNearInfinityStillConstrainsRotationAndIsFiniteAtRhoZero) {
  for (const double rho : {1e-6, 1e-9}) {  // a million and a billion metres away
    const InverseDepthPointFactor sut(Eigen::Vector2d(380.0, 240.0), intrinsics_, 1.0);
    const std::vector<Block> blocks = randomPointCase(rho, 0.5);
    expectJacobiansMatchNumeric(sut, blocks, 1e-6, 1e-7);
    // The rotation Jacobian of the observing pose does not vanish with rho.
    std::vector<double> J(2 * kPoseSize);
    std::vector<double*> jacobians = {J.data(), nullptr, nullptr, nullptr};
    std::vector<const double*> parameters;
    for (const Block& b : blocks) parameters.push_back(b.value.data());
    Eigen::Vector2d r;
    ASSERT_TRUE(sut.Evaluate(parameters.data(), r.data(), jacobians.data()));
    using PoseJacobian = Eigen::Matrix<double, 2, kPoseSize, Eigen::RowMajor>;
    EXPECT_GT(Eigen::Map<PoseJacobian>(J.data()).rightCols<4>().norm(), 100.0);

    std::vector<Block> at_infinity = blocks;
    at_infinity[3].value(2) = 0.0;
    bool ok = false;
    const VectorXd r_inf = evaluate(sut, at_infinity, &ok);
    ASSERT_TRUE(ok);
    EXPECT_TRUE(r_inf.allFinite());
    EXPECT_LT((r_inf - evaluate(sut, blocks)).norm(), 1e-3 * rho / 1e-6);
    expectJacobiansMatchNumeric(sut, at_infinity, 1e-6, 1e-7);
  }
}

TEST_F(InverseDepthPointFactorTest, ResidualIsTheOldFactorsOnTheSamePointAndBehindTheCameraIsNotEvaluable) {
  for (int trial = 0; trial < 10; ++trial) {
    const std::vector<Block> bearing_blocks = randomCase(random_.uniform(0.05, 1.0), 0.5);
    const std::vector<Block> point_blocks = asPointBlocks(bearing_blocks);
    // By hand with the SE3 types, independently of either factor's algebra.
    const SE3d T_w_si = poseFromBlock(point_blocks[0].value.data());
    const SE3d T_w_sr = poseFromBlock(point_blocks[1].value.data());
    const Vector3d p_cr = inverseDepthPointInCamera(point_blocks[3].value);
    const Vector3d p_ci = (T_w_si * T_s_c_).inverse() * (T_w_sr * T_s_c_ * p_cr);
    const Eigen::Vector2d px(intrinsics_.fx * p_ci.x() / p_ci.z() + intrinsics_.cx,
                             intrinsics_.fy * p_ci.y() / p_ci.z() + intrinsics_.cy);
    const InverseDepthPointFactor sut(px + Eigen::Vector2d(3.0, -4.0), intrinsics_, 2.0);
    EXPECT_LT((evaluate(sut, point_blocks) - Eigen::Vector2d(-1.5, 2.0)).norm(), 1e-8);
    const ReprojectionFactor old(px + Eigen::Vector2d(3.0, -4.0), intrinsics_, 2.0);
    EXPECT_LT((evaluate(sut, point_blocks) - evaluate(old, bearing_blocks)).norm(), 1e-9);
    // cam1 too.
    const InverseDepthPointFactor sut1(Eigen::Vector2d(320.0, 210.0), cam1_, 1.2, stereoOffsetT_c1_c0());
    const ReprojectionFactor old1(Eigen::Vector2d(320.0, 210.0), cam1_, 1.2, stereoOffsetT_c1_c0());
    EXPECT_LT((evaluate(sut1, point_blocks) - evaluate(old1, bearing_blocks)).norm(), 1e-9);
  }
  // The observing camera turned around: the point is behind it.
  std::vector<Block> behind = randomPointCase(0.2, 0.3);
  const SE3d T_w_si = poseFromBlock(behind[0].value.data());
  const SE3d T_w_ci = T_w_si * T_s_c_;
  const SE3d T_w_ci_turned = T_w_ci * SE3d(SO3d::exp(Vector3d(0.0, M_PI, 0.0)), Vector3d::Zero());
  behind[0].value = poseToBlock(T_w_ci_turned * T_s_c_.inverse());
  const InverseDepthPointFactor sut(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.0);
  bool ok = true;
  evaluate(sut, behind, &ok);
  EXPECT_FALSE(ok);
}

TEST_F(InverseDepthPointFactorTest, SecondCameraJacobiansMatchNumericAtRandomStatesAndNearInfinity) {
  for (int trial = 0; trial < 20; ++trial) {
    const InverseDepthPointFactor sut(Eigen::Vector2d(320.0, 210.0), cam1_, 1.2, stereoOffsetT_c1_c0());
    expectJacobiansMatchNumeric(sut, randomPointCase(random_.uniform(0.1, 1.0), M_PI / std::sqrt(3.0)));
  }
  const InverseDepthPointFactor far(Eigen::Vector2d(320.0, 210.0), cam1_, 1.0, stereoOffsetT_c1_c0());
  expectJacobiansMatchNumeric(far, randomPointCase(1e-9, 0.5), 1e-6, 1e-7);
  // With the identity offset and cam0's intrinsics it is exactly the cam0 factor.
  const std::vector<Block> blocks = randomPointCase(0.3, 0.4);
  const InverseDepthPointFactor as_cam0(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5, SE3d());
  const InverseDepthPointFactor cam0(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5);
  EXPECT_LT((evaluate(as_cam0, blocks) - evaluate(cam0, blocks)).norm(), 1e-12);
}

TEST_F(InverseDepthPointFactorTest, HostObservationIsLinearInABAndIgnoresRho) {
  for (int trial = 0; trial < 10; ++trial) {
    const Vector3d bearing = (Vector3d(0, 0, 1) + random_.vector3(0.4)).normalized();
    const double inverse_distance = random_.uniform(0.0, 2.0);
    Vector3d point;
    ASSERT_TRUE(inverseDepthPointFromBearing(bearing, inverse_distance, point));
    const InverseDepthPointHostFactor sut(Eigen::Vector2d(350.0, 260.0), intrinsics_, 1.3);
    expectJacobiansMatchNumeric(sut, {vectorBlock(point)});
    const ReprojectionHostFactor old(Eigen::Vector2d(350.0, 260.0), intrinsics_, 1.3);
    EXPECT_LT((evaluate(sut, {vectorBlock(point)}) - evaluate(old, {{VectorXd(bearing), &bearing_manifold_}})).norm(),
              1e-9);
    Vector3d moved_in_depth = point;
    moved_in_depth.z() *= 3.0;
    EXPECT_EQ(evaluate(sut, {vectorBlock(point)}), evaluate(sut, {vectorBlock(moved_in_depth)}));
  }
}

TEST_F(InverseDepthPointFactorTest, SecondCameraHostObservationFixesDepthAndItsJacobianMatchesNumeric) {
  const SE3d T_c1_c0 = stereoOffsetT_c1_c0();
  for (int trial = 0; trial < 10; ++trial) {
    const Vector3d bearing = (Vector3d(0, 0, 1) + random_.vector3(0.4)).normalized();
    const double inverse_distance = random_.uniform(0.05, 2.0);
    Vector3d point;
    ASSERT_TRUE(inverseDepthPointFromBearing(bearing, inverse_distance, point));
    const InverseDepthPointSecondCameraHostFactor sut(Eigen::Vector2d(350.0, 260.0), cam1_, 1.0, T_c1_c0);
    expectJacobiansMatchNumeric(sut, {vectorBlock(point)});
    const SecondCameraHostFactor old(Eigen::Vector2d(350.0, 260.0), cam1_, 1.0, T_c1_c0);
    EXPECT_LT(
        (evaluate(sut, {vectorBlock(point)}) -
         evaluate(old, {{VectorXd(bearing), &bearing_manifold_}, vectorBlock(VectorXd::Constant(1, inverse_distance))}))
            .norm(),
        1e-9);
  }
  // Near infinity: finite, and the Jacobian still right.
  Vector3d far;
  ASSERT_TRUE(inverseDepthPointFromBearing(Vector3d(0.1, -0.05, 1.0).normalized(), 1e-9, far));
  const InverseDepthPointSecondCameraHostFactor far_sut(Eigen::Vector2d(350.0, 260.0), cam1_, 1.0, T_c1_c0);
  expectJacobiansMatchNumeric(far_sut, {vectorBlock(far)}, 1e-6, 1e-7);
  // Zero residual at the true depth, and a wrong depth shows: the baseline makes depth observable.
  const Vector3d bearing = Vector3d(0.1, -0.05, 1.0).normalized();
  const double depth = 4.0;
  const Vector3d p_c1 = T_c1_c0 * (bearing * depth);
  const Eigen::Vector2d px(cam1_.fx * p_c1.x() / p_c1.z() + cam1_.cx, cam1_.fy * p_c1.y() / p_c1.z() + cam1_.cy);
  const InverseDepthPointSecondCameraHostFactor sut(px, cam1_, 1.0, T_c1_c0);
  Vector3d truth;
  Vector3d wrong;
  ASSERT_TRUE(inverseDepthPointFromBearing(bearing, 1.0 / depth, truth));
  ASSERT_TRUE(inverseDepthPointFromBearing(bearing, 1.0 / (0.9 * depth), wrong));
  EXPECT_LT(evaluate(sut, {vectorBlock(truth)}).norm(), 1e-9);
  EXPECT_GT(evaluate(sut, {vectorBlock(wrong)}).norm(), 1.2);
}

// ------------------------------------------------------------------------------------------- priors
TEST(PriorFactors, PosePriorJacobianMatchesNumericIncludingNearPi) {
  const PoseManifold manifold;
  Random random(51);
  Eigen::Matrix<double, 6, 6> S = Eigen::Matrix<double, 6, 6>::Identity();
  S.diagonal() << 10, 20, 30, 40, 50, 60;
  S(0, 4) = 3.0;
  const SE3d prior = random.pose(3.0);
  const PosePriorFactor sut(prior, S);
  for (int trial = 0; trial < 10; ++trial) {
    expectJacobiansMatchNumeric(sut, {poseBlock(random.pose(3.0), manifold)});
  }
  const SE3d near_pi(prior.so3() * SO3d::exp(Vector3d(1, 2, 3).normalized() * (M_PI - 1e-4)), prior.translation());
  expectJacobiansMatchNumeric(sut, {poseBlock(near_pi, manifold)}, 1e-5);
  EXPECT_LT(evaluate(sut, {poseBlock(prior, manifold)}).norm(), 1e-12);
}

TEST(PriorFactors, BearingPriorIsTheManifoldMinusAndItsJacobianMatchesNumeric) {
  const UnitBearingManifold manifold;
  Random random(52);
  const Vector3d b0 = random.unitVector();
  const Eigen::Matrix2d S = Eigen::Vector2d(5.0, 7.0).asDiagonal();
  const BearingPriorFactor sut(b0, S);
  for (int trial = 0; trial < 10; ++trial) {
    const Vector3d b = (b0 + random.vector3(0.8)).normalized();
    expectJacobiansMatchNumeric(sut, {{VectorXd(b), &manifold}});
    Eigen::Vector2d minus;
    manifold.Minus(b.data(), b0.data(), minus.data());
    EXPECT_LT((evaluate(sut, {{VectorXd(b), &manifold}}) - S * minus).norm(), 1e-12);
  }
  expectJacobiansMatchNumeric(sut, {{VectorXd(b0), &manifold}});  // at the prior itself
}

TEST(PriorFactors, VectorPriorJacobianMatchesNumeric) {
  Random random(53);
  Eigen::Matrix3d S = Eigen::Matrix3d::Identity() * 4.0;
  S(0, 2) = 1.0;
  const VectorPriorFactor<3> velocity_prior(random.vector3(1.0), S);
  expectJacobiansMatchNumeric(velocity_prior, {vectorBlock(random.vector3(1.0))});
  const VectorPriorFactor<1> inverse_depth_prior(Eigen::Matrix<double, 1, 1>(0.5), Eigen::Matrix<double, 1, 1>(10.0));
  expectJacobiansMatchNumeric(inverse_depth_prior, {vectorBlock(VectorXd::Constant(1, 0.7))});
  EXPECT_NEAR(evaluate(inverse_depth_prior, {vectorBlock(VectorXd::Constant(1, 0.7))})(0), 2.0, 1e-12);
}

TEST(SqrtInformation, WhitensTheCovarianceToIdentity) {
  Random random(54);
  Eigen::Matrix<double, 9, 9> A;
  for (int i = 0; i < 9; ++i) A.col(i) << random.vector3(1.0), random.vector3(1.0), random.vector3(1.0);
  const Eigen::Matrix<double, 9, 9> covariance = A * A.transpose() + 1e-3 * Eigen::Matrix<double, 9, 9>::Identity();
  const Eigen::Matrix<double, 9, 9> S = sqrtInformationFromCovariance<9>(covariance);
  EXPECT_LT((S * covariance * S.transpose() - Eigen::Matrix<double, 9, 9>::Identity()).cwiseAbs().maxCoeff(), 1e-9);
}

// ------------------------------------------------------------------------- the camera-IMU time offset
class TimeOffsetPointFactorTest : public InverseDepthPointFactorTest {
 protected:
  KeyframeMotion randomMotion() { return {random_.vector3(1.5), random_.vector3(1.0), random_.uniform(-0.03, 0.03)}; }
};

TEST_F(TimeOffsetPointFactorTest, JacobiansMatchNumericAtRandomStatesMotionsAndOffsets) {
  for (int trial = 0; trial < 20; ++trial) {
    const KeyframeMotion observing = randomMotion();
    const KeyframeMotion reference = randomMotion();
    std::vector<Block> blocks = randomPointCase(random_.uniform(0.1, 1.0), M_PI / std::sqrt(3.0));
    blocks.push_back(vectorBlock(VectorXd::Constant(1, random_.uniform(-0.05, 0.05))));
    const TimeOffsetPointFactor cam0(
        std::make_unique<InverseDepthPointFactor>(Eigen::Vector2d(300.0, 200.0), intrinsics_, 1.5), observing,
        reference);
    expectJacobiansMatchNumeric(cam0, blocks);
    const TimeOffsetPointFactor cam1(
        std::make_unique<InverseDepthPointFactor>(Eigen::Vector2d(320.0, 210.0), cam1_, 1.2, stereoOffsetT_c1_c0()),
        observing, reference);
    expectJacobiansMatchNumeric(cam1, blocks);
  }
}

TEST_F(TimeOffsetPointFactorTest, WithoutMotionItIsTheFactorWithoutOffsetAndTdIsUnobservable) {
  std::vector<Block> blocks = randomPointCase(0.4, 0.5);
  const InverseDepthPointFactor inner(Eigen::Vector2d(310.0, 190.0), intrinsics_, 1.0);
  blocks.push_back(vectorBlock(VectorXd::Constant(1, 0.02)));
  const TimeOffsetPointFactor sut(
      std::make_unique<InverseDepthPointFactor>(Eigen::Vector2d(310.0, 190.0), intrinsics_, 1.0), KeyframeMotion{},
      KeyframeMotion{});
  const std::vector<Block> inner_blocks(blocks.begin(), blocks.begin() + 4);
  EXPECT_LT((evaluate(sut, blocks) - evaluate(inner, inner_blocks)).norm(), 1e-12);

  std::vector<const double*> parameters;
  for (const Block& b : blocks) parameters.push_back(b.value.data());
  std::vector<MatrixXdRowMajor> J = {MatrixXdRowMajor(2, 7), MatrixXdRowMajor(2, 7), MatrixXdRowMajor(2, 7),
                                     MatrixXdRowMajor(2, 3), MatrixXdRowMajor(2, 1)};
  std::vector<double*> J_ptrs;
  for (auto& m : J) J_ptrs.push_back(m.data());
  Eigen::Vector2d residual;
  ASSERT_TRUE(sut.Evaluate(parameters.data(), residual.data(), J_ptrs.data()));
  EXPECT_EQ(J[4].norm(), 0.0);
}

// A body turning and moving at constant rates, its camera's images taken td_true after the state times that
// the keyframes' corrections say: the factor's residual vanishes at the true offset, and not elsewhere.
TEST_F(TimeOffsetPointFactorTest, TheTrueOffsetExplainsImagesTakenLateOnAMovingBody) {
  const Vector3d v_w(1.2, 0.3, -0.2);
  const Vector3d omega_s(0.2, 0.9, -0.4);
  const SE3d T_w_s0(SO3d::exp(Vector3d(0.1, -0.2, 0.3)), Vector3d(1.0, 2.0, 0.5));
  // Constant body rate and world velocity: R(t) = R0 Exp(w t), p(t) = p0 + v t, exactly.
  const auto body_at = [&](double t) {
    return SE3d(T_w_s0.so3() * SO3d::exp(omega_s * t), T_w_s0.translation() + v_w * t);
  };
  const double td_true = 0.027;
  const double t_cam_r = 0.0;
  const double t_cam_i = 0.15;
  const KeyframeMotion reference{v_w, omega_s, 0.004};
  const KeyframeMotion observing{v_w, omega_s, 0.011};
  const SE3d T_w_cr = body_at(t_cam_r + td_true) * T_s_c_;
  const SE3d T_w_ci = body_at(t_cam_i + td_true) * T_s_c_;
  const Vector3d X_cr(0.3, -0.2, 4.0);
  const Vector3d X_ci = T_w_ci.inverse() * (T_w_cr * X_cr);
  ASSERT_GT(X_ci.z(), 1.0);
  const Eigen::Vector2d keypoint_px(intrinsics_.fx * X_ci.x() / X_ci.z() + intrinsics_.cx,
                                    intrinsics_.fy * X_ci.y() / X_ci.z() + intrinsics_.cy);
  const TimeOffsetPointFactor sut(std::make_unique<InverseDepthPointFactor>(keypoint_px, intrinsics_, 1.0), observing,
                                  reference);
  const auto residual_at = [&](double td) {
    return evaluate(sut, {poseBlock(body_at(t_cam_i + observing.time_correction_s), pose_manifold_),
                          poseBlock(body_at(t_cam_r + reference.time_correction_s), pose_manifold_),
                          poseBlock(T_s_c_, pose_manifold_),
                          vectorBlock(Vector3d(X_cr.x() / X_cr.z(), X_cr.y() / X_cr.z(), 1.0 / X_cr.z())),
                          vectorBlock(VectorXd::Constant(1, td))});
  };
  EXPECT_LT(residual_at(td_true).norm(), 1e-8);
  // Whitened pixels. Both keyframes move alike over the shift, so most of it cancels between them; what is left
  // (a fifth of a pixel here), summed over hundreds of observations against the IMU's poses, is what makes td
  // observable.
  EXPECT_GT(residual_at(0.0).norm(), 0.1);
  EXPECT_GT(residual_at(2.0 * td_true).norm(), 0.1);
}

}  // namespace
}  // namespace cvislam::factors
