// Measurement and state types shared by the dataset readers, the simulator, the agent and the evaluator.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "common/geometry/lie.hpp"

namespace cvislam::dataset {

// One IMU reading in the IMU (sensor) frame s, as EuRoC's imu0/data.csv stores it.
struct ImuSample {
  std::int64_t t_ns = 0;
  Eigen::Vector3d gyro_s = Eigen::Vector3d::Zero();   // angular rate w_RS_S [rad/s]
  Eigen::Vector3d accel_s = Eigen::Vector3d::Zero();  // specific force a_RS_S [m/s^2]
};

// A timestamped pose of a body (IMU) frame b in a world frame w.
struct StampedPose {
  std::int64_t t_ns = 0;
  geometry::SE3d T_w_b;
  // Made before the estimator's world frame was final (before its IMU initialisation): up to scale in mono, and
  // not what a metric estimate is scored on. Trajectory files mark such rows (kBeforeInitialisationMark).
  bool before_initialisation = false;
};
using Trajectory = std::vector<StampedPose>;

// EuRoC state_groundtruth_estimate0: pose, velocity and the IMU biases of the body (= IMU) frame.
struct GroundTruthState {
  std::int64_t t_ns = 0;
  geometry::SE3d T_w_b;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();         // [m/s]
  Eigen::Vector3d gyro_bias = Eigen::Vector3d::Zero();   // b_w [rad/s]
  Eigen::Vector3d accel_bias = Eigen::Vector3d::Zero();  // b_a [m/s^2]
  bool has_velocity_and_biases = false;                  // false for pose-only files
};

enum class DistortionModel { kNone, kRadialTangential, kEquidistant };

// One camera as described by an ASL sensor.yaml.
struct CameraCalibration {
  std::string name = "cam0";
  int width = 752;
  int height = 480;
  double rate_hz = 20.0;
  double fx = 458.654;  // pinhole intrinsics [px]
  double fy = 457.296;
  double cx = 367.215;
  double cy = 248.375;
  DistortionModel distortion = DistortionModel::kRadialTangential;
  std::array<double, 4> distortion_coefficients{};  // radtan: k1 k2 p1 p2; equidistant: k1 k2 k3 k4
  geometry::SE3d T_b_c;                             // camera -> body (EuRoC's T_BS)
  std::string comment;
};

// The IMU as described by an ASL sensor.yaml (continuous-time noise densities, as Kalibr defines them).
struct ImuCalibration {
  double rate_hz = 200.0;
  double gyro_noise_density = 1.6968e-4;  // [rad/s/sqrt(Hz)]
  double gyro_random_walk = 1.9393e-5;    // [rad/s^2/sqrt(Hz)]
  double accel_noise_density = 2.0e-3;    // [m/s^2/sqrt(Hz)]
  double accel_random_walk = 3.0e-3;      // [m/s^3/sqrt(Hz)]
  geometry::SE3d T_b_i;                   // IMU -> body (identity on EuRoC)
  std::string comment;
};

std::string_view toString(DistortionModel model);

}  // namespace cvislam::dataset
