// Tests of common/geometry/lie.hpp: group axioms, exp/log against the matrix exponential, the adjoint, and
// every Jacobian against central differences, at random points, near zero and near pi.
#include "common/geometry/lie.hpp"

#include <cmath>
#include <random>
#include <vector>

#include <gtest/gtest.h>
#include <unsupported/Eigen/MatrixFunctions>

#include "test/support/numeric_diff.hpp"

namespace cvislam::geometry {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Angles that exercise the Taylor branches, their thresholds and the neighbourhood of pi.
const std::vector<double> kEdgeAngles = {0.0,    1e-12,  1e-8,   1e-5, 1e-3,       1e-2,       0.3,       0.4999,
                                         0.5001, 0.9999, 1.0001, 1.7,  kPi - 1e-2, kPi - 1e-4, kPi - 1e-6};

template <typename Group>
struct Traits;

template <>
struct Traits<SO3d> {
  static SO3d::Tangent tangent(std::mt19937& rng, double angle) {
    std::normal_distribution<double> n(0.0, 1.0);
    const Eigen::Vector3d axis = Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
    return angle * axis;
  }
};

template <>
struct Traits<SE3d> {
  static SE3d::Tangent tangent(std::mt19937& rng, double angle) {
    std::uniform_real_distribution<double> u(-2.0, 2.0);
    SE3d::Tangent xi;
    xi << u(rng), u(rng), u(rng), Traits<SO3d>::tangent(rng, angle);
    return xi;
  }
};

template <>
struct Traits<Sim3d> {
  static Sim3d::Tangent tangent(std::mt19937& rng, double angle) {
    std::uniform_real_distribution<double> u(-2.0, 2.0);
    std::uniform_real_distribution<double> s(-1.0, 1.0);
    Sim3d::Tangent zeta;
    zeta << u(rng), u(rng), u(rng), Traits<SO3d>::tangent(rng, angle), s(rng);
    return zeta;
  }
};

// 4x4 (or 3x3) matrix representation, so that every group can be checked against matrix algebra.
Eigen::Matrix3d asMatrix(const SO3d& R) {
  return R.matrix();
}
Eigen::Matrix4d asMatrix(const SE3d& T) {
  return T.matrix();
}
Eigen::Matrix4d asMatrix(const Sim3d& S) {
  return S.matrix();
}

template <typename Group>
class LieGroupTest : public ::testing::Test {
 protected:
  using Tangent = typename Group::Tangent;

  // Random tangents at edge angles plus random ones; the rotation angle always stays below pi.
  std::vector<Tangent> samples() {
    std::mt19937 rng(20261122);
    std::vector<Tangent> out;
    for (double angle : kEdgeAngles) {
      for (int k = 0; k < 3; ++k) out.push_back(Traits<Group>::tangent(rng, angle));
    }
    std::uniform_real_distribution<double> angle(0.0, kPi - 1e-3);
    for (int k = 0; k < 40; ++k) out.push_back(Traits<Group>::tangent(rng, angle(rng)));
    return out;
  }
};

using Groups = ::testing::Types<SO3d, SE3d, Sim3d>;
TYPED_TEST_SUITE(LieGroupTest, Groups);

TYPED_TEST(LieGroupTest, ExpMatchesMatrixExponentialOfHat) {
  for (const auto& x : this->samples()) {
    const auto expected = TypeParam::hat(x).exp().eval();
    EXPECT_LT((asMatrix(TypeParam::exp(x)) - expected).cwiseAbs().maxCoeff(), 1e-12) << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, LogInvertsExp) {
  for (const auto& x : this->samples()) {
    EXPECT_LT((TypeParam::exp(x).log() - x).cwiseAbs().maxCoeff(), 1e-9) << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, HatAndVeeAreInverse) {
  for (const auto& x : this->samples()) {
    EXPECT_LT((TypeParam::vee(TypeParam::hat(x)) - x).cwiseAbs().maxCoeff(), 1e-15);
  }
}

TYPED_TEST(LieGroupTest, ComposeInverseAndActMatchMatrices) {
  const auto xs = this->samples();
  for (std::size_t i = 0; i + 1 < xs.size(); ++i) {
    const TypeParam a = TypeParam::exp(xs[i]);
    const TypeParam b = TypeParam::exp(xs[i + 1]);
    EXPECT_LT((asMatrix(a * b) - asMatrix(a) * asMatrix(b)).cwiseAbs().maxCoeff(), 1e-12);
    EXPECT_LT((asMatrix(a * a.inverse()) - decltype(asMatrix(a))::Identity()).cwiseAbs().maxCoeff(), 1e-12);
    const Eigen::Vector3d p(0.3, -1.2, 2.5);
    Eigen::Vector3d expected;
    if constexpr (TypeParam::kDoF == 3) {
      expected = asMatrix(a) * p;
    } else {
      expected = (asMatrix(a) * p.homogeneous()).template head<3>();
    }
    EXPECT_LT(((a * p) - expected).cwiseAbs().maxCoeff(), 1e-12);
  }
}

TYPED_TEST(LieGroupTest, AdjointConjugatesTheAlgebra) {
  // X hat(d) X^-1 = hat(Ad(X) d)
  const auto xs = this->samples();
  for (std::size_t i = 0; i + 1 < xs.size(); ++i) {
    const TypeParam X = TypeParam::exp(xs[i]);
    const auto& d = xs[i + 1];
    const auto lhs = (asMatrix(X) * TypeParam::hat(d) * asMatrix(X.inverse())).eval();
    EXPECT_LT((lhs - TypeParam::hat(X.adjoint() * d)).cwiseAbs().maxCoeff(), 1e-11);
  }
}

TYPED_TEST(LieGroupTest, RightJacobianMatchesNumeric) {
  // exp(x + d) ~= exp(x) exp(Jr(x) d)  =>  Jr = d/dd log(exp(x)^-1 exp(x + d))
  constexpr int N = TypeParam::kDoF;
  for (const auto& x : this->samples()) {
    const TypeParam X_inv = TypeParam::exp(x).inverse();
    const auto numeric = test::numericJacobian<N, N>(
        [&](const typename TypeParam::Tangent& d) { return (X_inv * TypeParam::exp(x + d)).log(); },
        TypeParam::Tangent::Zero().eval());
    EXPECT_LT((TypeParam::rightJacobian(x) - numeric).cwiseAbs().maxCoeff(), 1e-7) << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, LeftJacobianMatchesNumeric) {
  constexpr int N = TypeParam::kDoF;
  for (const auto& x : this->samples()) {
    const TypeParam X_inv = TypeParam::exp(x).inverse();
    const auto numeric = test::numericJacobian<N, N>(
        [&](const typename TypeParam::Tangent& d) { return (TypeParam::exp(x + d) * X_inv).log(); },
        TypeParam::Tangent::Zero().eval());
    EXPECT_LT((TypeParam::leftJacobian(x) - numeric).cwiseAbs().maxCoeff(), 1e-7) << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, RightJacobianInverseMatchesNumeric) {
  // log(X exp(d)) ~= x + Jr(x)^-1 d
  constexpr int N = TypeParam::kDoF;
  for (const auto& x : this->samples()) {
    if (x.template segment<3>(TypeParam::kDoF == 3 ? 0 : 3).norm() > kPi - 1e-5) continue;  // log wraps at pi
    const TypeParam X = TypeParam::exp(x);
    const auto numeric =
        test::numericJacobian<N, N>([&](const typename TypeParam::Tangent& d) { return (X * TypeParam::exp(d)).log(); },
                                    TypeParam::Tangent::Zero().eval(), 1e-7);
    EXPECT_LT((TypeParam::rightJacobianInverse(x) - numeric).cwiseAbs().maxCoeff(), 2e-6) << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, LeftJacobianInverseMatchesNumeric) {
  constexpr int N = TypeParam::kDoF;
  for (const auto& x : this->samples()) {
    if (x.template segment<3>(TypeParam::kDoF == 3 ? 0 : 3).norm() > kPi - 1e-5) continue;  // log wraps at pi
    const TypeParam X = TypeParam::exp(x);
    const auto numeric =
        test::numericJacobian<N, N>([&](const typename TypeParam::Tangent& d) { return (TypeParam::exp(d) * X).log(); },
                                    TypeParam::Tangent::Zero().eval(), 1e-7);
    EXPECT_LT((TypeParam::leftJacobianInverse(x) - numeric).cwiseAbs().maxCoeff(), 2e-6) << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, JacobianInversesAreInversesIncludingNearPi) {
  constexpr int N = TypeParam::kDoF;
  using Matrix = Eigen::Matrix<double, N, N>;
  for (const auto& x : this->samples()) {
    EXPECT_LT(
        (TypeParam::rightJacobian(x) * TypeParam::rightJacobianInverse(x) - Matrix::Identity()).cwiseAbs().maxCoeff(),
        1e-9)
        << x.transpose();
    EXPECT_LT(
        (TypeParam::leftJacobian(x) * TypeParam::leftJacobianInverse(x) - Matrix::Identity()).cwiseAbs().maxCoeff(),
        1e-9)
        << x.transpose();
  }
}

TYPED_TEST(LieGroupTest, LeftJacobianIsAdjointTimesRightJacobian) {
  for (const auto& x : this->samples()) {
    const auto lhs = TypeParam::leftJacobian(x);
    const auto rhs = (TypeParam::exp(x).adjoint() * TypeParam::rightJacobian(x)).eval();
    EXPECT_LT((lhs - rhs).cwiseAbs().maxCoeff(), 1e-10) << x.transpose();
  }
}

// ------------------------------------------------------------------------- group-specific checks

TEST(SO3Test, AlgebraAdjointIsTheCommutator) {
  std::mt19937 rng(7);
  for (int k = 0; k < 20; ++k) {
    const Eigen::Vector3d a = Traits<SO3d>::tangent(rng, 1.0);
    const Eigen::Vector3d b = Traits<SO3d>::tangent(rng, 2.0);
    const Eigen::Matrix3d commutator = SO3d::hat(a) * SO3d::hat(b) - SO3d::hat(b) * SO3d::hat(a);
    EXPECT_LT((SO3d::hat(a.cross(b)) - commutator).cwiseAbs().maxCoeff(), 1e-14);
  }
}

TEST(SO3Test, LogReturnsAnglesUpToPiForBothQuaternionSigns) {
  const Eigen::Vector3d axis = Eigen::Vector3d(1.0, 2.0, -0.5).normalized();
  for (double angle : {kPi - 1e-9, kPi}) {
    const SO3d R = SO3d::exp(angle * axis);
    const SO3d R_flipped(Eigen::Quaterniond(-R.quaternion().coeffs()));
    for (const SO3d& r : {R, R_flipped}) {
      const Eigen::Vector3d phi = r.log();
      EXPECT_NEAR(phi.norm(), angle, 1e-9);
      EXPECT_LT((SO3d::exp(phi).matrix() - R.matrix()).cwiseAbs().maxCoeff(), 1e-12);
    }
  }
}

TEST(SO3Test, ConstructionFromMatrixAndQuaternionAgree) {
  const SO3d R = SO3d::exp(Eigen::Vector3d(0.2, -0.4, 1.1));
  EXPECT_LT((SO3d(R.matrix()).matrix() - R.matrix()).cwiseAbs().maxCoeff(), 1e-14);
  EXPECT_LT((SO3d(Eigen::Quaterniond(2.0 * R.quaternion().coeffs())).matrix() - R.matrix()).cwiseAbs().maxCoeff(),
            1e-14);
}

template <typename Group>
typename Group::Adjoint seriesJacobian(const typename Group::Adjoint& ad) {
  typename Group::Adjoint sum = Group::Adjoint::Identity();
  typename Group::Adjoint term = Group::Adjoint::Identity();
  for (int k = 1; k < 60; ++k) {
    term = (term * ad / static_cast<double>(k + 1)).eval();
    sum += term;
  }
  return sum;
}

TEST(SE3Test, ClosedFormJacobiansMatchThePowerSeries) {
  std::mt19937 rng(11);
  for (double angle : kEdgeAngles) {
    const SE3d::Tangent xi = Traits<SE3d>::tangent(rng, angle);
    EXPECT_LT((SE3d::leftJacobian(xi) - seriesJacobian<SE3d>(SE3d::ad(xi))).cwiseAbs().maxCoeff(), 1e-12);
    EXPECT_LT((SE3d::rightJacobian(xi) - seriesJacobian<SE3d>(-SE3d::ad(xi))).cwiseAbs().maxCoeff(), 1e-12);
  }
}

template <typename Group>
void expectAlgebraAdjointIsCommutator() {
  std::mt19937 rng(13);
  for (int k = 0; k < 20; ++k) {
    const auto a = Traits<Group>::tangent(rng, 1.0);
    const auto b = Traits<Group>::tangent(rng, 2.5);
    const auto commutator = (Group::hat(a) * Group::hat(b) - Group::hat(b) * Group::hat(a)).eval();
    EXPECT_LT((Group::hat(Group::ad(a) * b) - commutator).cwiseAbs().maxCoeff(), 1e-13);
  }
}

TEST(SE3Test, AlgebraAdjointIsTheCommutator) {
  expectAlgebraAdjointIsCommutator<SE3d>();
}
TEST(Sim3Test, AlgebraAdjointIsTheCommutator) {
  expectAlgebraAdjointIsCommutator<Sim3d>();
}

TEST(Sim3Test, ExpLogAtLargeAndTinyScales) {
  // sigma far from zero uses the moment recurrence; tiny sigma and tiny angle the series.
  for (double sigma : {-4.0, -2.5, -1e-9, 0.0, 1e-7, 2.5, 4.0}) {
    for (double angle : {0.0, 1e-6, 5e-3, 0.8, kPi - 1e-3}) {
      Sim3d::Tangent zeta;
      zeta << 0.4, -1.5, 2.0, angle * Eigen::Vector3d(0.6, 0.0, 0.8), sigma;
      const Eigen::Matrix4d expected = Sim3d::hat(zeta).exp();
      EXPECT_LT((Sim3d::exp(zeta).matrix() - expected).cwiseAbs().maxCoeff(), 1e-10 * expected.cwiseAbs().maxCoeff())
          << "sigma " << sigma << " angle " << angle;
      EXPECT_LT((Sim3d::exp(zeta).log() - zeta).cwiseAbs().maxCoeff(), 1e-9) << "sigma " << sigma << " angle " << angle;
    }
  }
}

TEST(Sim3Test, InverseAndScale) {
  const Sim3d S(2.5, SO3d::exp(Eigen::Vector3d(0.1, 0.2, 0.3)), Eigen::Vector3d(1.0, -2.0, 3.0));
  const Eigen::Vector3d p(0.5, 0.25, -4.0);
  EXPECT_LT((S.inverse() * (S * p) - p).norm(), 1e-12);
  EXPECT_NEAR((S * S.inverse()).scale(), 1.0, 1e-15);
  EXPECT_NEAR(((S * p) - (S * Eigen::Vector3d::Zero())).norm(), 2.5 * p.norm(), 1e-12);
}

}  // namespace
}  // namespace cvislam::geometry
