#include "common/geometry/triangulation.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include <Eigen/Eigenvalues>

namespace cvislam::geometry {

Status TriangulationOptions::validate() const {
  if (!(min_parallax_rad >= 0.0 && min_parallax_rad < 3.14159265358979323846)) {
    return Error{ErrorCode::kInvalidArgument, "triangulation.min_parallax_rad must be in [0, pi)"};
  }
  if (!(max_bearing_error_rad > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "triangulation.max_bearing_error_rad must be > 0"};
  }
  return Status::Ok();
}

double rayAngle(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  // atan2 of |a x b| and a . b is accurate at small and at large angles, unlike acos.
  return std::atan2(a.cross(b).norm(), a.dot(b));
}

double parallaxAngle(const Eigen::Vector3d& p_w, const Eigen::Vector3d& c0_w, const Eigen::Vector3d& c1_w) {
  return rayAngle(p_w - c0_w, p_w - c1_w);
}

Result<Eigen::Vector3d> triangulateLinear(std::span<const SE3d> T_c_w, std::span<const Eigen::Vector3d> bearings_c,
                                          const TriangulationOptions& options) {
  if (T_c_w.size() != bearings_c.size()) {
    return Error{ErrorCode::kInvalidArgument, "triangulation needs one pose per bearing"};
  }
  if (T_c_w.size() < 2) {
    return Error{ErrorCode::kDegenerate, "triangulation needs at least 2 views, got " + std::to_string(T_c_w.size())};
  }
  // Each view contributes A_i = [b_i]x [R_i | t_i] (3x4); accumulate H = sum A_i^T A_i (fixed size, no heap).
  Eigen::Matrix4d H = Eigen::Matrix4d::Zero();
  for (std::size_t i = 0; i < T_c_w.size(); ++i) {
    const double norm = bearings_c[i].norm();
    if (!(norm > 0.0)) return Error{ErrorCode::kInvalidArgument, "triangulation: zero bearing"};
    Eigen::Matrix<double, 3, 4> P;
    P.leftCols<3>() = T_c_w[i].rotationMatrix();
    P.col(3) = T_c_w[i].translation();
    const Eigen::Matrix<double, 3, 4> A = hatSO3<double>(bearings_c[i] / norm) * P;
    H.noalias() += A.transpose() * A;
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eig(H);
  const Eigen::Vector4d X = eig.eigenvectors().col(0);  // smallest eigenvalue first
  if (std::abs(X(3)) <= 1e-12 * X.head<3>().norm()) {
    return Error{ErrorCode::kDegenerate, "triangulation: the point is at infinity (no parallax)"};
  }
  const Eigen::Vector3d p_w = X.head<3>() / X(3);

  double max_parallax = 0.0;
  for (std::size_t i = 0; i < T_c_w.size(); ++i) {
    const Eigen::Vector3d p_c = T_c_w[i] * p_w;
    if (!(p_c.dot(bearings_c[i]) > 0.0)) {
      return Error{ErrorCode::kDegenerate, "triangulation: the point lies behind camera " + std::to_string(i)};
    }
    if (rayAngle(p_c, bearings_c[i]) > options.max_bearing_error_rad) {
      return Error{ErrorCode::kDegenerate, "triangulation: bearing " + std::to_string(i) + " disagrees with the point"};
    }
    const Eigen::Vector3d c_i = T_c_w[i].inverse().translation();
    for (std::size_t j = 0; j < i; ++j) {
      const Eigen::Vector3d c_j = T_c_w[j].inverse().translation();
      max_parallax = std::max(max_parallax, parallaxAngle(p_w, c_i, c_j));
    }
  }
  if (max_parallax < options.min_parallax_rad) {
    return Error{ErrorCode::kDegenerate, "triangulation: parallax too small for a reliable depth"};
  }
  return p_w;
}

Result<Eigen::Vector3d> triangulateMidpoint(const SE3d& T_w_c0, const Eigen::Vector3d& bearing_c0, const SE3d& T_w_c1,
                                            const Eigen::Vector3d& bearing_c1) {
  const Eigen::Vector3d& o0 = T_w_c0.translation();
  const Eigen::Vector3d& o1 = T_w_c1.translation();
  const Eigen::Vector3d d0 = (T_w_c0.so3() * bearing_c0).normalized();
  const Eigen::Vector3d d1 = (T_w_c1.so3() * bearing_c1).normalized();
  // Closest points o0 + s d0 and o1 + u d1: solve the 2x2 normal equations.
  const double b = d0.dot(d1);
  const double denom = 1.0 - b * b;
  if (denom < 1e-12) return Error{ErrorCode::kDegenerate, "midpoint triangulation: the rays are parallel"};
  const Eigen::Vector3d w = o0 - o1;
  const double d = d0.dot(w);
  const double e = d1.dot(w);
  const double s = (b * e - d) / denom;
  const double u = (e - b * d) / denom;
  if (s <= 0.0 || u <= 0.0)
    return Error{ErrorCode::kDegenerate, "midpoint triangulation: the point is behind a camera"};
  return Eigen::Vector3d(0.5 * ((o0 + s * d0) + (o1 + u * d1)));
}

}  // namespace cvislam::geometry
