#include "agent_rt/tracking/inertial_pose_optimizer.hpp"

#include <array>
#include <string>

#include <Eigen/Cholesky>

#include "common/factors/imu_factor.hpp"

namespace cvislam::agent {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;
using Vec9 = Eigen::Matrix<double, 9, 1>;
using Mat9 = Eigen::Matrix<double, 9, 9>;

Vec9 inertialResidualBetween(const InertialAnchor& i, const SE3d& T_w_sj, const Vector3d& v_wj, Mat9* J_i, Mat9* J_j) {
  const imu::Preintegration& pre = *i.preintegration;
  const double dt = pre.dt();
  const Eigen::Matrix3d R_i_t = i.T_w_s.rotationMatrix().transpose();
  const SO3d dR = pre.correctedDeltaR(i.bias);
  const Vector3d& g = imu::kGravityW;
  const Vector3d dv_w = v_wj - i.v_w - g * dt;
  const Vector3d dp_w = T_w_sj.translation() - i.T_w_s.translation() - i.v_w * dt - 0.5 * g * dt * dt;
  Vec9 r;
  const SO3d R_err = dR.inverse() * i.T_w_s.so3().inverse() * T_w_sj.so3();
  r.segment<3>(0) = R_err.log();
  r.segment<3>(3) = R_i_t * dv_w - pre.correctedDeltaV(i.bias);
  r.segment<3>(6) = R_i_t * dp_w - pre.correctedDeltaP(i.bias);
  const Eigen::Matrix3d Jr_inv = SO3d::rightJacobianInverse(r.segment<3>(0));
  if (J_j != nullptr) {
    J_j->setZero();
    J_j->block<3, 3>(0, 3) = Jr_inv;  // r_R wrt dphi_j
    J_j->block<3, 3>(3, 6) = R_i_t;   // r_v wrt dv_j
    J_j->block<3, 3>(6, 0) = R_i_t;   // r_p wrt dp_j
  }
  if (J_i != nullptr) {
    // Right perturbation R_i Exp(phi): (R_i Exp(phi))^T a = R_i^T a + [R_i^T a]x phi.
    J_i->setZero();
    J_i->block<3, 3>(0, 3) = -Jr_inv * (T_w_sj.rotationMatrix().transpose() * i.T_w_s.rotationMatrix());
    J_i->block<3, 3>(3, 3) = geometry::hatSO3(Vector3d(R_i_t * dv_w));
    J_i->block<3, 3>(3, 6) = -R_i_t;
    J_i->block<3, 3>(6, 0) = -R_i_t;
    J_i->block<3, 3>(6, 3) = geometry::hatSO3(Vector3d(R_i_t * dp_w));
    J_i->block<3, 3>(6, 6) = -R_i_t * dt;
  }
  return r;
}

Vec9 inertialResidual(const InertialAnchor& anchor, const SE3d& T_w_s, const Vector3d& v_w, Mat9* J) {
  return inertialResidualBetween(anchor, T_w_s, v_w, nullptr, J);
}

Result<InertialPoseResult> optimizePoseInertial(std::span<const PoseObservation> observations,
                                                const SE3d& T_w_s_initial, const Vector3d& v_w_initial,
                                                const InertialAnchor& anchor, const SE3d& T_s_c,
                                                const factors::PinholeIntrinsics& intrinsics,
                                                const PoseOptimizerOptions& options,
                                                std::span<std::uint8_t> is_outlier) {
  // The window with the anchor as its one (held) keyframe.
  std::array<MotionWindowKeyframe, 1> window{};
  window[0].T_w_s = anchor.T_w_s;
  window[0].v_w = anchor.v_w;
  window[0].bias = anchor.bias;
  window[0].to_next = anchor.preintegration;
  auto windowed =
      optimizeMotionWindow(window, observations, T_w_s_initial, v_w_initial, T_s_c, intrinsics, options, is_outlier);
  if (!windowed) return windowed.error();
  InertialPoseResult result;
  result.T_w_s = windowed->T_w_s;
  result.v_w = windowed->v_w;
  result.inliers = windowed->inliers;
  result.iterations = windowed->iterations;
  result.imu_chi2 = windowed->imu_chi2;
  return result;
}

namespace {

constexpr int kMaxWindowDim = 9 * static_cast<int>(kMaxMotionWindowKeyframes + 1);
using MatW = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxWindowDim, kMaxWindowDim>;
using VecW = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxWindowDim, 1>;

struct Node {
  SE3d T_w_s;
  Vector3d v_w;
};

}  // namespace

Result<MotionWindowResult> optimizeMotionWindow(std::span<MotionWindowKeyframe> keyframes,
                                                std::span<const PoseObservation> observations,
                                                const SE3d& T_w_s_initial, const Vector3d& v_w_initial,
                                                const SE3d& T_s_c, const factors::PinholeIntrinsics& intrinsics,
                                                const PoseOptimizerOptions& options,
                                                std::span<std::uint8_t> is_outlier) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  if (keyframes.empty() || keyframes.size() > kMaxMotionWindowKeyframes) {
    return Error{ErrorCode::kInvalidArgument, "optimizeMotionWindow: " + std::to_string(keyframes.size()) +
                                                  " keyframes; give 1 to " + std::to_string(kMaxMotionWindowKeyframes)};
  }
  if (is_outlier.size() != observations.size()) {
    return Error{ErrorCode::kInvalidArgument, "optimizeMotionWindow: is_outlier must be as long as observations"};
  }
  for (const MotionWindowKeyframe& kf : keyframes) {
    if (kf.to_next == nullptr || kf.to_next->dt() <= 0.0) {
      return Error{ErrorCode::kInvalidArgument, "optimizeMotionWindow: a keyframe has no IMU to the next state"};
    }
    if (kf.is_outlier.size() != kf.observations.size()) {
      return Error{ErrorCode::kInvalidArgument,
                   "optimizeMotionWindow: a keyframe's is_outlier is not as long as "
                   "its observations"};
    }
  }
  const std::size_t k_count = keyframes.size();
  const auto frame = k_count;                     // the frame is the last node
  const int dim = 9 * static_cast<int>(k_count);  // node 0, the oldest keyframe, is held
  const auto offset = [](std::size_t node) { return 9 * (static_cast<int>(node) - 1); };

  std::array<Node, kMaxMotionWindowKeyframes + 1> nodes;
  std::array<Mat9, kMaxMotionWindowKeyframes> S;  // square-root information of each IMU link
  for (std::size_t k = 0; k < k_count; ++k) {
    nodes[k] = {keyframes[k].T_w_s, keyframes[k].v_w};
    S[k] = factors::sqrtInformationFromCovariance<9>(keyframes[k].to_next->covariance());
    for (std::uint8_t& flag : keyframes[k].is_outlier) flag = 0;
  }
  nodes[frame] = {T_w_s_initial, v_w_initial};
  for (std::uint8_t& flag : is_outlier) flag = 0;

  const auto anchorOf = [&](std::size_t k) {
    return InertialAnchor{nodes[k].T_w_s, nodes[k].v_w, keyframes[k].bias, keyframes[k].to_next};
  };
  const auto imuChi2 = [&]() {
    double chi2 = 0.0;
    for (std::size_t k = 0; k < k_count; ++k) {
      chi2 += (S[k] * inertialResidualBetween(anchorOf(k), nodes[k + 1].T_w_s, nodes[k + 1].v_w, nullptr, nullptr))
                  .squaredNorm();
    }
    return chi2;
  };

  MotionWindowResult result;
  MatW H(dim, dim);
  VecW g(dim);
  for (int round = 0; round < options.rounds; ++round) {
    for (int it = 0; it < options.iterations_per_round; ++it) {
      H.setZero();
      g.setZero();
      int used_frame = 0;
      for (std::size_t k = 1; k <= k_count; ++k) {
        Eigen::Matrix<double, 6, 6> H_pose = Eigen::Matrix<double, 6, 6>::Zero();
        Eigen::Matrix<double, 6, 1> g_pose = Eigen::Matrix<double, 6, 1>::Zero();
        const bool is_frame = k == frame;
        const int used = accumulateReprojection(is_frame ? observations : keyframes[k].observations, nodes[k].T_w_s,
                                                T_s_c, intrinsics, options.huber_delta,
                                                is_frame ? is_outlier : keyframes[k].is_outlier, H_pose, g_pose);
        if (is_frame) used_frame = used;
        const int o = offset(k);
        H.block<6, 6>(o, o) += H_pose;
        g.segment<6>(o) += g_pose;
      }
      if (used_frame < options.min_inliers) break;
      for (std::size_t k = 0; k < k_count; ++k) {
        Mat9 J_i;
        Mat9 J_j;
        const Vec9 r = S[k] * inertialResidualBetween(anchorOf(k), nodes[k + 1].T_w_s, nodes[k + 1].v_w, &J_i, &J_j);
        J_i = S[k] * J_i;
        J_j = S[k] * J_j;
        const int b = offset(k + 1);
        H.block<9, 9>(b, b).noalias() += J_j.transpose() * J_j;
        g.segment<9>(b).noalias() += J_j.transpose() * r;
        if (k == 0) continue;  // the held keyframe has no unknowns
        const int a = offset(k);
        H.block<9, 9>(a, a).noalias() += J_i.transpose() * J_i;
        H.block<9, 9>(a, b).noalias() += J_i.transpose() * J_j;
        H.block<9, 9>(b, a).noalias() += J_j.transpose() * J_i;
        g.segment<9>(a).noalias() += J_i.transpose() * r;
      }
      const VecW dx = -H.ldlt().solve(g);
      if (!dx.allFinite()) break;
      for (std::size_t k = 1; k <= k_count; ++k) {
        const int o = offset(k);
        Node& n = nodes[k];
        n.T_w_s = SE3d(n.T_w_s.so3() * SO3d::exp(dx.segment<3>(o + 3)), n.T_w_s.translation() + dx.segment<3>(o));
        n.v_w += dx.segment<3>(o + 6);
      }
      ++result.iterations;
      if (dx.norm() < options.min_step) break;
    }
    result.keyframe_inliers = 0;
    for (std::size_t k = 1; k < k_count; ++k) {
      result.keyframe_inliers += classifyObservations(keyframes[k].observations, nodes[k].T_w_s, T_s_c, intrinsics,
                                                      options.chi2_threshold, keyframes[k].is_outlier, nullptr);
    }
    result.inliers = classifyObservations(observations, nodes[frame].T_w_s, T_s_c, intrinsics, options.chi2_threshold,
                                          is_outlier, nullptr);
  }
  result.T_w_s = nodes[frame].T_w_s;
  result.v_w = nodes[frame].v_w;
  result.imu_chi2 = imuChi2();
  if (result.inliers < options.min_inliers) {
    // Met by tracking on weak frames: a message short enough for std::string's inline buffer, no allocation.
    return Error{ErrorCode::kDegenerate, "few inliers"};
  }
  return result;
}

}  // namespace cvislam::agent
