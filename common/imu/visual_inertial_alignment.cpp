#include "common/imu/visual_inertial_alignment.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include <Eigen/Dense>

#include "common/geometry/unit_sphere.hpp"

namespace cvislam::imu {

using Eigen::Matrix3d;
using Eigen::MatrixXd;
using Eigen::Vector3d;
using Eigen::VectorXd;
using geometry::SO3d;

Status VisualInertialAlignmentOptions::validate() const {
  if (!(gravity_magnitude > 0.0)) return Error{ErrorCode::kInvalidArgument, "gravity_magnitude must be > 0"};
  if (gravity_refinement_iterations < 0 || gyro_bias_iterations < 1) {
    return Error{ErrorCode::kInvalidArgument,
                 "gyro_bias_iterations must be >= 1 and gravity_refinement_iterations >= 0"};
  }
  if (!(max_gravity_magnitude_error > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "max_gravity_magnitude_error must be > 0"};
  }
  if (!(known_scale >= 0.0) || !std::isfinite(known_scale)) {
    return Error{ErrorCode::kInvalidArgument, "IMU initialisation: known_scale must be >= 0 (0 = estimate it)"};
  }
  if (!(time_offset_prior_sigma_s > 0.0) || !(max_time_offset_s > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "time_offset_prior_sigma_s and max_time_offset_s must be > 0"};
  }
  return Status::Ok();
}

namespace {

// Step 1's unknowns.
struct GyroAndTime {
  Vector3d gyro_bias = Vector3d::Zero();
  double time_correction_s = 0.0;
};

// Step 1: the gyroscope bias (and the time offset's correction td) that make the preintegrated rotations agree with
// the visual ones. With d_k = td - c_k, the state rotations are R_vis_k Exp(-w_k d_k), so pair k compares
//   E = dR(b)^T Exp(w_i d_i) A Exp(-w_j d_j),   A = R_vis_i^T R_vis_j,   r = Log(E);
// dr/dtd = Jr^-1(r) ((A Exp(-w_j d_j))^T w_i - w_j), since moving Exp(w_i e) past A Exp(-w_j d_j) turns it by that
// rotation's transpose; the bias Jacobian is the usual one with this E.
GyroAndTime estimateGyroBiasAndTime(const std::vector<SO3d>& R_v_s, const std::vector<VisualKeyframe>& keyframes,
                                    const std::vector<Preintegration>& pre,
                                    const VisualInertialAlignmentOptions& options) {
  GyroAndTime x{pre.front().biasLin().gyro, keyframes.back().time_correction_s};
  const double td_prior = x.time_correction_s;
  const bool with_time = options.estimate_time_offset;
  const Eigen::Index unknowns = with_time ? 4 : 3;
  // Rotation residuals are radians; a time prior of sigma s weighs like one residual of 1e-3 rad per s.
  const double prior_weight = std::pow(1e-3 / options.time_offset_prior_sigma_s, 2);
  for (int it = 0; it < options.gyro_bias_iterations + (with_time ? 2 : 0); ++it) {
    Eigen::Matrix4d H = Eigen::Matrix4d::Zero();
    Eigen::Vector4d g = Eigen::Vector4d::Zero();
    for (std::size_t k = 0; k < pre.size(); ++k) {
      ImuBias b = pre[k].biasLin();
      b.gyro = x.gyro_bias;
      const Vector3d w_i = keyframes[k].omega_s - x.gyro_bias;
      const Vector3d w_j = keyframes[k + 1].omega_s - x.gyro_bias;
      const double d_i = with_time ? x.time_correction_s - keyframes[k].time_correction_s : 0.0;
      const double d_j = with_time ? x.time_correction_s - keyframes[k + 1].time_correction_s : 0.0;
      const SO3d A_N = R_v_s[k].inverse() * R_v_s[k + 1] * SO3d::exp(-w_j * d_j);
      const Vector3d correction = pre[k].dR_dbg() * (x.gyro_bias - pre[k].biasLin().gyro);
      const SO3d E = pre[k].correctedDeltaR(b).inverse() * SO3d::exp(w_i * d_i) * A_N;
      const Vector3d r = E.log();
      Eigen::Matrix<double, 3, 4> J = Eigen::Matrix<double, 3, 4>::Zero();
      J.leftCols<3>() =
          -SO3d::rightJacobianInverse(r) * E.inverse().matrix() * SO3d::rightJacobian(correction) * pre[k].dR_dbg();
      if (with_time) J.col(3) = SO3d::rightJacobianInverse(r) * (A_N.inverse() * w_i - w_j);
      H += J.transpose() * J;
      g += J.transpose() * r;
    }
    if (with_time) {
      H(3, 3) += prior_weight;
      g(3) += prior_weight * (x.time_correction_s - td_prior);
    }
    const Eigen::VectorXd step = H.topLeftCorner(unknowns, unknowns).ldlt().solve(g.head(unknowns));
    x.gyro_bias -= step.head<3>();
    if (with_time) {
      x.time_correction_s =
          std::clamp(x.time_correction_s - step(3), -options.max_time_offset_s, options.max_time_offset_s);
    }
  }
  return x;
}

struct LinearSystem {
  MatrixXd A;
  VectorXd b;
};

// Step 2 and 3's equations: for each keyframe pair, 3 position rows and 3 velocity rows in the unknowns
// [v_0 .. v_{N-1}, gravity columns, s]. The visual positions are where the body was shift_s[k] after its state time
// (the time offset not yet in the keyframe's time): p_k = p_vis_k - v_k shift_s[k], linear in the velocities.
// `gravity_basis` (3 x m) maps the m gravity unknowns to g_v, and `gravity_offset` is the part of g_v that is known.
LinearSystem buildSystem(const std::vector<SO3d>& R_v_s, const std::vector<Vector3d>& c_v,
                         const std::vector<Matrix3d>& R_v_c, const Vector3d& t_c_s, const std::vector<double>& shift_s,
                         const std::vector<Preintegration>& pre, const ImuBias& bias,
                         const Eigen::Matrix<double, 3, Eigen::Dynamic>& gravity_basis,
                         const Vector3d& gravity_offset) {
  const auto n = static_cast<Eigen::Index>(R_v_s.size());
  const Eigen::Index m = gravity_basis.cols();
  const Eigen::Index cols = 3 * n + m + 1;
  LinearSystem sys{MatrixXd::Zero(6 * (n - 1), cols), VectorXd::Zero(6 * (n - 1))};
  for (Eigen::Index i = 0; i + 1 < n; ++i) {
    const auto k = static_cast<std::size_t>(i);
    const double dt = pre[k].dt();
    const Matrix3d Rt = R_v_s[k].matrix().transpose();
    const Eigen::Index row = 6 * i;
    // Position: R_i^T (s (c_j - c_i) + (R_cj - R_ci) t_cs - v_i dt - g dt^2 / 2) = dp
    sys.A.block<3, 3>(row, 3 * i) = -Rt * (dt - shift_s[k]);
    sys.A.block<3, 3>(row, 3 * (i + 1)) = -Rt * shift_s[k + 1];
    sys.A.block(row, 3 * n, 3, m) = -0.5 * Rt * gravity_basis * dt * dt;
    sys.A.block<3, 1>(row, cols - 1) = Rt * (c_v[k + 1] - c_v[k]);
    sys.b.segment<3>(row) =
        pre[k].correctedDeltaP(bias) - Rt * (R_v_c[k + 1] - R_v_c[k]) * t_c_s + 0.5 * Rt * gravity_offset * dt * dt;
    // Velocity: R_i^T (v_j - v_i - g dt) = dv
    sys.A.block<3, 3>(row + 3, 3 * i) = -Rt;
    sys.A.block<3, 3>(row + 3, 3 * (i + 1)) = Rt;
    sys.A.block(row + 3, 3 * n, 3, m) = -Rt * gravity_basis * dt;
    sys.b.segment<3>(row + 3) = pre[k].correctedDeltaV(bias) + Rt * gravity_offset * dt;
  }
  return sys;
}

// The scale's standard deviation over the scale, from the least-squares covariance sigma^2 (A^T A)^-1 with sigma^2
// estimated from the residual: how well the motion so far has observed scale, as the equations themselves say.
// Infinite when there are no spare equations or the normal matrix is singular.
double relativeScaleSigma(const LinearSystem& sys, const VectorXd& x) {
  const Eigen::Index rows = sys.A.rows();
  const Eigen::Index cols = sys.A.cols();
  if (rows <= cols) return std::numeric_limits<double>::infinity();
  const double sigma2 = (sys.A * x - sys.b).squaredNorm() / static_cast<double>(rows - cols);
  const Eigen::LDLT<MatrixXd> normal(sys.A.transpose() * sys.A);
  if (normal.info() != Eigen::Success || !normal.isPositive()) return std::numeric_limits<double>::infinity();
  VectorXd unit = VectorXd::Zero(cols);
  unit(cols - 1) = 1.0;
  const double variance = sigma2 * normal.solve(unit)(cols - 1);
  const double scale = x(cols - 1);
  return variance >= 0.0 && scale > 0.0 ? std::sqrt(variance) / scale : std::numeric_limits<double>::infinity();
}

}  // namespace

Result<VisualInertialAlignment> alignVisualInertial(const std::vector<VisualKeyframe>& keyframes,
                                                    const std::vector<Preintegration>& preintegrations,
                                                    const geometry::SE3d& T_s_c,
                                                    const VisualInertialAlignmentOptions& options) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  if (keyframes.size() < 4) {
    return Error{ErrorCode::kInvalidArgument,
                 "IMU initialisation needs at least 4 keyframes, got " + std::to_string(keyframes.size())};
  }
  if (preintegrations.size() + 1 != keyframes.size()) {
    return Error{ErrorCode::kInvalidArgument, "IMU initialisation needs one preintegration between each pair of " +
                                                  std::to_string(keyframes.size()) + " keyframes, got " +
                                                  std::to_string(preintegrations.size())};
  }
  const geometry::SE3d T_c_s = T_s_c.inverse();
  std::vector<SO3d> R_v_s;
  std::vector<Matrix3d> R_v_c;
  std::vector<Vector3d> c_v;
  for (const VisualKeyframe& kf : keyframes) {
    R_v_s.push_back(kf.T_v_c.so3() * T_c_s.so3());
    R_v_c.push_back(kf.T_v_c.rotationMatrix());
    c_v.push_back(kf.T_v_c.translation());
  }
  const auto n = static_cast<Eigen::Index>(keyframes.size());

  VisualInertialAlignment out;
  const GyroAndTime step1 = estimateGyroBiasAndTime(R_v_s, keyframes, preintegrations, options);
  out.gyro_bias = step1.gyro_bias;
  out.time_correction_s = step1.time_correction_s;
  // Steps 2 and 3 on the rotations at the state times, and the positions' shift in the system.
  std::vector<double> shift_s(keyframes.size(), 0.0);
  if (options.estimate_time_offset) {
    for (std::size_t k = 0; k < R_v_s.size(); ++k) {
      shift_s[k] = out.time_correction_s - keyframes[k].time_correction_s;
      R_v_s[k] = R_v_s[k] * SO3d::exp(-(keyframes[k].omega_s - out.gyro_bias) * shift_s[k]);
    }
  }
  ImuBias bias = preintegrations.front().biasLin();
  bias.gyro = out.gyro_bias;

  // Step 2: gravity free (3 unknowns).
  const LinearSystem free = buildSystem(R_v_s, c_v, R_v_c, T_c_s.translation(), shift_s, preintegrations, bias,
                                        Matrix3d::Identity(), Vector3d::Zero());
  // With a known scale (a stereo map is metric) the scale column moves to the right-hand side.
  const bool fixed_scale = options.known_scale > 0.0;
  const auto solve = [&](const LinearSystem& sys, bool svd_check) -> Result<VectorXd> {
    const Eigen::Index cols = fixed_scale ? sys.A.cols() - 1 : sys.A.cols();
    const VectorXd b = fixed_scale ? VectorXd(sys.b - sys.A.col(sys.A.cols() - 1) * options.known_scale) : sys.b;
    VectorXd solution(sys.A.cols());
    if (svd_check) {
      const Eigen::JacobiSVD<MatrixXd> svd(sys.A.leftCols(cols), Eigen::ComputeThinU | Eigen::ComputeThinV);
      const VectorXd& sv = svd.singularValues();
      if (sv(sv.size() - 1) < options.min_scale_observability * sv(0)) {
        return Error{ErrorCode::kDegenerate,
                     "IMU initialisation: the motion does not observe scale and gravity (too little acceleration or "
                     "translation); waiting for more keyframes"};
      }
      solution.head(cols) = svd.solve(b);
    } else {
      solution.head(cols) = sys.A.leftCols(cols).colPivHouseholderQr().solve(b);
    }
    if (fixed_scale) solution(solution.size() - 1) = options.known_scale;
    return solution;
  };
  auto solved = solve(free, true);
  if (!solved) return solved.error();
  VectorXd x = *solved;
  Vector3d g_v = x.segment<3>(3 * n);
  double scale = x(x.size() - 1);
  const double g_error = std::abs(g_v.norm() - options.gravity_magnitude) / options.gravity_magnitude;
  if (!(scale > 0.0) || g_error > options.max_gravity_magnitude_error) {
    return Error{ErrorCode::kDegenerate, "IMU initialisation: implausible solution (scale " + std::to_string(scale) +
                                             ", |g| " + std::to_string(g_v.norm()) +
                                             " m/s^2); waiting for more keyframes"};
  }

  // Step 3: gravity on the sphere of radius |g|, two unknowns about the current direction.
  LinearSystem last = free;
  for (int it = 0; it < options.gravity_refinement_iterations; ++it) {
    const Vector3d g_dir = g_v.normalized();
    const Eigen::Matrix<double, 3, 2> B = geometry::bearingTangentBasis(g_dir);
    last = buildSystem(R_v_s, c_v, R_v_c, T_c_s.translation(), shift_s, preintegrations, bias, B,
                       options.gravity_magnitude * g_dir);
    x = solve(last, false).value();
    g_v = (options.gravity_magnitude * g_dir + B * x.segment<2>(3 * n)).normalized() * options.gravity_magnitude;
    scale = x(x.size() - 1);
  }
  if (!(scale > 0.0)) {
    return Error{ErrorCode::kDegenerate, "IMU initialisation: negative scale after gravity refinement"};
  }

  out.scale = scale;
  if (!fixed_scale) out.scale_sigma_relative = relativeScaleSigma(last, x);
  out.g_v = g_v;
  // The smallest rotation that turns gravity down: the yaw of v is kept.
  out.R_w_v = SO3d::exp(geometry::greatCircleRotation(g_v.normalized(), -Vector3d::UnitZ()));
  for (Eigen::Index i = 0; i < n; ++i) {
    const auto k = static_cast<std::size_t>(i);
    const Vector3d p_v_s = scale * c_v[k] + R_v_c[k] * T_c_s.translation();
    out.T_w_s.emplace_back(out.R_w_v * R_v_s[k], out.R_w_v * p_v_s);
    out.v_w.push_back(out.R_w_v * Vector3d(x.segment<3>(3 * i)));
  }
  return out;
}

}  // namespace cvislam::imu
