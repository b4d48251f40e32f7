#pragma once
// Internal to common/features: FAST-9 corners with 3x3 non-maximum suppression, in 16 or 32 byte lanes, and the
// 64-bit key each corner is reported as. OrbExtractor (orb.cpp) is the only user.

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

namespace cvislam::features::detail {

constexpr int kMaxImageSide = 4096;  // x and y are packed into 12 bits each in a corner key

// Corner keys: one 64-bit word per corner, so that sorting them orders by score and then by a hash of the
// position (ties between equal FAST scores are frequent; a position hash breaks them without favouring any part
// of the image, and deterministically).
//   bits 56-63 score, 28-55 tie-break hash, 24-27 level, 12-23 y, 0-11 x

constexpr std::uint64_t packKey(int score, int level, int x, int y) {
  std::uint32_t h = static_cast<std::uint32_t>(x) * 0x9E3779B1U ^ static_cast<std::uint32_t>(y) * 0x85EBCA77U ^
                    static_cast<std::uint32_t>(level) * 0xC2B2AE3DU;
  h ^= h >> 15U;
  h *= 0x2C1B3C6DU;
  h ^= h >> 12U;
  return (static_cast<std::uint64_t>(score) << 56U) | (static_cast<std::uint64_t>(h & 0x0FFFFFFFU) << 28U) |
         (static_cast<std::uint64_t>(level) << 24U) | (static_cast<std::uint64_t>(y) << 12U) |
         static_cast<std::uint64_t>(x);
}
constexpr int keyScore(std::uint64_t key) {
  return static_cast<int>(key >> 56U);
}
constexpr int keyLevel(std::uint64_t key) {
  return static_cast<int>((key >> 24U) & 0xFU);
}
constexpr int keyY(std::uint64_t key) {
  return static_cast<int>((key >> 12U) & 0xFFFU);
}
constexpr int keyX(std::uint64_t key) {
  return static_cast<int>(key & 0xFFFU);
}

// One pyramid level to scan for corners, and three rows of scratch for the scores.
struct CornerScan {
  const std::uint8_t* image = nullptr;
  int width = 0;  // also the row stride
  int height = 0;
  int edge = 0;  // corners at least this far from the border
  std::uint8_t threshold = 0;
  int level = 0;
  std::array<std::uint8_t*, 3> score_rows{};  // each at least `width` bytes
};

// FAST-9 corners of the level (score > threshold) that beat their 3x3 neighbourhood, as keys into `corners`;
// returns their number (at most corners.size()). Both give the same corners in the same order: narrow is 16
// lanes (SSE2, NEON); wide is 32 lanes where wideVectorsAvailable(), and narrow otherwise.
int detectCornersNarrow(const CornerScan& scan, std::span<std::uint64_t> corners);
int detectCornersWide(const CornerScan& scan, std::span<std::uint64_t> corners);

// Whether detectCornersWide runs 32 lanes on this CPU. CVISLAM_ORB_NARROW=1 in the environment turns it off
// (the corners are the same either way; it is there to compare, and as a way out should a CPU misreport).
bool wideVectorsAvailable();

}  // namespace cvislam::features::detail
