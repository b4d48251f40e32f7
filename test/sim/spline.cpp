#include "test/sim/spline.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <string>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

namespace cvislam::sim {

namespace {

// Values of the degree-d uniform B-spline basis functions that are non-zero at x (knots at the integers),
// for the span [m, m+1) containing x: out[r] belongs to the basis function starting at knot m - d + r.
// de Boor / Cox recursion (Piegl and Tiller, The NURBS Book, algorithm A2.2) with unit knot spacing.
void uniformBasis(double x, int m, int d, std::array<double, QuinticSpline::kDegree + 1>& out) {
  std::array<double, QuinticSpline::kDegree + 1> left{};
  std::array<double, QuinticSpline::kDegree + 1> right{};
  out[0] = 1.0;
  for (int j = 1; j <= d; ++j) {
    left[static_cast<std::size_t>(j)] = x - static_cast<double>(m + 1 - j);
    right[static_cast<std::size_t>(j)] = static_cast<double>(m + j) - x;
    double saved = 0.0;
    for (int r = 0; r < j; ++r) {
      const auto ur = static_cast<std::size_t>(r);
      const double temp = out[ur] / (right[ur + 1] + left[static_cast<std::size_t>(j - r)]);
      out[ur] = saved + right[ur + 1] * temp;
      saved = left[static_cast<std::size_t>(j - r)] * temp;
    }
    out[static_cast<std::size_t>(j)] = saved;
  }
}

// Span index and spline parameter for time t: x = degree + t/h, m = floor(x) clamped to the valid spans.
void locate(double t_s, double h, int n_control, double& x, int& m) {
  constexpr int kP = QuinticSpline::kDegree;
  x = kP + t_s / h;
  x = std::clamp(x, static_cast<double>(kP), static_cast<double>(n_control));
  m = std::min(static_cast<int>(std::floor(x)), n_control - 1);
}

}  // namespace

QuinticSpline::QuinticSpline(double knot_spacing_s, std::vector<Vector6d> control_points)
    : knot_spacing_s_(knot_spacing_s), control_points_(std::move(control_points)) {}

double QuinticSpline::duration() const {
  return static_cast<double>(static_cast<int>(control_points_.size()) - kDegree) * knot_spacing_s_;
}

Vector6d QuinticSpline::evaluate(double t_s, int derivative_order) const {
  constexpr int kP = kDegree;
  const int n = static_cast<int>(control_points_.size());
  double x = 0.0;
  int m = 0;
  locate(t_s, knot_spacing_s_, n, x, m);
  const int k = std::clamp(derivative_order, 0, kP - 1);
  // The k-th derivative is a degree (kP - k) spline over the k-th backward differences of the control points,
  // on the same knots, divided by h^k.
  std::array<double, kP + 1> basis{};
  uniformBasis(x, m, kP - k, basis);
  static constexpr int kBinomial[5][5] = {
      {1, 0, 0, 0, 0}, {1, 1, 0, 0, 0}, {1, 2, 1, 0, 0}, {1, 3, 3, 1, 0}, {1, 4, 6, 4, 1}};
  Vector6d value = Vector6d::Zero();
  for (int r = 0; r <= kP - k; ++r) {
    const int i = m - (kP - k) + r;
    Vector6d diff = Vector6d::Zero();
    for (int j = 0; j <= k; ++j) {
      const double sign = (j % 2 == 0) ? 1.0 : -1.0;
      diff += sign * kBinomial[k][j] * control_points_[static_cast<std::size_t>(i - j)];
    }
    value += basis[static_cast<std::size_t>(r)] * diff;
  }
  return value / std::pow(knot_spacing_s_, k);
}

Result<QuinticSpline> fitQuinticSpline(const std::vector<double>& t_s, const std::vector<Vector6d>& values,
                                       double duration_s, const SplineFitOptions& options) {
  constexpr int kP = QuinticSpline::kDegree;
  if (t_s.size() != values.size() || t_s.empty()) {
    return Error{ErrorCode::kInvalidArgument, "spline fit: need as many times as values, and at least one"};
  }
  if (!(options.knot_spacing_s > 0.0) || !(duration_s > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "spline fit: knot spacing and duration must be positive"};
  }
  const int spans = std::max(1, static_cast<int>(std::ceil(duration_s / options.knot_spacing_s - 1e-9)));
  const int n = spans + kP;
  using Triplet = Eigen::Triplet<double>;
  std::vector<Triplet> triplets;
  Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(n, 6);
  std::array<double, kP + 1> basis{};
  std::size_t used = 0;
  for (std::size_t s = 0; s < t_s.size(); ++s) {
    if (t_s[s] < -1e-9 || t_s[s] > spans * options.knot_spacing_s + 1e-9) continue;
    ++used;
    double x = 0.0;
    int m = 0;
    locate(t_s[s], options.knot_spacing_s, n, x, m);
    uniformBasis(x, m, kP, basis);
    for (int a = 0; a <= kP; ++a) {
      const int ia = m - kP + a;
      rhs.row(ia) += basis[static_cast<std::size_t>(a)] * values[s].transpose();
      for (int b = 0; b <= kP; ++b) {
        triplets.emplace_back(ia, m - kP + b, basis[static_cast<std::size_t>(a)] * basis[static_cast<std::size_t>(b)]);
      }
    }
  }
  constexpr std::size_t kMinSamples = kP + 1;
  if (used < kMinSamples) {
    return Error{ErrorCode::kDataError, "spline fit: only " + std::to_string(used) + " samples in the time range"};
  }
  // Third differences c_i - 3c_{i-1} + 3c_{i-2} - c_{i-3}, plus a tiny ridge so that the system is never singular.
  const std::array<double, 4> d3 = {1.0, -3.0, 3.0, -1.0};
  for (int i = 3; i < n; ++i) {
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        triplets.emplace_back(i - a, i - b,
                              options.smoothing * d3[static_cast<std::size_t>(a)] * d3[static_cast<std::size_t>(b)]);
      }
    }
  }
  for (int i = 0; i < n; ++i) triplets.emplace_back(i, i, 1e-12);
  Eigen::SparseMatrix<double> normal(n, n);
  normal.setFromTriplets(triplets.begin(), triplets.end());
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(normal);
  if (solver.info() != Eigen::Success)
    return Error{ErrorCode::kDegenerate, "spline fit: normal equations are singular"};
  const Eigen::MatrixXd solution = solver.solve(rhs);
  std::vector<Vector6d> control(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) control[static_cast<std::size_t>(i)] = solution.row(i).transpose();
  return QuinticSpline(options.knot_spacing_s, std::move(control));
}

}  // namespace cvislam::sim
