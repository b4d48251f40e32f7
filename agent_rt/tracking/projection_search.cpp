#include "agent_rt/tracking/projection_search.hpp"
#include "common/features/best_two.hpp"

#include <algorithm>
#include <limits>

namespace cvislam::agent {

Status ProjectionSearchOptions::validate() const {
  if (max_distance < 1 || max_distance > 256) {
    return Error{ErrorCode::kInvalidArgument,
                 "projection search: max_distance (tracking.max_descriptor_distance) must be in [1, 256] bits"};
  }
  if (!(ratio > 0.0F && ratio <= 1.0F)) {
    return Error{ErrorCode::kInvalidArgument, "projection search: ratio (tracking.match_ratio) must be in (0, 1]"};
  }
  return Status::Ok();
}

void KeypointGrid::build(std::span<const features::Keypoint> keypoints, int width, int height, int cell_px) {
  keypoints_ = keypoints.first(std::min(keypoints.size(), kMaxFrameKeypoints));
  cell_px_ = std::max(1, cell_px);
  columns_ = std::max(1, (width + cell_px_ - 1) / cell_px_);
  rows_ = std::max(1, (height + cell_px_ - 1) / cell_px_);
  while (static_cast<std::size_t>(columns_) * static_cast<std::size_t>(rows_) > kMaxGridCells) {  // coarsen
    cell_px_ *= 2;
    columns_ = (width + cell_px_ - 1) / cell_px_;
    rows_ = (height + cell_px_ - 1) / cell_px_;
  }
  const std::size_t cells = static_cast<std::size_t>(columns_) * static_cast<std::size_t>(rows_);
  // Counting sort of the keypoints by cell.
  std::fill(start_.begin(), start_.begin() + static_cast<std::ptrdiff_t>(cells) + 1, std::uint16_t{0});
  const auto cell_of = [&](const features::Keypoint& k) {
    return static_cast<std::size_t>(cellOf(static_cast<double>(k.px.y()), rows_)) * static_cast<std::size_t>(columns_) +
           static_cast<std::size_t>(cellOf(static_cast<double>(k.px.x()), columns_));
  };
  for (const features::Keypoint& k : keypoints_) ++start_[cell_of(k) + 1];
  for (std::size_t c = 0; c < cells; ++c) start_[c + 1] = static_cast<std::uint16_t>(start_[c + 1] + start_[c]);
  std::array<std::uint16_t, kMaxGridCells> fill{};  // on the stack: 8 KB
  for (std::size_t i = 0; i < keypoints_.size(); ++i) {
    const std::size_t cell = cell_of(keypoints_[i]);
    order_[start_[cell] + fill[cell]++] = static_cast<std::uint16_t>(i);
  }
}

int ProjectionMatcher::search(std::span<const ProjectedMapPoint> points, const KeypointGrid& grid,
                              std::span<const features::Descriptor> frame_descriptors,
                              const ProjectionSearchOptions& options, std::span<int> match_of_point) {
  const std::size_t keypoints = std::min(frame_descriptors.size(), kMaxFrameKeypoints);
  std::fill(owner_.begin(), owner_.begin() + static_cast<std::ptrdiff_t>(keypoints), -1);
  for (std::size_t i = 0; i < points.size() && i < match_of_point.size(); ++i) {
    match_of_point[i] = -1;
    features::BestTwo<int> nearest(std::numeric_limits<int>::max(), -1);
    grid.forEachWithin(points[i].px, points[i].radius_px, [&](int k) {
      if (static_cast<std::size_t>(k) >= keypoints) return;
      nearest.offer(features::hammingDistance(points[i].descriptor, frame_descriptors[static_cast<std::size_t>(k)]), k);
    });
    const int best = nearest.best;
    const int best_keypoint = nearest.candidate;
    if (best_keypoint < 0 || best > options.max_distance) continue;
    if (nearest.hasSecond() &&
        (best == nearest.second || static_cast<float>(best) > options.ratio * static_cast<float>(nearest.second))) {
      continue;  // ambiguous, a tie included
    }
    const auto k = static_cast<std::size_t>(best_keypoint);
    if (owner_[k] >= 0) {
      if (owner_distance_[k] <= best) continue;  // the keypoint stays with the closer point
      match_of_point[static_cast<std::size_t>(owner_[k])] = -1;
    }
    owner_[k] = static_cast<int>(i);
    owner_distance_[k] = best;
    match_of_point[i] = best_keypoint;
  }
  return static_cast<int>(std::count_if(
      match_of_point.begin(),
      match_of_point.begin() + static_cast<std::ptrdiff_t>(std::min(points.size(), match_of_point.size())),
      [](int m) { return m >= 0; }));
}

}  // namespace cvislam::agent
