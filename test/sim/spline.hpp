// A uniform quintic B-spline in R^6 (position and three angles), with exact derivatives, fitted to samples by
// regularised least squares. Degree 5 makes positions C4, so accelerations and angular rates are smooth (C2
// or better) and an IMU derived from them has no steps.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "common/core/result.hpp"

namespace cvislam::sim {

using Vector6d = Eigen::Matrix<double, 6, 1>;

class QuinticSpline {
 public:
  static constexpr int kDegree = 5;

  QuinticSpline() = default;
  // Control points c_0..c_{n-1} on knots spaced knot_spacing_s apart; valid on [0, duration()].
  QuinticSpline(double knot_spacing_s, std::vector<Vector6d> control_points);

  // Value (order 0) or time derivative of order 1..4 at t in [0, duration()] (clamped to it).
  [[nodiscard]] Vector6d evaluate(double t_s, int derivative_order = 0) const;
  [[nodiscard]] double duration() const;
  [[nodiscard]] double knotSpacing() const { return knot_spacing_s_; }
  [[nodiscard]] const std::vector<Vector6d>& controlPoints() const { return control_points_; }

 private:
  double knot_spacing_s_ = 1.0;
  std::vector<Vector6d> control_points_;
};

struct SplineFitOptions {
  double knot_spacing_s = 0.1;
  // Weight of the squared third differences of the control points (per knot), relative to the squared
  // residuals of the samples. Keeps the fit smooth over gaps and damps measurement noise.
  double smoothing = 1e-3;
};

// Least-squares fit of a spline covering [0, duration_s] to samples (t_s, y); samples outside are ignored.
Result<QuinticSpline> fitQuinticSpline(const std::vector<double>& t_s, const std::vector<Vector6d>& values,
                                       double duration_s, const SplineFitOptions& options);

}  // namespace cvislam::sim
