// Guided matching of projected map points to a frame's keypoints (tracking's projection search): each
// map point, projected with the predicted pose, is matched to the keypoint with the closest descriptor
// within a radius of its projection, if unambiguous; a keypoint goes to at most one map point (the closest
// in descriptor space; the other point stays unmatched in this pass, with no second try). A grid over the image makes
// the radius queries cheap. Fixed-capacity storage: nothing allocates after construction.
#pragma once

#include <array>
#include <cstdint>
#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/features/orb.hpp"

namespace cvislam::agent {

inline constexpr std::size_t kMaxFrameKeypoints = 4096;
inline constexpr std::size_t kMaxGridCells = 4096;

class KeypointGrid {
 public:
  // Buckets the keypoints (at most kMaxFrameKeypoints; the rest are ignored) in square cells of cell_px. The
  // grid keeps a view of `keypoints`, which must outlive the queries.
  void build(std::span<const features::Keypoint> keypoints, int width, int height, int cell_px = 16);

  // Calls f(index) for every keypoint within `radius_px` of `px`.
  template <typename F>
  void forEachWithin(const Eigen::Vector2d& px, double radius_px, F&& f) const {
    if (columns_ == 0) return;
    const int x0 = cellOf(px.x() - radius_px, columns_);
    const int x1 = cellOf(px.x() + radius_px, columns_);
    const int y0 = cellOf(px.y() - radius_px, rows_);
    const int y1 = cellOf(px.y() + radius_px, rows_);
    const double r2 = radius_px * radius_px;
    for (int cy = y0; cy <= y1; ++cy) {
      for (int cx = x0; cx <= x1; ++cx) {
        const std::size_t cell =
            static_cast<std::size_t>(cy) * static_cast<std::size_t>(columns_) + static_cast<std::size_t>(cx);
        for (std::uint16_t k = start_[cell]; k < start_[cell + 1]; ++k) {
          const std::uint16_t index = order_[k];
          if ((keypoints_[index].px.cast<double>() - px).squaredNorm() <= r2) f(static_cast<int>(index));
        }
      }
    }
  }

 private:
  [[nodiscard]] int cellOf(double coordinate, int cells) const {
    const double c = coordinate / static_cast<double>(cell_px_);
    if (!(c >= 0.0)) return 0;  // negative or NaN
    return c >= static_cast<double>(cells - 1) ? cells - 1 : static_cast<int>(c);
  }

  std::span<const features::Keypoint> keypoints_;
  int cell_px_ = 16;
  int columns_ = 0;
  int rows_ = 0;
  std::array<std::uint16_t, kMaxGridCells + 1> start_{};
  std::array<std::uint16_t, kMaxFrameKeypoints> order_{};
};

struct ProjectedMapPoint {
  Eigen::Vector2d px = Eigen::Vector2d::Zero();  // projection with the predicted pose (distorted pixels)
  features::Descriptor descriptor{};
  double radius_px = 8.0;  // search radius; grows with the prediction's uncertainty and the point's level
};

struct ProjectionSearchOptions {
  int max_distance = 50;  // Hamming bits
  float ratio = 0.9F;     // best / second best within the radius

  [[nodiscard]] Status validate() const;
};

class ProjectionMatcher {
 public:
  // match_of_point[i] receives the keypoint index matched to points[i], or -1. Returns the number matched.
  int search(std::span<const ProjectedMapPoint> points, const KeypointGrid& grid,
             std::span<const features::Descriptor> frame_descriptors, const ProjectionSearchOptions& options,
             std::span<int> match_of_point);

 private:
  std::array<int, kMaxFrameKeypoints> owner_{};  // the point that holds each keypoint, or -1
  std::array<int, kMaxFrameKeypoints> owner_distance_{};
};

}  // namespace cvislam::agent
