#include "agent_rt/mapping/keyframe_retention.hpp"

#include <cmath>
#include <limits>

namespace cvislam::agent {

Status KeyframeRetentionOptions::validate() const {
  if (place_keyframes < 0) return Error{ErrorCode::kInvalidArgument, "mapping: place_keyframes must be >= 0"};
  if (!(angle_weight_m >= 0.0) || !std::isfinite(angle_weight_m)) {
    return Error{ErrorCode::kInvalidArgument, "mapping: place_angle_weight_m must be a finite number >= 0"};
  }
  return Status::Ok();
}

namespace {

struct Place {
  Eigen::Vector3d p_w;     // camera centre
  Eigen::Vector3d axis_w;  // optical axis
};

Place placeOf(const LocalMap& map, PoolHandle handle) {
  const geometry::SE3d T_w_c = map.keyframes().get(handle)->T_w_s * map.extrinsics();
  return Place{T_w_c.translation(), T_w_c.so3().matrix().col(2)};
}

double squaredDistance(const Place& a, const Place& b, double angle_weight_m) {
  const double angle_rad = std::atan2(a.axis_w.cross(b.axis_w).norm(), a.axis_w.dot(b.axis_w));
  const double angle_m = angle_weight_m * angle_rad;
  return (a.p_w - b.p_w).squaredNorm() + angle_m * angle_m;
}

}  // namespace

std::optional<PoolHandle> keyframeToEvict(const LocalMap& map, const std::vector<PoolHandle>& own, int recent,
                                          const KeyframeRetentionOptions& options) {
  if (own.empty()) return std::nullopt;
  // Candidates are own[0, older); below two of them no older keyframe can cover one, and age decides.
  const std::size_t kept = recent > 0 ? static_cast<std::size_t>(recent) : 0;
  const std::size_t older = own.size() > kept ? own.size() - kept : 0;
  if (older < 2 || options.place_keyframes == 0) return own.front();
  std::vector<Place> places;
  places.reserve(older);
  for (std::size_t i = 0; i < older; ++i) places.push_back(placeOf(map, own[i]));
  std::size_t evict = 0;  // the oldest has no older keyframe to cover it: it stays unless nothing else can go
  double best = std::numeric_limits<double>::infinity();
  for (std::size_t i = 1; i < older; ++i) {
    double nearest = std::numeric_limits<double>::infinity();
    for (std::size_t j = 0; j < i; ++j)
      nearest = std::min(nearest, squaredDistance(places[i], places[j], options.angle_weight_m));
    // Ties go to the newer keyframe, for the reason in the header.
    if (nearest <= best) {
      best = nearest;
      evict = i;
    }
  }
  return own[evict];
}

}  // namespace cvislam::agent
