// ceres::Manifold implementations for cvislam's states (layouts in state_layout.hpp).
#pragma once

#include <ceres/manifold.h>

namespace cvislam::factors {

// T_w_s as SO3 x R3: [p, q_xyzw] (+) [dp, dphi] = [p + dp, q * Exp(dphi)].
// Minus(y, x) = [p_y - p_x, Log(q_x^-1 q_y)].
class PoseManifold final : public ceres::Manifold {
 public:
  [[nodiscard]] int AmbientSize() const override { return 7; }
  [[nodiscard]] int TangentSize() const override { return 6; }
  bool Plus(const double* x, const double* delta, double* x_plus_delta) const override;
  bool PlusJacobian(const double* x, double* jacobian) const override;
  bool Minus(const double* y, const double* x, double* y_minus_x) const override;
  bool MinusJacobian(const double* x, double* jacobian) const override;
};

// A unit bearing b on the sphere S2. b (+) d = Exp(B(b) d) b moves b along a great circle by the angle |d|,
// B(b) = bearingTangentBasis(b). Minus(y, x) = B(x)^T w, with w the rotation vector that turns x into y
// along the great circle. Antipodal points have no unique Minus; one of the answers is returned.
class UnitBearingManifold final : public ceres::Manifold {
 public:
  [[nodiscard]] int AmbientSize() const override { return 3; }
  [[nodiscard]] int TangentSize() const override { return 2; }
  bool Plus(const double* x, const double* delta, double* x_plus_delta) const override;
  bool PlusJacobian(const double* x, double* jacobian) const override;
  bool Minus(const double* y, const double* x, double* y_minus_x) const override;
  bool MinusJacobian(const double* x, double* jacobian) const override;
};

}  // namespace cvislam::factors
