#include "test/sim/trajectory.hpp"

#include <cmath>
#include <numbers>
#include <string>

#include <Eigen/Geometry>

namespace cvislam::sim {

Eigen::Matrix3d rotationFlightFromBody() {
  Eigen::Matrix3d R_f_b;
  R_f_b << 0.0, 0.0, 1.0,  //
      0.0, -1.0, 0.0,      //
      1.0, 0.0, 0.0;
  return R_f_b;
}

Eigen::Matrix3d rotationFromYawPitchRoll(double yaw, double pitch, double roll) {
  return (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

KinematicState BodyTrajectory::state(double t_s) const {
  const Vector6d q = spline_.evaluate(t_s, 0);
  const Vector6d dq = spline_.evaluate(t_s, 1);
  const Vector6d ddq = spline_.evaluate(t_s, 2);
  const double yaw = q(3), pitch = q(4), roll = q(5);
  const double d_yaw = dq(3), d_pitch = dq(4), d_roll = dq(5);
  // Body rates of Z-Y-X Euler angles, in the rotating (flight) frame.
  const double sp = std::sin(pitch), cp = std::cos(pitch), sr = std::sin(roll), cr = std::cos(roll);
  const Eigen::Vector3d omega_f(d_roll - d_yaw * sp, d_pitch * cr + d_yaw * cp * sr, d_yaw * cp * cr - d_pitch * sr);
  const Eigen::Matrix3d R_f_b = rotationFlightFromBody();
  KinematicState s;
  s.t_s = t_s;
  const Eigen::Matrix3d R_w_b = rotationFromYawPitchRoll(yaw, pitch, roll) * R_f_b;
  s.T_w_b = geometry::SE3d(geometry::SO3d(R_w_b), q.head<3>());
  s.v_w = dq.head<3>();
  s.a_w = ddq.head<3>();
  s.omega_b = R_f_b.transpose() * omega_f;
  return s;
}

namespace {

double unwrapNear(double angle, double previous) {
  constexpr double kTwoPi = 2.0 * std::numbers::pi;
  return angle - kTwoPi * std::round((angle - previous) / kTwoPi);
}

}  // namespace

Result<BodyTrajectory> fitTrajectory(const std::vector<PathSample>& samples, double duration_s,
                                     const SplineFitOptions& options) {
  std::vector<double> t;
  std::vector<Vector6d> y;
  t.reserve(samples.size());
  y.reserve(samples.size());
  double yaw = 0.0, roll = 0.0;
  for (std::size_t i = 0; i < samples.size(); ++i) {
    const PathSample& s = samples[i];
    yaw = i == 0 ? s.yaw : unwrapNear(s.yaw, yaw);
    roll = i == 0 ? s.roll : unwrapNear(s.roll, roll);
    Vector6d v;
    v << s.p_w, yaw, s.pitch, roll;
    t.push_back(s.t_s);
    y.push_back(v);
  }
  Result<QuinticSpline> spline = fitQuinticSpline(t, y, duration_s, options);
  if (!spline) return spline.error();
  return BodyTrajectory(std::move(spline).value());
}

Result<std::vector<PathSample>> pathSamplesFromPoses(const dataset::Trajectory& poses, double duration_s) {
  if (poses.empty()) return Error{ErrorCode::kDataError, "no poses to replay"};
  const Eigen::Matrix3d R_b_f = rotationFlightFromBody().transpose();
  std::vector<PathSample> out;
  const std::int64_t t0_ns = poses.front().t_ns;
  for (const dataset::StampedPose& pose : poses) {
    const double t_s = static_cast<double>(pose.t_ns - t0_ns) * 1e-9;
    if (t_s > duration_s + 1.0) break;  // a little beyond the end keeps the fit well-posed there
    const Eigen::Matrix3d R_w_f = pose.T_w_b.rotationMatrix() * R_b_f;
    PathSample s;
    s.t_s = t_s;
    s.p_w = pose.T_w_b.translation();
    s.yaw = std::atan2(R_w_f(1, 0), R_w_f(0, 0));
    s.pitch = -std::asin(std::clamp(R_w_f(2, 0), -1.0, 1.0));
    s.roll = std::atan2(R_w_f(2, 1), R_w_f(2, 2));
    constexpr double kMaxPitchRad = 75.0 * std::numbers::pi / 180.0;
    if (std::abs(s.pitch) > kMaxPitchRad) {
      return Error{ErrorCode::kDataError,
                   "pose at t=" + std::to_string(t_s) +
                       " s is far from level (the body x axis should point up, as on the EuRoC MAV); cannot replay it"};
    }
    out.push_back(s);
  }
  return out;
}

}  // namespace cvislam::sim
