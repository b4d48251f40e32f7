// What the factor tests share: a seeded random source, and the check of a factor's analytic Jacobians against
// central differences of its residual along each parameter block's manifold.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include <ceres/cost_function.h>
#include <ceres/manifold.h>
#include <gtest/gtest.h>

#include "common/factors/manifolds.hpp"
#include "common/factors/state_layout.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::factors::test_support {

using Eigen::Vector3d;
using Eigen::VectorXd;
using geometry::SE3d;
using geometry::SO3d;
using MatrixXdRowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

class Random {
 public:
  explicit Random(std::uint64_t seed) : rng_(seed) {}
  double uniform(double a, double b) { return std::uniform_real_distribution<double>(a, b)(rng_); }
  Vector3d vector3(double scale) { return scale * Vector3d(uniform(-1, 1), uniform(-1, 1), uniform(-1, 1)); }
  SO3d rotation() { return SO3d::exp(vector3(M_PI) / std::sqrt(3.0)); }
  SE3d pose(double translation_scale) { return {rotation(), vector3(translation_scale)}; }
  Vector3d unitVector() { return vector3(1.0).normalized(); }

 private:
  std::mt19937_64 rng_;
};

// One parameter block of a factor under test, with its manifold (nullptr for a Euclidean block).
struct Block {
  VectorXd value;
  const ceres::Manifold* manifold = nullptr;
};

inline VectorXd evaluate(const ceres::CostFunction& cost, const std::vector<Block>& blocks, bool* ok = nullptr) {
  std::vector<const double*> parameters;
  for (const Block& b : blocks) parameters.push_back(b.value.data());
  VectorXd residual(cost.num_residuals());
  const bool evaluated = cost.Evaluate(parameters.data(), residual.data(), nullptr);
  if (ok != nullptr) *ok = evaluated;
  return residual;
}

// Compares, for every block, (analytic ambient Jacobian) x (manifold PlusJacobian) with the central
// difference of the residual along the manifold's tangent directions, x [+] (+-h e_k).
inline void expectJacobiansMatchNumeric(const ceres::CostFunction& cost, const std::vector<Block>& blocks,
                                        double tolerance = 1e-6, double h = 1e-6) {
  const int rows = cost.num_residuals();
  std::vector<const double*> parameters;
  std::vector<MatrixXdRowMajor> jacobians;
  std::vector<double*> jacobian_ptrs;
  for (const Block& b : blocks) {
    parameters.push_back(b.value.data());
    jacobians.emplace_back(rows, b.value.size());
  }
  for (auto& J : jacobians) jacobian_ptrs.push_back(J.data());
  VectorXd residual(rows);
  ASSERT_TRUE(cost.Evaluate(parameters.data(), residual.data(), jacobian_ptrs.data()));

  for (std::size_t i = 0; i < blocks.size(); ++i) {
    const Block& b = blocks[i];
    const int tangent = b.manifold != nullptr ? b.manifold->TangentSize() : static_cast<int>(b.value.size());
    Eigen::MatrixXd J_analytic = jacobians[i];
    if (b.manifold != nullptr) {
      MatrixXdRowMajor plus_jacobian(b.value.size(), tangent);
      ASSERT_TRUE(b.manifold->PlusJacobian(b.value.data(), plus_jacobian.data()));
      J_analytic = jacobians[i] * plus_jacobian;
    }
    Eigen::MatrixXd J_numeric(rows, tangent);
    for (int k = 0; k < tangent; ++k) {
      std::vector<Block> plus = blocks;
      std::vector<Block> minus = blocks;
      VectorXd delta = VectorXd::Zero(tangent);
      delta(k) = h;
      if (b.manifold != nullptr) {
        b.manifold->Plus(b.value.data(), delta.data(), plus[i].value.data());
        delta(k) = -h;
        b.manifold->Plus(b.value.data(), delta.data(), minus[i].value.data());
      } else {
        plus[i].value(k) += h;
        minus[i].value(k) -= h;
      }
      J_numeric.col(k) = (evaluate(cost, plus) - evaluate(cost, minus)) / (2.0 * h);
    }
    const double scale = std::max(1.0, J_numeric.cwiseAbs().maxCoeff());
    EXPECT_LT((J_analytic - J_numeric).cwiseAbs().maxCoeff(), tolerance * scale) << "block " << i << "\nanalytic\n"
                                                                                 << J_analytic << "\nnumeric\n"
                                                                                 << J_numeric;
  }
}

inline Block poseBlock(const SE3d& T, const PoseManifold& manifold) {
  return {poseToBlock(T), &manifold};
}
inline Block vectorBlock(const VectorXd& v) {
  return {v, nullptr};
}

}  // namespace cvislam::factors::test_support
