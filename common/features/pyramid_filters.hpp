#pragma once
// Internal to common/features: the two row filters of the ORB pyramid, in 8 or 16 lanes of 16 bits (SSE2 or NEON;
// AVX2), with the same integer arithmetic either way, so both give the same pixels. OrbExtractor (orb.cpp) is the
// only user; it picks the wide form where wideVectorsAvailable() (fast_corners.hpp) says so.

#include <array>
#include <cstdint>

namespace cvislam::features::detail {

// The blur before the descriptors: a Gaussian of sigma 2 sampled at -3..3 and scaled to sum to 256, separable.
constexpr int kBlurRadius = 3;
constexpr std::array<std::uint16_t, 7> kBlurWeights = {18, 33, 49, 56, 49, 33, 18};

// Rows [y_begin, y_end) (clipped to the image) of a width x height image, blurred with kBlurWeights vertically and
// then horizontally, each pass rounded back to 8 bits of range; the border is replicated. Rows of `image` and `out`
// are `width` bytes apart. `scratch` holds at least width + 16 values.
void blurRowsNarrow(const std::uint8_t* image, int width, int height, int y_begin, int y_end, std::uint8_t* out,
                    std::uint16_t* scratch);
void blurRowsWide(const std::uint8_t* image, int width, int height, int y_begin, int y_end, std::uint8_t* out,
                  std::uint16_t* scratch);

// Two rows blended for bilinear downsampling: out[x] = upper[x] * upper_weight + lower[x] * lower_weight, for x in
// [0, width); the weights sum to 256, so every value fits 16 bits.
void blendRowsNarrow(const std::uint8_t* upper, const std::uint8_t* lower, std::uint16_t upper_weight,
                     std::uint16_t lower_weight, int width, std::uint16_t* out);
void blendRowsWide(const std::uint8_t* upper, const std::uint8_t* lower, std::uint16_t upper_weight,
                   std::uint16_t lower_weight, int width, std::uint16_t* out);

// One row of a level from the blended row of the level above (blendRows*), bilinear along x:
//   out[x] = (row[index[x]] * (256 - weight[x]) + row[index[x] + step] * weight[x] + 32768) >> 16
// for x in [0, width); step is 1, or 0 when the source row is one pixel wide. The wide form gathers 8 pixels at a
// time with AVX2 (x86-64 only; elsewhere it is the narrow, scalar one).
void resampleRowNarrow(const std::uint16_t* row, const std::int32_t* index, const std::int32_t* weight, int step,
                       int width, std::uint8_t* out);
void resampleRowWide(const std::uint16_t* row, const std::int32_t* index, const std::int32_t* weight, int step,
                     int width, std::uint8_t* out);

}  // namespace cvislam::features::detail
