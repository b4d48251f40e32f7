// Central-difference Jacobians, the reference every analytic Jacobian in cvislam is tested against.
#pragma once

#include <Eigen/Core>

namespace cvislam::test {

// J(i, j) = d f_i / d x_j at x0, by central differences with step h.
// f maps Eigen::Matrix<double, N, 1> to Eigen::Matrix<double, M, 1>.
template <int M, int N, typename F>
Eigen::Matrix<double, M, N> numericJacobian(F&& f, const Eigen::Matrix<double, N, 1>& x0, double h = 1e-6) {
  Eigen::Matrix<double, M, N> J;
  for (int j = 0; j < N; ++j) {
    Eigen::Matrix<double, N, 1> dx = Eigen::Matrix<double, N, 1>::Zero();
    dx(j) = h;
    J.col(j) = (f(x0 + dx) - f(x0 - dx)) / (2.0 * h);
  }
  return J;
}

}  // namespace cvislam::test
