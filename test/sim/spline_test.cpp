#include "test/sim/spline.hpp"

#include <cmath>
#include <vector>

#include <gtest/gtest.h>

#include "test/sim/random.hpp"
#include "test/sim/trajectory.hpp"

namespace cvislam::sim {
namespace {

// A quadratic in every channel: a quintic B-spline reproduces it exactly, and its third differences vanish,
// so the smoothing term does not bias the fit.
Vector6d quadratic(double t, int order) {
  Vector6d c0, c1, c2;
  c0 << 1.0, -2.0, 0.5, 0.3, -0.1, 0.2;
  c1 << 0.4, 1.1, -0.7, 0.05, 0.02, -0.03;
  c2 << -0.3, 0.25, 0.1, 0.02, -0.01, 0.015;
  if (order == 0) return c0 + c1 * t + c2 * t * t;
  if (order == 1) return c1 + 2.0 * c2 * t;
  if (order == 2) return 2.0 * c2;
  return Vector6d::Zero();
}

TEST(QuinticSpline, FitReproducesAQuadraticAndItsDerivativesExactly) {
  std::vector<double> t;
  std::vector<Vector6d> y;
  constexpr double kDurationS = 4.0;
  for (double s = 0.0; s <= kDurationS + 1e-9; s += 0.02) {
    t.push_back(s);
    y.push_back(quadratic(s, 0));
  }
  SplineFitOptions options;
  options.knot_spacing_s = 0.1;
  auto sut = fitQuinticSpline(t, y, kDurationS, options);
  ASSERT_TRUE(sut.ok()) << sut.error().toString();
  // Rounding in the control points (~1e-10) grows by 1/h per derivative.
  constexpr double kTolerance[] = {1e-8, 1e-7, 1e-6, 1e-5};
  for (double s = 0.013; s < kDurationS; s += 0.37) {
    for (int order = 0; order <= 3; ++order) {
      EXPECT_LT((sut->evaluate(s, order) - quadratic(s, order)).norm(), kTolerance[order])
          << "t=" << s << " order=" << order;
    }
  }
}

TEST(QuinticSpline, DerivativesMatchCentralDifferencesForRandomControlPoints) {
  Rng rng(42);
  std::vector<Vector6d> control(30);
  for (Vector6d& c : control) {
    for (int i = 0; i < 6; ++i) c(i) = rng.uniform(-1.0, 1.0);
  }
  const QuinticSpline sut(0.2, control);
  constexpr double kStep = 1e-5;
  for (double s = 0.05; s < sut.duration() - 0.05; s += 0.29) {
    for (int order = 1; order <= 3; ++order) {
      const Vector6d numeric = (sut.evaluate(s + kStep, order - 1) - sut.evaluate(s - kStep, order - 1)) / (2 * kStep);
      const Vector6d analytic = sut.evaluate(s, order);
      EXPECT_LT((numeric - analytic).norm(), 1e-5 * (1.0 + analytic.norm())) << "t=" << s << " order=" << order;
    }
  }
}

TEST(BodyTrajectory, VelocityAndAngularRateMatchNumericDerivativesOfThePose) {
  Rng rng(7);
  std::vector<Vector6d> control(40);
  for (Vector6d& c : control) {
    for (int i = 0; i < 3; ++i) c(i) = rng.uniform(-2.0, 2.0);
    for (int i = 3; i < 6; ++i) c(i) = rng.uniform(-0.6, 0.6);
  }
  const BodyTrajectory sut(QuinticSpline(0.25, control));
  constexpr double kStep = 1e-5;
  for (double s = 0.1; s < sut.duration() - 0.1; s += 0.31) {
    const KinematicState x = sut.state(s);
    const KinematicState before = sut.state(s - kStep), after = sut.state(s + kStep);
    const Eigen::Vector3d v_numeric = (after.T_w_b.translation() - before.T_w_b.translation()) / (2 * kStep);
    const Eigen::Vector3d a_numeric = (after.v_w - before.v_w) / (2 * kStep);
    // R(t + h) = R(t - h) exp(2 h omega_b)  (the angular rate is a right, body-frame increment).
    const Eigen::Vector3d omega_numeric = (before.T_w_b.so3().inverse() * after.T_w_b.so3()).log() / (2 * kStep);
    EXPECT_LT((v_numeric - x.v_w).norm(), 1e-6) << "t=" << s;
    EXPECT_LT((a_numeric - x.a_w).norm(), 1e-5) << "t=" << s;
    EXPECT_LT((omega_numeric - x.omega_b).norm(), 1e-6) << "t=" << s;
  }
}

TEST(BodyTrajectory, LevelFlightHasTheImuXAxisUpAndTheCameraAxisForward) {
  Vector6d level;
  level << 0.0, 0.0, 1.0, 0.0, 0.0, 0.0;  // yaw 0: flying along world +x
  const BodyTrajectory sut(QuinticSpline(0.1, std::vector<Vector6d>(8, level)));
  const Eigen::Matrix3d R_w_b = sut.state(0.1).T_w_b.rotationMatrix();
  EXPECT_LT((R_w_b.col(0) - Eigen::Vector3d::UnitZ()).norm(), 1e-12);  // IMU x up, as on the EuRoC MAV
  EXPECT_LT((R_w_b.col(2) - Eigen::Vector3d::UnitX()).norm(), 1e-12);  // z forward
}

TEST(ReplayInput, RefusesPosesWhoseImuXAxisIsNotUp) {
  dataset::Trajectory poses(3);
  for (std::size_t i = 0; i < poses.size(); ++i) {
    poses[i].t_ns = static_cast<std::int64_t>(i) * 5'000'000;
    poses[i].T_w_b = geometry::SE3d();  // identity: body x horizontal, z (camera) pointing up
  }
  auto sut = pathSamplesFromPoses(poses, 1.0);
  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("x axis should point up"), std::string::npos) << sut.error().message();
}

}  // namespace
}  // namespace cvislam::sim
