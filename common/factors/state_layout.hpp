// How optimisation states are laid out in Ceres parameter blocks, shared by every factor and by the code
// that builds problems (the agent's local BA, the server's global BA).
//
//   pose      double[7]  [p_w_s (x, y, z), q_w_s (x, y, z, w)]   T_w_s; manifold PoseManifold (tangent [dp, dphi])
//   velocity  double[3]  v_w                                      Euclidean
//   bias      double[6]  [b_g, b_a]                               Euclidean
//   bearing   double[3]  unit vector in the reference camera      manifold UnitBearingManifold (tangent 2)
//   inv_depth double[1]  rho = 1 / depth along the bearing [1/m]  Euclidean
//   point     double[3]  [a, b, rho]: X_c = (a, b, 1) / rho         Euclidean; one block per point, in its
//                        reference camera (inverse_depth_point_factor.hpp), what the agent's local BA uses
//
// Rotation perturbations are on the right (R Exp(dphi)), positions additive in the world frame, as the
// convention in common/geometry/lie.hpp says. Factors give Ceres ambient Jacobians built so that, multiplied
// by the manifold's PlusJacobian, they equal the exact tangent-space Jacobian (see liftRotationJacobian).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "common/geometry/lie.hpp"
#include "common/geometry/unit_sphere.hpp"

namespace cvislam::factors {

inline constexpr int kPoseSize = 7;
inline constexpr int kPoseTangentSize = 6;
inline constexpr int kVelocitySize = 3;
inline constexpr int kBiasSize = 6;
inline constexpr int kBearingSize = 3;
inline constexpr int kBearingTangentSize = 2;

using PoseBlock = Eigen::Matrix<double, kPoseSize, 1>;

inline geometry::SE3d poseFromBlock(const double* block) {
  return {Eigen::Quaterniond(block[6], block[3], block[4], block[5]), Eigen::Vector3d(block[0], block[1], block[2])};
}

inline void poseToBlock(const geometry::SE3d& T, double* block) {
  const Eigen::Quaterniond& q = T.quaternion();
  block[0] = T.translation().x();
  block[1] = T.translation().y();
  block[2] = T.translation().z();
  block[3] = q.x();
  block[4] = q.y();
  block[5] = q.z();
  block[6] = q.w();
}

inline PoseBlock poseToBlock(const geometry::SE3d& T) {
  PoseBlock block;
  poseToBlock(T, block.data());
  return block;
}

// d(q * Exp(dphi)) / d(dphi) at dphi = 0, rows x, y, z, w: 1/2 [w I + [v]x; -v^T]. Its columns are orthogonal
// with norm 1/2 for a unit q, so P^T P = I/4.
inline Eigen::Matrix<double, 4, 3> quaternionPlusJacobian(const double* q_xyzw) {
  const Eigen::Vector3d v(q_xyzw[0], q_xyzw[1], q_xyzw[2]);
  Eigen::Matrix<double, 4, 3> P;
  P.topRows<3>() = 0.5 * (q_xyzw[3] * Eigen::Matrix3d::Identity() + geometry::hatSO3(v));
  P.bottomRows<1>() = -0.5 * v.transpose();
  return P;
}

// Turns a Jacobian with respect to the right rotation perturbation (R x 3) into one with respect to the four
// quaternion coefficients (R x 4) whose product with quaternionPlusJacobian() is the original: J 4 P^T.
template <int Rows>
Eigen::Matrix<double, Rows, 4> liftRotationJacobian(const Eigen::Matrix<double, Rows, 3>& J_tangent,
                                                    const double* q_xyzw) {
  return 4.0 * J_tangent * quaternionPlusJacobian(q_xyzw).transpose();
}

// Writes a Jacobian with respect to a pose's tangent [dp, dphi] (Rows x 6) as the ambient Jacobian Ceres
// expects for the 7 pose parameters (row-major Rows x 7); see liftRotationJacobian.
template <int Rows>
void writePoseJacobian(const Eigen::Matrix<double, Rows, 6>& J_tangent, const double* pose, double* jacobian) {
  Eigen::Map<Eigen::Matrix<double, Rows, kPoseSize, Eigen::RowMajor>> J_out(jacobian);
  J_out.template leftCols<3>() = J_tangent.template leftCols<3>();
  J_out.template rightCols<4>() = liftRotationJacobian<Rows>(J_tangent.template rightCols<3>(), pose + 3);
}

using geometry::bearingTangentBasis;
using geometry::greatCircleRotation;

}  // namespace cvislam::factors
