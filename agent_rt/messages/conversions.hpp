// Between the plain arrays of the messages and the Eigen / Lie types of the code.
#pragma once

#include <array>

#include <Eigen/Core>

#include "agent_rt/messages/messages.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

inline PoseMsg toMsg(const geometry::SE3d& T) {
  const Eigen::Quaterniond& q = T.quaternion();
  return PoseMsg{{T.translation().x(), T.translation().y(), T.translation().z()}, {q.x(), q.y(), q.z(), q.w()}};
}

inline geometry::SE3d fromMsg(const PoseMsg& m) {
  return {Eigen::Quaterniond(m.q[3], m.q[0], m.q[1], m.q[2]).normalized(), Eigen::Vector3d(m.p[0], m.p[1], m.p[2])};
}

inline std::array<double, 3> toArray(const Eigen::Vector3d& v) {
  return {v.x(), v.y(), v.z()};
}
inline Eigen::Vector3d toVector3(const std::array<double, 3>& a) {
  return {a[0], a[1], a[2]};
}

inline std::array<double, 6> toMsg(const imu::ImuBias& b) {
  return {b.gyro.x(), b.gyro.y(), b.gyro.z(), b.accel.x(), b.accel.y(), b.accel.z()};
}
inline imu::ImuBias biasFromMsg(const std::array<double, 6>& a) {
  imu::ImuBias b;
  b.gyro = Eigen::Vector3d(a[0], a[1], a[2]);
  b.accel = Eigen::Vector3d(a[3], a[4], a[5]);
  return b;
}

inline ImuSampleMsg toMsg(const dataset::ImuSample& s) {
  return {s.t_ns, toArray(s.gyro_s), toArray(s.accel_s)};
}

inline dataset::ImuSample fromMsg(const ImuSampleMsg& m) {
  dataset::ImuSample s;
  s.t_ns = m.t_ns;
  s.gyro_s = toVector3(m.gyro);
  s.accel_s = toVector3(m.accel);
  return s;
}

}  // namespace cvislam::agent
