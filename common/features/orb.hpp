// ORB features spread over the image, and binary descriptor matching (CVI-SLAM: 500 ORB features per
// keyframe, spread on a grid, over a scale pyramid).
//
// Extraction uses OpenCV's FAST/ORB on a view of the caller's pixels (no copy) and keeps the strongest
// corners of each grid cell, handing the quota of cells that have too few to the others, so that texture-rich
// regions cannot take all the features. Output goes to caller-owned fixed-capacity storage. OpenCV
// allocates inside detect/compute; bench_features counts those allocations per frame.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"

namespace cvislam::features {

using Descriptor = std::array<std::uint8_t, 32>;  // 256-bit rBRIEF

struct Keypoint {
  Eigen::Vector2f px = Eigen::Vector2f::Zero();  // distorted pixel position, level-0 coordinates
  float response = 0.0F;                         // FAST/Harris score
  float angle_deg = 0.0F;                        // orientation
  std::uint8_t octave = 0;                       // pyramid level
};

struct OrbOptions {
  int max_features = 500;
  int grid_columns = 8;
  int grid_rows = 6;
  int pyramid_levels = 8;
  float scale_factor = 1.2F;
  int fast_threshold = 7;   // low, so that weak regions still give corners; the grid keeps the strongest
  int edge_threshold = 19;  // border without features [px]; rBRIEF needs 16 px around a keypoint at its level
  // Corners detected per feature kept, before the grid selection. OpenCV keeps the strongest corners of the
  // whole image, so too few candidates leave weak regions empty: on EuRoC V1_01, 4 covered 46 % of an 8x6
  // grid in the worst frame, 12 covers 98 %, 20 covers 100 % but its weak corners match worse.
  int candidates_per_feature = 12;

  // Names the bad field.
  [[nodiscard]] Status validate() const;
};

class OrbExtractor {
 public:
  static Result<OrbExtractor> create(const OrbOptions& options);
  OrbExtractor(OrbExtractor&&) noexcept;
  OrbExtractor& operator=(OrbExtractor&&) noexcept;
  ~OrbExtractor();

  // Extracts up to options.max_features keypoints and descriptors from a row-major 8-bit image into the
  // two spans (which must hold max_features); returns how many were written.
  int extract(std::span<const std::uint8_t> pixels, int width, int height, std::span<Keypoint> keypoints,
              std::span<Descriptor> descriptors);

  [[nodiscard]] const OrbOptions& options() const;

 private:
  struct Impl;
  explicit OrbExtractor(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// Number of differing bits.
int hammingDistance(const Descriptor& a, const Descriptor& b);

struct DescriptorMatch {
  int query = 0;
  int train = 0;
  int distance = 0;
};

struct MatchOptions {
  int max_distance = 50;  // bits out of 256
  float ratio = 0.8F;     // best / second best, Lowe's test
  bool mutual = true;     // also the query must be the train's best
};

// Brute-force matching of every query against every train descriptor, into caller-owned storage (as long
// as `query`); returns the number of matches. For the guided searches of tracking, which compare a few
// candidates each, call hammingDistance directly.
int matchDescriptors(std::span<const Descriptor> query, std::span<const Descriptor> train, const MatchOptions& options,
                     std::span<DescriptorMatch> matches);

}  // namespace cvislam::features
