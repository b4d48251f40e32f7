// Parsing position + quaternion fields, shared by the EuRoC and TUM readers.
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "common/geometry/lie.hpp"

namespace cvislam::dataset {

// fields[first..first+6] = p_x p_y p_z q_w q_x q_y q_z (EuRoC order).
bool parsePositionQuaternionWxyz(const std::vector<std::string_view>& fields, std::size_t first, geometry::SE3d& T,
                                 std::string& problem);
// fields[first..first+6] = p_x p_y p_z q_x q_y q_z q_w (TUM order).
bool parsePositionQuaternionXyzw(const std::vector<std::string_view>& fields, std::size_t first, geometry::SE3d& T,
                                 std::string& problem);

}  // namespace cvislam::dataset
