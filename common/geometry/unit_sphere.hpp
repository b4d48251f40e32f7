// Unit vectors (bearings, gravity directions) on the sphere S2: a tangent basis and the great-circle rotation
// between two of them. The bearing manifold and the gravity refinement of the IMU initialisation use them.
#pragma once

#include <cmath>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace cvislam::geometry {

// An orthonormal 3x2 basis of the plane perpendicular to the unit vector b, a fixed function of b.
inline Eigen::Matrix<double, 3, 2> bearingTangentBasis(const Eigen::Vector3d& b) {
  int axis = 0;  // the coordinate axis least aligned with b
  b.cwiseAbs().minCoeff(&axis);
  const Eigen::Vector3d u = b.cross(Eigen::Vector3d::Unit(axis)).normalized();
  Eigen::Matrix<double, 3, 2> B;
  B.col(0) = u;
  B.col(1) = b.cross(u);
  return B;
}

// The rotation vector that turns unit x into unit y along the great circle through both: the bearing
// manifold's Minus is bearingTangentBasis(x)^T times this. Antipodal points give one of the answers.
inline Eigen::Vector3d greatCircleRotation(const Eigen::Vector3d& x, const Eigen::Vector3d& y) {
  const Eigen::Vector3d s = x.cross(y);
  const double n = s.norm();
  const double c = x.dot(y);
  if (n < 1e-12) {
    if (c > 0.0) return s / c;  // theta / n -> 1 / c
    return std::atan2(n, c) * bearingTangentBasis(x).col(0);
  }
  return (std::atan2(n, c) / n) * s;
}

}  // namespace cvislam::geometry
