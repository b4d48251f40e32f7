#include "agent_rt/tracking/pose_optimizer.hpp"

#include <array>
#include <cmath>
#include <string>

#include <Eigen/Cholesky>

namespace cvislam::agent {

using Eigen::Matrix3d;
using Eigen::Vector2d;
using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;
using Mat6 = Eigen::Matrix<double, 6, 6>;
using Vec6 = Eigen::Matrix<double, 6, 1>;

Status PoseOptimizerOptions::validate() const {
  const auto bad = [](const std::string& what) {
    return Error{ErrorCode::kInvalidArgument, "pose optimizer options: " + what};
  };
  if (rounds < 1 || iterations_per_round < 1) return bad("rounds and iterations_per_round must be >= 1");
  if (!(chi2_threshold > 0.0) || !(huber_delta > 0.0)) return bad("chi2_threshold and huber_delta must be > 0");
  if (min_inliers < 3) return bad("min_inliers must be >= 3 (a pose has 6 degrees of freedom)");
  if (!(max_leverage >= 0.5 && max_leverage <= 1.0)) return bad("max_leverage must be in [0.5, 1]");
  return Status::Ok();
}

bool poseReprojectionResidual(const PoseObservation& o, const SE3d& T_w_s, const SE3d& T_s_c,
                              const factors::PinholeIntrinsics& K, Vector2d& residual, Eigen::Matrix<double, 2, 6>* J) {
  const Matrix3d R_s_w = T_w_s.rotationMatrix().transpose();
  const Matrix3d R_c_s = T_s_c.rotationMatrix().transpose();
  const Vector3d p_s = R_s_w * (o.p_w - T_w_s.translation());  // the point in the IMU frame
  const Vector3d p_c = R_c_s * (p_s - T_s_c.translation());
  if (!(p_c.z() > 1e-3)) return false;
  const double inv_z = 1.0 / p_c.z();
  residual = Vector2d(K.fx * p_c.x() * inv_z + K.cx, K.fy * p_c.y() * inv_z + K.cy) - o.keypoint_px;
  if (J != nullptr) {
    Eigen::Matrix<double, 2, 3> d_px_d_pc;
    d_px_d_pc << K.fx * inv_z, 0.0, -K.fx * p_c.x() * inv_z * inv_z,  //
        0.0, K.fy * inv_z, -K.fy * p_c.y() * inv_z * inv_z;
    const Eigen::Matrix<double, 2, 3> d_px_d_ps = d_px_d_pc * R_c_s;
    J->leftCols<3>() = -d_px_d_ps * R_s_w;                  // p_w_s moves the point the other way
    J->rightCols<3>() = d_px_d_ps * geometry::hatSO3(p_s);  // R_w_s Exp(dphi): p_s -> p_s + [p_s]x dphi
  }
  return true;
}

namespace {

// An observation's residual and Jacobian, whitened by its sigma, and its Huber weight.
bool whitened(const PoseObservation& o, const SE3d& T_w_s, const SE3d& T_s_c, const factors::PinholeIntrinsics& K,
              double huber_delta, Vector2d& r, Eigen::Matrix<double, 2, 6>& J, double& w) {
  if (!poseReprojectionResidual(o, T_w_s, T_s_c, K, r, &J)) return false;
  const double inv_sigma = 1.0 / o.sigma_px;
  r *= inv_sigma;
  J *= inv_sigma;
  const double e = r.norm();
  w = e <= huber_delta ? 1.0 : huber_delta / e;
  return true;
}

}  // namespace

int accumulateReprojection(std::span<const PoseObservation> observations, const SE3d& T_w_s, const SE3d& T_s_c,
                           const factors::PinholeIntrinsics& intrinsics, double huber_delta,
                           std::span<const std::uint8_t> is_outlier, Mat6& H, Vec6& g) {
  int used = 0;
  for (std::size_t i = 0; i < observations.size(); ++i) {
    if (is_outlier[i] != 0) continue;
    Vector2d r;
    Eigen::Matrix<double, 2, 6> J;
    double w = 1.0;
    if (!whitened(observations[i], T_w_s, T_s_c, intrinsics, huber_delta, r, J, w)) continue;
    H.noalias() += w * J.transpose() * J;
    g.noalias() += w * J.transpose() * r;
    ++used;
  }
  return used;
}

int classifyObservations(std::span<const PoseObservation> observations, const SE3d& T_w_s, const SE3d& T_s_c,
                         const factors::PinholeIntrinsics& intrinsics, double chi2_threshold,
                         std::span<std::uint8_t> is_outlier, double* chi2) {
  int inliers = 0;
  for (std::size_t i = 0; i < observations.size(); ++i) {
    Vector2d r;
    const bool in_front = poseReprojectionResidual(observations[i], T_w_s, T_s_c, intrinsics, r, nullptr);
    const double e2 = in_front ? r.squaredNorm() / (observations[i].sigma_px * observations[i].sigma_px) : 1e30;
    is_outlier[i] = e2 > chi2_threshold ? 1 : 0;
    if (is_outlier[i] == 0) {
      ++inliers;
      if (chi2 != nullptr) *chi2 += e2;
    }
  }
  return inliers;
}

namespace {

constexpr std::size_t kMaxHeldOut = 12;  // leverages add up to 6, each held-out one has more than 0.5
using HeldOut = std::array<std::size_t, kMaxHeldOut>;

// The inliers whose leverage, trace(w J H^-1 J^T), exceeds max_leverage: marked outliers for the next round and
// listed in `held`. None when that would leave fewer than min_inliers.
int holdOutHighLeverage(std::span<const PoseObservation> observations, const SE3d& T_w_s, const SE3d& T_s_c,
                        const factors::PinholeIntrinsics& K, const PoseOptimizerOptions& options,
                        std::span<std::uint8_t> is_outlier, HeldOut& held) {
  if (options.max_leverage >= 1.0) return 0;
  Mat6 H = Mat6::Zero();
  Vec6 g = Vec6::Zero();
  const int used = accumulateReprojection(observations, T_w_s, T_s_c, K, options.huber_delta, is_outlier, H, g);
  const Eigen::LDLT<Mat6> ldlt(H);
  if (ldlt.info() != Eigen::Success) return 0;
  int count = 0;
  for (std::size_t i = 0; i < observations.size() && count < static_cast<int>(kMaxHeldOut); ++i) {
    if (is_outlier[i] != 0) continue;
    Vector2d r;
    Eigen::Matrix<double, 2, 6> J;
    double w = 1.0;
    if (!whitened(observations[i], T_w_s, T_s_c, K, options.huber_delta, r, J, w)) continue;
    const Eigen::Matrix<double, 6, 2> X = ldlt.solve(J.transpose());
    if (w * (J * X).trace() > options.max_leverage) held[static_cast<std::size_t>(count++)] = i;
  }
  if (used - count < options.min_inliers) return 0;
  for (int k = 0; k < count; ++k) is_outlier[held[static_cast<std::size_t>(k)]] = 1;
  return count;
}

// Judges the held-out observations by the pose found without them (is_outlier still holds them out): each one's
// residual against the chi-square bound, with the pose's uncertainty (H^-1 of the others) added to its covariance.
// fits[k] and e2[k] (its plain chi-square) for held[k].
void judgeHeldOut(std::span<const PoseObservation> observations, const SE3d& T_w_s, const SE3d& T_s_c,
                  const factors::PinholeIntrinsics& K, const PoseOptimizerOptions& options,
                  std::span<const std::uint8_t> is_outlier, const HeldOut& held, int count,
                  std::array<bool, kMaxHeldOut>& fits, std::array<double, kMaxHeldOut>& e2) {
  Mat6 H = Mat6::Zero();
  Vec6 g = Vec6::Zero();
  (void)accumulateReprojection(observations, T_w_s, T_s_c, K, options.huber_delta, is_outlier, H, g);
  const Eigen::LDLT<Mat6> ldlt(H);
  for (std::size_t k = 0; k < static_cast<std::size_t>(count); ++k) {
    fits[k] = false;
    Vector2d r;
    Eigen::Matrix<double, 2, 6> J;
    double w = 1.0;
    if (ldlt.info() != Eigen::Success ||
        !whitened(observations[held[k]], T_w_s, T_s_c, K, options.huber_delta, r, J, w)) {
      continue;
    }
    const Eigen::Matrix2d S = Eigen::Matrix2d::Identity() + J * ldlt.solve(J.transpose());
    e2[k] = r.squaredNorm();
    fits[k] = r.dot(S.ldlt().solve(r)) <= options.chi2_threshold;
  }
}

}  // namespace

Result<PoseOptimizerResult> optimizePose(std::span<const PoseObservation> observations, const SE3d& T_w_s_initial,
                                         const SE3d& T_s_c, const factors::PinholeIntrinsics& intrinsics,
                                         const PoseOptimizerOptions& options, std::span<std::uint8_t> is_outlier) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  if (is_outlier.size() != observations.size()) {
    return Error{ErrorCode::kInvalidArgument, "optimizePose: is_outlier must be as long as observations"};
  }
  for (std::uint8_t& flag : is_outlier) flag = 0;

  PoseOptimizerResult result;
  result.T_w_s = T_w_s_initial;
  HeldOut held{};
  for (int round = 0; round < options.rounds; ++round) {
    for (int it = 0; it < options.iterations_per_round; ++it) {
      Mat6 H = Mat6::Zero();
      Vec6 g = Vec6::Zero();
      const int used =
          accumulateReprojection(observations, result.T_w_s, T_s_c, intrinsics, options.huber_delta, is_outlier, H, g);
      if (used < options.min_inliers) break;
      const Vec6 dx = -H.ldlt().solve(g);
      if (!dx.allFinite()) break;
      result.T_w_s = SE3d(result.T_w_s.so3() * SO3d::exp(dx.tail<3>()), result.T_w_s.translation() + dx.head<3>());
      ++result.iterations;
      if (dx.norm() < options.min_step) break;
    }
    result.final_chi2 = 0.0;
    result.inliers = classifyObservations(observations, result.T_w_s, T_s_c, intrinsics, options.chi2_threshold,
                                          is_outlier, &result.final_chi2);
    if (round == 1 && result.held_out > 0) {
      // classifyObservations() judged the held-out ones by their residual alone; their own judgement wins.
      const auto count = static_cast<std::size_t>(result.held_out);
      std::array<bool, kMaxHeldOut> was_inlier{};
      for (std::size_t k = 0; k < count; ++k) {
        was_inlier[k] = is_outlier[held[k]] == 0;
        is_outlier[held[k]] = 1;
      }
      std::array<bool, kMaxHeldOut> fits{};
      std::array<double, kMaxHeldOut> e2{};
      judgeHeldOut(observations, result.T_w_s, T_s_c, intrinsics, options, is_outlier, held, result.held_out, fits, e2);
      for (std::size_t k = 0; k < count; ++k) {
        if (was_inlier[k] != fits[k]) {
          const int sign = fits[k] ? 1 : -1;
          result.inliers += sign;
          result.final_chi2 += sign * e2[k];
        }
        is_outlier[held[k]] = fits[k] ? 0 : 1;
      }
    }
    if (round == 0 && options.rounds > 1) {
      result.held_out = holdOutHighLeverage(observations, result.T_w_s, T_s_c, intrinsics, options, is_outlier, held);
      result.inliers -= result.held_out;
    }
  }
  if (result.inliers < options.min_inliers) {
    // Tracking meets this every frame it is lost, so the message fits std::string's inline buffer: no allocation
    // (the inlier count is in the caller's hands anyway).
    return Error{ErrorCode::kDegenerate, "few inliers"};
  }
  return result;
}

}  // namespace cvislam::agent
