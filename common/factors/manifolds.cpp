#include "common/factors/manifolds.hpp"

#include <cmath>

#include "common/factors/state_layout.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::factors {

namespace {

constexpr int kRowMajor = Eigen::RowMajor;

Eigen::Quaterniond quaternionAt(const double* q_xyzw) {
  return {q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]};
}

}  // namespace

bool PoseManifold::Plus(const double* x, const double* delta, double* x_plus_delta) const {
  for (int i = 0; i < 3; ++i) x_plus_delta[i] = x[i] + delta[i];
  const geometry::SO3d R = geometry::SO3d(quaternionAt(x + 3)) * geometry::SO3d::exp(Eigen::Vector3d(delta + 3));
  const Eigen::Quaterniond& q = R.quaternion();
  x_plus_delta[3] = q.x();
  x_plus_delta[4] = q.y();
  x_plus_delta[5] = q.z();
  x_plus_delta[6] = q.w();
  return true;
}

bool PoseManifold::PlusJacobian(const double* x, double* jacobian) const {
  Eigen::Map<Eigen::Matrix<double, 7, 6, kRowMajor>> J(jacobian);
  J.setZero();
  J.topLeftCorner<3, 3>().setIdentity();
  J.bottomRightCorner<4, 3>() = quaternionPlusJacobian(x + 3);
  return true;
}

bool PoseManifold::Minus(const double* y, const double* x, double* y_minus_x) const {
  for (int i = 0; i < 3; ++i) y_minus_x[i] = y[i] - x[i];
  const Eigen::Vector3d phi =
      (geometry::SO3d(quaternionAt(x + 3)).inverse() * geometry::SO3d(quaternionAt(y + 3))).log();
  for (int i = 0; i < 3; ++i) y_minus_x[3 + i] = phi[i];
  return true;
}

bool PoseManifold::MinusJacobian(const double* x, double* jacobian) const {
  Eigen::Map<Eigen::Matrix<double, 6, 7, kRowMajor>> J(jacobian);
  J.setZero();
  J.topLeftCorner<3, 3>().setIdentity();
  J.bottomRightCorner<3, 4>() = 4.0 * quaternionPlusJacobian(x + 3).transpose();
  return true;
}

bool UnitBearingManifold::Plus(const double* x, const double* delta, double* x_plus_delta) const {
  const Eigen::Vector3d b(x[0], x[1], x[2]);
  const Eigen::Vector3d w = bearingTangentBasis(b) * Eigen::Vector2d(delta[0], delta[1]);
  Eigen::Map<Eigen::Vector3d>{x_plus_delta} = (geometry::SO3d::exp(w) * b).normalized();
  return true;
}

bool UnitBearingManifold::PlusJacobian(const double* x, double* jacobian) const {
  const Eigen::Vector3d b(x[0], x[1], x[2]);
  Eigen::Map<Eigen::Matrix<double, 3, 2, kRowMajor>>{jacobian} = -geometry::hatSO3(b) * bearingTangentBasis(b);
  return true;
}

bool UnitBearingManifold::Minus(const double* y, const double* x, double* y_minus_x) const {
  const Eigen::Vector3d b_x(x[0], x[1], x[2]);
  const Eigen::Vector3d b_y(y[0], y[1], y[2]);
  Eigen::Map<Eigen::Vector2d>{y_minus_x} = bearingTangentBasis(b_x).transpose() * greatCircleRotation(b_x, b_y);
  return true;
}

bool UnitBearingManifold::MinusJacobian(const double* x, double* jacobian) const {
  const Eigen::Vector3d b(x[0], x[1], x[2]);
  Eigen::Map<Eigen::Matrix<double, 2, 3, kRowMajor>>{jacobian} =
      bearingTangentBasis(b).transpose() * geometry::hatSO3(b);
  return true;
}

}  // namespace cvislam::factors
