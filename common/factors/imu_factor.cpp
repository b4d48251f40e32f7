#include "common/factors/imu_factor.hpp"

#include <cmath>

#include <Eigen/Cholesky>

namespace cvislam::factors {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using geometry::SO3d;
constexpr int kRowMajor = Eigen::RowMajor;

template <int N>
Eigen::Matrix<double, N, N> sqrtInformationFromCovariance(const Eigen::Matrix<double, N, N>& covariance) {
  using Mat = Eigen::Matrix<double, N, N>;
  const Mat symmetric = 0.5 * (covariance + covariance.transpose());
  Eigen::LLT<Mat> llt(symmetric);
  if (llt.info() != Eigen::Success) llt.compute(symmetric + 1e-12 * Mat::Identity());
  // Sigma = L L^T  =>  Sigma^-1 = L^-T L^-1, so S = L^-1 (lower triangular) whitens: S^T S = Sigma^-1.
  // Ceres only needs S^T S; a triangular S keeps the whitening cheap.
  const Mat L = llt.matrixL();
  return L.template triangularView<Eigen::Lower>().solve(Mat::Identity());
}

template Eigen::Matrix<double, 9, 9> sqrtInformationFromCovariance<9>(const Eigen::Matrix<double, 9, 9>&);
template Eigen::Matrix<double, 6, 6> sqrtInformationFromCovariance<6>(const Eigen::Matrix<double, 6, 6>&);
template Eigen::Matrix<double, 3, 3> sqrtInformationFromCovariance<3>(const Eigen::Matrix<double, 3, 3>&);

ImuFactor::ImuFactor(const imu::Preintegration& preintegration, const Vector3d& g_w)
    : preintegration_(preintegration),
      g_w_(g_w),
      sqrt_information_(sqrtInformationFromCovariance<9>(preintegration.covariance())) {}

bool ImuFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const double* pose_i = parameters[0];
  const double* pose_j = parameters[3];
  const Eigen::Map<const Vector3d> p_i(pose_i);
  const Eigen::Map<const Vector3d> p_j(pose_j);
  const SO3d R_w_i(Eigen::Quaterniond(pose_i[6], pose_i[3], pose_i[4], pose_i[5]));
  const SO3d R_w_j(Eigen::Quaterniond(pose_j[6], pose_j[3], pose_j[4], pose_j[5]));
  const Eigen::Map<const Vector3d> v_i(parameters[1]);
  const Eigen::Map<const Vector3d> v_j(parameters[4]);
  const Eigen::Map<const Vector3d> bg_i(parameters[2]);
  const Eigen::Map<const Vector3d> ba_i(parameters[2] + 3);

  const imu::Preintegration& pre = preintegration_;
  const double dt = pre.dt();
  const Vector3d dbg = bg_i - pre.biasLin().gyro;
  const Vector3d dba = ba_i - pre.biasLin().accel;

  const Vector3d dR_correction = pre.dR_dbg() * dbg;
  const SO3d dR_corrected = pre.deltaR() * SO3d::exp(dR_correction);
  const Matrix3d Rt_i = R_w_i.matrix().transpose();
  const Vector3d v_term = Rt_i * (v_j - v_i - g_w_ * dt);
  const Vector3d p_term = Rt_i * (p_j - p_i - v_i * dt - 0.5 * g_w_ * dt * dt);

  const SO3d E = dR_corrected.inverse() * R_w_i.inverse() * R_w_j;
  const Vector3d r_R = E.log();
  Eigen::Matrix<double, 9, 1> r;
  r.segment<3>(0) = r_R;
  r.segment<3>(3) = v_term - (pre.deltaV() + pre.dv_dbg() * dbg + pre.dv_dba() * dba);
  r.segment<3>(6) = p_term - (pre.deltaP() + pre.dp_dbg() * dbg + pre.dp_dba() * dba);
  Eigen::Map<Eigen::Matrix<double, 9, 1>>{residuals} = sqrt_information_ * r;

  if (jacobians == nullptr) return true;

  const Matrix3d Jr_inv = SO3d::rightJacobianInverse(r_R);
  const Matrix3d R_j_i = R_w_j.matrix().transpose() * R_w_i.matrix();

  if (jacobians[0] != nullptr) {  // pose_i: [dp, dphi] -> ambient
    Eigen::Matrix<double, 9, 6> J = Eigen::Matrix<double, 9, 6>::Zero();
    J.block<3, 3>(0, 3) = -Jr_inv * R_j_i;
    J.block<3, 3>(3, 3) = geometry::hatSO3(v_term);
    J.block<3, 3>(6, 0) = -Rt_i;
    J.block<3, 3>(6, 3) = geometry::hatSO3(p_term);
    J = sqrt_information_ * J;
    writePoseJacobian<9>(J, pose_i, jacobians[0]);
  }
  if (jacobians[1] != nullptr) {  // v_i
    Eigen::Matrix<double, 9, 3> J = Eigen::Matrix<double, 9, 3>::Zero();
    J.block<3, 3>(3, 0) = -Rt_i;
    J.block<3, 3>(6, 0) = -Rt_i * dt;
    Eigen::Map<Eigen::Matrix<double, 9, 3, kRowMajor>>{jacobians[1]} = sqrt_information_ * J;
  }
  if (jacobians[2] != nullptr) {  // bias_i = [b_g, b_a]
    Eigen::Matrix<double, 9, 6> J = Eigen::Matrix<double, 9, 6>::Zero();
    J.block<3, 3>(0, 0) = -Jr_inv * E.inverse().matrix() * SO3d::rightJacobian(dR_correction) * pre.dR_dbg();
    J.block<3, 3>(3, 0) = -pre.dv_dbg();
    J.block<3, 3>(3, 3) = -pre.dv_dba();
    J.block<3, 3>(6, 0) = -pre.dp_dbg();
    J.block<3, 3>(6, 3) = -pre.dp_dba();
    Eigen::Map<Eigen::Matrix<double, 9, 6, kRowMajor>>{jacobians[2]} = sqrt_information_ * J;
  }
  if (jacobians[3] != nullptr) {  // pose_j
    Eigen::Matrix<double, 9, 6> J = Eigen::Matrix<double, 9, 6>::Zero();
    J.block<3, 3>(0, 3) = Jr_inv;
    J.block<3, 3>(6, 0) = Rt_i;
    J = sqrt_information_ * J;
    writePoseJacobian<9>(J, pose_j, jacobians[3]);
  }
  if (jacobians[4] != nullptr) {  // v_j
    Eigen::Matrix<double, 9, 3> J = Eigen::Matrix<double, 9, 3>::Zero();
    J.block<3, 3>(3, 0) = Rt_i;
    Eigen::Map<Eigen::Matrix<double, 9, 3, kRowMajor>>{jacobians[4]} = sqrt_information_ * J;
  }
  return true;
}

BiasRandomWalkFactor::BiasRandomWalkFactor(const imu::ImuNoise& noise, double dt_s) {
  const double sqrt_dt = std::sqrt(std::max(dt_s, 1e-6));
  sqrt_information_diagonal_.head<3>().setConstant(1.0 / (noise.gyro_random_walk * sqrt_dt));
  sqrt_information_diagonal_.tail<3>().setConstant(1.0 / (noise.accel_random_walk * sqrt_dt));
}

bool BiasRandomWalkFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const Eigen::Map<const Eigen::Matrix<double, 6, 1>> b_i(parameters[0]);
  const Eigen::Map<const Eigen::Matrix<double, 6, 1>> b_j(parameters[1]);
  Eigen::Map<Eigen::Matrix<double, 6, 1>>{residuals} = sqrt_information_diagonal_.cwiseProduct(b_j - b_i);
  if (jacobians == nullptr) return true;
  using Mat6 = Eigen::Matrix<double, 6, 6, kRowMajor>;
  if (jacobians[0] != nullptr) Eigen::Map<Mat6>{jacobians[0]} = -Mat6(sqrt_information_diagonal_.asDiagonal());
  if (jacobians[1] != nullptr) Eigen::Map<Mat6>{jacobians[1]} = Mat6(sqrt_information_diagonal_.asDiagonal());
  return true;
}

}  // namespace cvislam::factors
