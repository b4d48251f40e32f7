#include "common/factors/time_offset_point_factor.hpp"

#include <array>
#include <utility>

namespace cvislam::factors {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using RowMajor2x7 = Eigen::Matrix<double, 2, kPoseSize, Eigen::RowMajor>;
using Tangent2x6 = Eigen::Matrix<double, 2, 6>;

namespace {

// The pose block moved by `motion` over d seconds: p + v d, q Exp(w d). Returns the rotation of the shift,
// Exp(w d), for the Jacobian.
Matrix3d shiftPose(const double* pose, const KeyframeMotion& motion, double d, PoseBlock& shifted) {
  const geometry::SO3d step = geometry::SO3d::exp(motion.omega_s * d);
  const Eigen::Quaterniond q =
      (Eigen::Quaterniond(pose[6], pose[3], pose[4], pose[5]).normalized() * step.quaternion()).normalized();
  shifted.head<3>() = Eigen::Map<const Vector3d>(pose) + motion.v_w * d;
  shifted.tail<4>() << q.x(), q.y(), q.z(), q.w();
  return step.matrix();
}

// The inner factor's ambient Jacobian (2 x 7) back to its tangent [dp, dphi] at the pose it was taken at.
Tangent2x6 tangentOf(const RowMajor2x7& J_ambient, const double* pose) {
  Tangent2x6 J;
  J.leftCols<3>() = J_ambient.leftCols<3>();
  J.rightCols<3>() = J_ambient.rightCols<4>() * quaternionPlusJacobian(pose + 3);
  return J;
}

}  // namespace

TimeOffsetPointFactor::TimeOffsetPointFactor(std::unique_ptr<const InverseDepthPointFactor> observation,
                                             const KeyframeMotion& observing, const KeyframeMotion& reference)
    : observation_(std::move(observation)), observing_(observing), reference_(reference) {}

bool TimeOffsetPointFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const double td = parameters[4][0];
  PoseBlock pose_i;
  PoseBlock pose_r;
  const Matrix3d step_i = shiftPose(parameters[0], observing_, td - observing_.time_correction_s, pose_i);
  const Matrix3d step_r = shiftPose(parameters[1], reference_, td - reference_.time_correction_s, pose_r);
  const std::array<const double*, 4> inner = {pose_i.data(), pose_r.data(), parameters[2], parameters[3]};
  if (jacobians == nullptr) return observation_->Evaluate(inner.data(), residuals, nullptr);

  // The pose Jacobians are needed for td even when Ceres does not ask for them (a held keyframe).
  RowMajor2x7 J_i;
  RowMajor2x7 J_r;
  std::array<double*, 4> inner_jacobians = {J_i.data(), J_r.data(), jacobians[2], jacobians[3]};
  if (!observation_->Evaluate(inner.data(), residuals, inner_jacobians.data())) return false;
  const Tangent2x6 T_i = tangentOf(J_i, pose_i.data());
  const Tangent2x6 T_r = tangentOf(J_r, pose_r.data());
  const auto toPose = [](const Tangent2x6& J_shifted, const Matrix3d& step, const double* pose, double* out) {
    Tangent2x6 J = J_shifted;
    J.rightCols<3>() = J_shifted.rightCols<3>() * step.transpose();
    writePoseJacobian<2>(J, pose, out);
  };
  if (jacobians[0] != nullptr) toPose(T_i, step_i, parameters[0], jacobians[0]);
  if (jacobians[1] != nullptr) toPose(T_r, step_r, parameters[1], jacobians[1]);
  if (jacobians[4] != nullptr) {
    Eigen::Matrix<double, 6, 1> rate_i;
    Eigen::Matrix<double, 6, 1> rate_r;
    rate_i << observing_.v_w, observing_.omega_s;
    rate_r << reference_.v_w, reference_.omega_s;
    Eigen::Map<Eigen::Vector2d> J_td(jacobians[4]);
    J_td = T_i * rate_i + T_r * rate_r;
  }
  return true;
}

}  // namespace cvislam::factors
