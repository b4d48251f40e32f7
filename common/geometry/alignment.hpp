// Closed-form alignment of corresponding point sets: the transform X minimising sum |dst_i - X * src_i|^2.
//
// Umeyama, "Least-squares estimation of transformation parameters between two point patterns", PAMI 1991,
// for SE3 (rotation + translation) and Sim3 (with scale); and the 4-DoF position + yaw alignment that
// suits visual-inertial estimates, whose roll and pitch are observable through gravity.
#pragma once

#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::geometry {

// T_dst_src with scale fixed to 1. Needs >= 3 points that are not collinear.
Result<SE3d> alignSE3(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst);

// S_dst_src with scale. Needs >= 3 points that are not collinear.
Result<Sim3d> alignSim3(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst);

// T_dst_src restricted to a rotation about +z (gravity-aligned frames) and a translation.
// Needs >= 2 points with horizontal spread.
Result<SE3d> alignPositionYaw(std::span<const Eigen::Vector3d> src, std::span<const Eigen::Vector3d> dst);

// Rotation about +z by `yaw` radians.
SO3d rotationAboutZ(double yaw);

}  // namespace cvislam::geometry
