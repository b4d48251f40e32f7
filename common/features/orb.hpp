// ORB features spread over the image, and binary descriptor matching (CVI-SLAM: 500 ORB features per
// keyframe, spread on a grid, over a scale pyramid).
//
// Extraction is our own code and makes no heap allocation after OrbExtractor::create, which sizes every buffer
// (pyramid, smoothed levels, corner candidates) for OrbOptions::max_width x max_height; the tracking loop calls
// extract on every frame. Per frame:
//   1. a pyramid of pyramid_levels levels, each scale_factor smaller than the one before (bilinear);
//   2. FAST-9 corners (16-pixel Bresenham circle of radius 3, fast_threshold) on each level, scored by the FAST
//      score (the largest threshold at which the pixel is still a corner), 3x3 non-maximum suppression, at least
//      edge_threshold pixels from the level's border;
//   3. candidates: max_features x candidates_per_feature corners, shared out between the levels in proportion to
//      1/scale_factor^level (as ORB does), the strongest of each level; and, for each grid cell left without any,
//      the strongest corner the cell has (at any level);
//   4. the grid: the strongest candidates of each cell of a grid_columns x grid_rows grid over the image, up to an
//      equal quota per cell, then the strongest of the rest, so that the quota of under-filled cells goes to the
//      others and texture-rich regions cannot take all the features;
//   5. orientation by the intensity centroid of a disc of radius 15 around the corner at its level, and a steered
//      BRIEF descriptor (256 intensity comparisons of point pairs inside that disc, rotated by the orientation) on
//      the level smoothed by a 7-tap Gaussian (sigma 2).
// The 256 point pairs are generated once, at the first create(), by our own fixed-seed generator (isotropic
// Gaussian, sigma 31/5, both points inside the disc of radius 15, no two tests nearly alike), so descriptors do
// not change between runs, builds or platforms.
// Output goes to caller-owned fixed-capacity storage.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <span>

#include <Eigen/Core>

#include "common/core/result.hpp"

namespace cvislam::features {

using Descriptor = std::array<std::uint8_t, 32>;  // 256-bit steered BRIEF, test i in bit i % 8 of byte i / 8

struct Keypoint {
  Eigen::Vector2f px = Eigen::Vector2f::Zero();  // distorted pixel position, level-0 coordinates
  float response = 0.0F;                         // FAST score: largest threshold at which it is still a corner
  float angle_deg = 0.0F;                        // orientation in [0, 360): 0 along +x, 90 along +y (down)
  std::uint8_t octave = 0;                       // pyramid level
};

struct OrbOptions {
  int max_features = 500;
  int grid_columns = 8;
  int grid_rows = 6;
  int pyramid_levels = 8;
  float scale_factor = 1.2F;
  int fast_threshold = 7;   // low, so that weak regions still give corners; the grid keeps the strongest
  int edge_threshold = 19;  // border without features [px]; the descriptor and orientation disc needs 16 px
  // Corners kept per feature, before the grid selection, shared out between the levels; the strongest of each
  // level, so too few candidates leave weak regions empty, and too many let weak corners in everywhere. On
  // EuRoC V1_01 with an 8x6 grid (worst frame of cam0): 8 covers 71 % of the cells, 12 covers 94 %, 20 covers
  // 100 % but matches worse (stereo inliers 92 % -> 89 %). Each cell left without a candidate also gets its
  // strongest corner, which brings 12 to 98 % at no cost in matching.
  int candidates_per_feature = 12;
  // Largest image extract accepts; create() sizes all buffers for it: about 7 bytes per pixel with the default
  // pyramid (9.4 MB for 1280x1024).
  int max_width = 1280;
  int max_height = 1024;

  // Names the bad field.
  [[nodiscard]] Status validate() const;

  // These options with the buffers sized for one camera's images (max_width x max_height = width x height):
  // create() fills its buffers, so they are resident whether used or not.
  [[nodiscard]] OrbOptions forImageSize(int width, int height) const {
    OrbOptions sized = *this;
    sized.max_width = width;
    sized.max_height = height;
    return sized;
  }
};

class OrbExtractor {
 public:
  static Result<OrbExtractor> create(const OrbOptions& options);
  OrbExtractor(OrbExtractor&&) noexcept;
  OrbExtractor& operator=(OrbExtractor&&) noexcept;
  ~OrbExtractor();

  // Extracts up to options.max_features keypoints and descriptors from a row-major 8-bit image into the
  // two spans (which must hold max_features); returns how many were written, strongest first. Allocates
  // nothing. An image larger than options.max_width x max_height (see checkImageSize), or pixels shorter than
  // width x height, gives 0 keypoints.
  int extract(std::span<const std::uint8_t> pixels, int width, int height, std::span<Keypoint> keypoints,
              std::span<Descriptor> descriptors);

  // Whether extract accepts images of this size; for callers to check their camera once at start-up.
  [[nodiscard]] Status checkImageSize(int width, int height) const;

  [[nodiscard]] const OrbOptions& options() const;

  // Pixels the corner detector scores at a time: 32 where the CPU has AVX2, 16 otherwise (SSE2, NEON). The
  // output is the same either way; CVISLAM_ORB_NARROW=1 in the environment at create() forces 16.
  [[nodiscard]] int cornerLanes() const;

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
