// A smooth body (IMU) trajectory with exact kinematics.
//
// The body frame b is the IMU frame, as in EuRoC: x points up when the vehicle is level, z forward (along the
// camera's optical axis) and y to the right. The spline carries the position p_w and the Z-Y-X Euler angles
// (yaw, pitch, roll) of a "flight frame" f (x forward, y left, z up), with R_w_b = R_w_f * R_f_b. Angular
// rate and acceleration follow analytically from the spline derivatives; nothing is differenced numerically.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "test/sim/spline.hpp"

namespace cvislam::sim {

struct KinematicState {
  double t_s = 0.0;
  geometry::SE3d T_w_b;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();      // [m/s]
  Eigen::Vector3d a_w = Eigen::Vector3d::Zero();      // [m/s^2], gravity not included
  Eigen::Vector3d omega_b = Eigen::Vector3d::Zero();  // angular rate of b relative to w, in b [rad/s]
};

// Rotation of the body (IMU) frame in the flight frame: b_x = f_z (up), b_y = -f_y (right), b_z = f_x (forward).
Eigen::Matrix3d rotationFlightFromBody();
// R_w_f = Rz(yaw) * Ry(pitch) * Rx(roll).
Eigen::Matrix3d rotationFromYawPitchRoll(double yaw, double pitch, double roll);

class BodyTrajectory {
 public:
  BodyTrajectory() = default;
  // Spline channels: x, y, z [m], yaw, pitch, roll [rad]; time 0 is the start of the mission.
  explicit BodyTrajectory(QuinticSpline spline) : spline_(std::move(spline)) {}

  [[nodiscard]] KinematicState state(double t_s) const;
  [[nodiscard]] double duration() const { return spline_.duration(); }
  [[nodiscard]] const QuinticSpline& spline() const { return spline_; }

 private:
  QuinticSpline spline_;
};

// A designed path sample: position and flight-frame yaw/pitch/roll; yaw may wrap, it is unwrapped here.
struct PathSample {
  double t_s = 0.0;
  Eigen::Vector3d p_w = Eigen::Vector3d::Zero();
  double yaw = 0.0;
  double pitch = 0.0;
  double roll = 0.0;
};

// Fits the smooth trajectory through samples (unwrapping yaw and roll). Used both for designed paths and for
// replaying real flights.
Result<BodyTrajectory> fitTrajectory(const std::vector<PathSample>& samples, double duration_s,
                                     const SplineFitOptions& options);

// Converts real poses of the body (IMU) frame (EuRoC ground truth) into path samples, with time measured from
// the first pose, keeping those up to duration_s. Fails if the body is far from level (|pitch| > 75 deg),
// where Euler angles would be ill-conditioned.
Result<std::vector<PathSample>> pathSamplesFromPoses(const dataset::Trajectory& poses, double duration_s);

}  // namespace cvislam::sim
