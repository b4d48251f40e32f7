#include "common/dataset/pose_fields.hpp"

#include <cmath>

#include "common/core/text.hpp"
#include "common/dataset/csv.hpp"

namespace cvislam::dataset {
namespace {

// A quaternion far from unit length is a corrupt row, not a rounding effect: reject it.
bool makePose(const Eigen::Vector3d& p, const Eigen::Quaterniond& q, geometry::SE3d& T, std::string& problem) {
  const double norm = q.norm();
  if (!(norm > 0.9 && norm < 1.1)) {
    problem = "quaternion norm " + text::formatDouble(norm) + " is not 1 (corrupt row?)";
    return false;
  }
  T = geometry::SE3d(geometry::SO3d(q), p);
  return true;
}

bool parseValues(const std::vector<std::string_view>& fields, std::size_t first, double (&v)[7], std::string& problem) {
  for (std::size_t i = 0; i < 7; ++i) {
    if (!parseFieldDouble(fields, first + i, v[i], problem)) return false;
  }
  return true;
}

}  // namespace

bool parsePositionQuaternionWxyz(const std::vector<std::string_view>& fields, std::size_t first, geometry::SE3d& T,
                                 std::string& problem) {
  double v[7];
  if (!parseValues(fields, first, v, problem)) return false;
  return makePose(Eigen::Vector3d(v[0], v[1], v[2]), Eigen::Quaterniond(v[3], v[4], v[5], v[6]), T, problem);
}

bool parsePositionQuaternionXyzw(const std::vector<std::string_view>& fields, std::size_t first, geometry::SE3d& T,
                                 std::string& problem) {
  double v[7];
  if (!parseValues(fields, first, v, problem)) return false;
  return makePose(Eigen::Vector3d(v[0], v[1], v[2]), Eigen::Quaterniond(v[6], v[3], v[4], v[5]), T, problem);
}

}  // namespace cvislam::dataset
