#include "common/geometry/alignment.hpp"

#include <cmath>
#include <string>

#include <Eigen/SVD>

namespace cvislam::geometry {
namespace {

struct Moments {
  Eigen::Vector3d mean_src = Eigen::Vector3d::Zero();
  Eigen::Vector3d mean_dst = Eigen::Vector3d::Zero();
  Eigen::Matrix3d cov_dst_src = Eigen::Matrix3d::Zero();  // 1/n sum (dst - mean)(src - mean)^T
  double var_src = 0.0;                                   // 1/n sum |src - mean|^2
};

Status checkSizes(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst, std::size_t min_points) {
  if (src.size() != dst.size()) {
    return Error{ErrorCode::kInvalidArgument, "alignment needs corresponding point sets, got " +
                                                  std::to_string(src.size()) + " and " + std::to_string(dst.size())};
  }
  if (src.size() < min_points) {
    return Error{ErrorCode::kDegenerate, "alignment needs at least " + std::to_string(min_points) + " points, got " +
                                             std::to_string(src.size())};
  }
  return Status::Ok();
}

Moments computeMoments(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst) {
  Moments m;
  const double n = static_cast<double>(src.size());
  for (std::size_t i = 0; i < src.size(); ++i) {
    m.mean_src += src[i];
    m.mean_dst += dst[i];
  }
  m.mean_src /= n;
  m.mean_dst /= n;
  for (std::size_t i = 0; i < src.size(); ++i) {
    const Eigen::Vector3d a = src[i] - m.mean_src;
    const Eigen::Vector3d b = dst[i] - m.mean_dst;
    m.cov_dst_src += b * a.transpose();
    m.var_src += a.squaredNorm();
  }
  m.cov_dst_src /= n;
  m.var_src /= n;
  return m;
}

// Rotation and scale factor trace(D S) of Umeyama's solution.
Result<std::pair<Eigen::Matrix3d, double>> umeyamaRotation(const Moments& m) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(m.cov_dst_src, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d& d = svd.singularValues();
  // With rank < 2 (all points on a line, or all equal) the rotation about that line is not determined.
  if (!(d(1) > 1e-12 * std::max(d(0), 1e-300))) {
    return Error{ErrorCode::kDegenerate, "alignment is degenerate: the points are collinear or coincident"};
  }
  Eigen::Vector3d s = Eigen::Vector3d::Ones();
  if (svd.matrixU().determinant() * svd.matrixV().determinant() < 0.0) s(2) = -1.0;
  const Eigen::Matrix3d R = svd.matrixU() * s.asDiagonal() * svd.matrixV().transpose();
  return std::make_pair(R, d.dot(s));
}

}  // namespace

Result<SE3d> alignSE3(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst) {
  if (Status st = checkSizes(src, dst, 3); !st) return st.error();
  const Moments m = computeMoments(src, dst);
  auto rotation = umeyamaRotation(m);
  if (!rotation) return rotation.error();
  const SO3d R(rotation->first);
  return SE3d(R, m.mean_dst - R * m.mean_src);
}

Result<Sim3d> alignSim3(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst) {
  if (Status st = checkSizes(src, dst, 3); !st) return st.error();
  const Moments m = computeMoments(src, dst);
  auto rotation = umeyamaRotation(m);
  if (!rotation) return rotation.error();
  if (!(m.var_src > 0.0)) return Error{ErrorCode::kDegenerate, "alignment is degenerate: source points coincide"};
  const double scale = rotation->second / m.var_src;
  const SO3d R(rotation->first);
  return Sim3d(scale, R, m.mean_dst - scale * (R * m.mean_src));
}

SO3d rotationAboutZ(double yaw) {
  return SO3d::exp(Eigen::Vector3d(0.0, 0.0, yaw));
}

Result<SE3d> alignPositionYaw(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst) {
  if (Status st = checkSizes(src, dst, 2); !st) return st.error();
  const Moments m = computeMoments(src, dst);
  // Maximise sum b_i . Rz(yaw) a_i over the centred points: the xy-part of the cross-covariance gives
  // sum (a_x b_x + a_y b_y) cos(yaw) + (a_x b_y - a_y b_x) sin(yaw).
  const Eigen::Matrix3d& C = m.cov_dst_src;  // C(i, j) = mean of b_i a_j
  const double cos_term = C(0, 0) + C(1, 1);
  const double sin_term = C(1, 0) - C(0, 1);
  if (std::hypot(cos_term, sin_term) <= 1e-15 * std::max(1.0, C.cwiseAbs().maxCoeff())) {
    return Error{ErrorCode::kDegenerate, "position+yaw alignment is degenerate: no horizontal spread"};
  }
  const SO3d R = rotationAboutZ(std::atan2(sin_term, cos_term));
  return SE3d(R, m.mean_dst - R * m.mean_src);
}

}  // namespace cvislam::geometry
