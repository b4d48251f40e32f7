// Triangulation of a 3D point from bearing observations in several calibrated views.
//
// Bearings are rays in the camera frame (any length, normalised inside). Poses are T_c_w (world -> camera)
// for the linear method, the form a map stores for projection. All functions are allocation-free, so the
// agent's mapping thread can call them on its hot path.
#pragma once

#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::geometry {

struct TriangulationOptions {
  // Below this parallax (radians, largest angle between any two rays at the point) depth is unreliable.
  double min_parallax_rad = 0.5 * 3.14159265358979323846 / 180.0;
  // Largest angle (radians) between an observed bearing and the ray to the triangulated point.
  double max_bearing_error_rad = 2.0 * 3.14159265358979323846 / 180.0;

  [[nodiscard]] Status validate() const;
};

// Linear (DLT) triangulation: minimises sum |b_i x (R_i p + t_i)|^2 over homogeneous p, then checks that
// the point is finite, in front of every camera, seen with enough parallax and consistent with every
// bearing. Needs >= 2 views.
Result<Eigen::Vector3d> triangulateLinear(std::span<const SE3d> T_c_w, std::span<const Eigen::Vector3d> bearings_c,
                                          const TriangulationOptions& options = {});

// Two-view midpoint: the point halfway between the closest points of the two rays (camera poses T_w_c).
// Fails for parallel rays and for a point behind either camera.
Result<Eigen::Vector3d> triangulateMidpoint(const SE3d& T_w_c0, const Eigen::Vector3d& bearing_c0, const SE3d& T_w_c1,
                                            const Eigen::Vector3d& bearing_c1);

// Angle (radians) between two rays, in [0, pi].
double rayAngle(const Eigen::Vector3d& a, const Eigen::Vector3d& b);

// Parallax at p_w seen from camera centres c0_w and c1_w, in radians.
double parallaxAngle(const Eigen::Vector3d& p_w, const Eigen::Vector3d& c0_w, const Eigen::Vector3d& c1_w);

}  // namespace cvislam::geometry
