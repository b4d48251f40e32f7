#include "common/features/fast_corners.hpp"

#include <algorithm>
#include <bit>
#include <cstdlib>
#include <cstring>

#include "common/features/byte_vectors.hpp"

// GCC warns that passing 32-byte vectors by value changes the ABI without AVX. Every function here that does is
// internal to this file and inlined into its caller, so no call crosses the ABI.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

namespace cvislam::features::detail {

namespace {

// The 16 pixels of the Bresenham circle of radius 3, in order around the circle.
constexpr std::array<std::array<int, 2>, 16> kFastCircle = {{{0, -3},
                                                             {1, -3},
                                                             {2, -2},
                                                             {3, -1},
                                                             {3, 0},
                                                             {3, 1},
                                                             {2, 2},
                                                             {1, 3},
                                                             {0, 3},
                                                             {-1, 3},
                                                             {-2, 2},
                                                             {-3, 1},
                                                             {-3, 0},
                                                             {-3, -1},
                                                             {-2, -2},
                                                             {-1, -3}}};

// Offsets of the circle's pixels from the centre in an image with rows of `stride` bytes.
std::array<std::ptrdiff_t, 16> circleOffsets(int stride) {
  std::array<std::ptrdiff_t, 16> offsets{};
  for (std::size_t k = 0; k < 16; ++k) {
    offsets[k] = static_cast<std::ptrdiff_t>(kFastCircle[k][1]) * stride + kFastCircle[k][0];
  }
  return offsets;
}

// The FAST score of 16 consecutive pixels starting at p: the largest t for which 9 contiguous circle pixels are
// all brighter than the centre + t or all darker than the centre - t, i.e. the best arc's smallest difference.
// Pixels whose score is <= threshold (not FAST-9 corners at that threshold) get 0.
//
// The difference to the centre is monotonic in the circle pixel, so an arc's smallest difference is the
// difference of its extreme pixel: brighter arcs are scored by max over arcs of the arc's darkest pixel, darker
// arcs by min over arcs of the arc's brightest pixel, and the centre is subtracted once at the end.
template <class V>
[[gnu::always_inline]] inline V fastScores(const std::uint8_t* p, const std::array<std::ptrdiff_t, 16>& circle,
                                           V threshold) {
  const V centre = load<V>(p);
  // Filled in stages below, each element before it is read; zeroing them first would cost in the hot loop.
  std::array<V, 16> ring;  // NOLINT(cppcoreguidelines-pro-type-member-init)
  // A 9-arc covers two neighbouring compass points (0, 4, 8, 12): test them first, as FAST does, and work out
  // the arcs only of the polarity (brighter or darker) that passes in some pixel.
  for (std::size_t k = 0; k < 16; k += 4) ring[k] = load<V>(p + circle[k]);
  const V compass_bright = vmax(vmax(vmin(ring[0], ring[4]), vmin(ring[4], ring[8])),
                                vmax(vmin(ring[8], ring[12]), vmin(ring[12], ring[0])));
  const V compass_dark = vmin(vmin(vmax(ring[0], ring[4]), vmax(ring[4], ring[8])),
                              vmin(vmax(ring[8], ring[12]), vmax(ring[12], ring[0])));
  const bool bright = anyNonZero(reinterpret_cast<V>(saturatingSub(compass_bright, centre) > threshold));
  const bool dark = anyNonZero(reinterpret_cast<V>(saturatingSub(centre, compass_dark) > threshold));
  if (!bright && !dark) return V{};
#pragma GCC unroll 16
  for (std::size_t k = 0; k < 16; ++k) {
    if (k % 4 != 0) ring[k] = load<V>(p + circle[k]);
  }
  // The best arc of 9 by doubling: extremes over arcs of 2, 4, 8, then 9. `inner` is min for brighter arcs
  // (an arc is as bright as its darkest pixel) and `outer` picks the best arc, max; the other way for darker.
  const auto best_arc = [&ring](auto inner, auto outer, V worst) __attribute__((always_inline)) {
    std::array<V, 16> m2;  // NOLINT(cppcoreguidelines-pro-type-member-init): filled by the loops below
    std::array<V, 16> m4;  // NOLINT(cppcoreguidelines-pro-type-member-init)
#pragma GCC unroll 16
    for (std::size_t k = 0; k < 16; ++k) m2[k] = inner(ring[k], ring[(k + 1) & 15U]);
#pragma GCC unroll 16
    for (std::size_t k = 0; k < 16; ++k) m4[k] = inner(m2[k], m2[(k + 2) & 15U]);
    V best = worst;
#pragma GCC unroll 16
    for (std::size_t k = 0; k < 16; ++k)
      best = outer(best, inner(inner(m4[k], m4[(k + 4) & 15U]), ring[(k + 8) & 15U]));
    return best;
  };
  V score{};
  if (bright) score = saturatingSub(best_arc(Min{}, Max{}, V{}), centre);
  if (dark) score = vmax(score, saturatingSub(centre, best_arc(Max{}, Min{}, V{} + 255)));
  return score & reinterpret_cast<V>(score > threshold);
}

// FAST-9 corners of a level with 3x3 non-maximum suppression, sizeof(V) pixels at a time, into `corners`;
// returns their number. Scores are computed one row ahead of the suppression, in a ring of three rows, over one
// pixel more than the corners' range so that corners at its edge see all their neighbours. The same corners
// for any lane count (integer arithmetic; the last block of a row overlaps the one before it).
template <class V>
[[gnu::always_inline]] inline int detectCorners(const CornerScan& scan, std::span<std::uint64_t> corners) {
  const std::array<std::ptrdiff_t, 16> circle = circleOffsets(scan.width);
  constexpr int kLanes = sizeof(V);
  const int w = scan.width;
  const int h = scan.height;
  const int edge = scan.edge;
  const int x_begin = edge - 1;
  const int x_end = w - edge + 1;     // scores over [x_begin, x_end), corners over [edge, w - edge)
  const int corner_x_end = w - edge;  // corners over [edge, corner_x_end)
  if (corner_x_end - edge < kLanes || h - 2 * edge < 1) return 0;  // too small for a row of kLanes corners
  const V threshold = V{} + scan.threshold;

  const auto score_row = [&](int y, std::uint8_t* out) __attribute__((always_inline)) {
    // Only [x_begin, x_end) is written, and only that is read.
    const std::uint8_t* r = scan.image + static_cast<std::ptrdiff_t>(y) * w;
    for (int x = x_begin; x < x_end; x += kLanes) {
      const int x0 = std::min(x, x_end - kLanes);  // the last block overlaps the one before: same scores
      const V s = fastScores(r + x0, circle, threshold);
      std::memcpy(out + x0, &s, sizeof(s));
    }
  };

  std::size_t count = 0;
  std::uint8_t* above = scan.score_rows[0];
  std::uint8_t* centre = scan.score_rows[1];
  std::uint8_t* below = scan.score_rows[2];
  score_row(edge - 1, above);
  score_row(edge, centre);
  for (int y = edge; y < h - edge; ++y) {
    score_row(y + 1, below);
    // Ties: a corner must beat its right and lower neighbours and equal at least those left and above, so
    // that exactly one of two equal neighbours survives. The last block overlaps the one before it, whose
    // pixels it skips.
    for (int x = edge; x < corner_x_end; x += kLanes) {
      const int x0 = std::min(x, corner_x_end - kLanes);
      const V c = load<V>(centre + x0);
      if (!anyNonZero(c)) continue;
      const auto at_least = [&c](const std::uint8_t* q) __attribute__((always_inline)) {
        return vmax(c, load<V>(q)) == c;
      };
      const auto beats = [&c](const std::uint8_t* q) __attribute__((always_inline)) {
        return vmax(c, load<V>(q)) != load<V>(q);
      };
      const auto keep = reinterpret_cast<V>(at_least(above + x0 - 1) & at_least(above + x0) & at_least(above + x0 + 1) &
                                            at_least(centre + x0 - 1) & beats(centre + x0 + 1) & beats(below + x0 - 1) &
                                            beats(below + x0) & beats(below + x0 + 1));
      const auto keep_words = words(keep);
      for (std::size_t word = 0; word < keep_words.size(); ++word) {
        std::uint64_t bits = keep_words[word] & 0x8080808080808080ULL;
        while (bits != 0) {
          const int lane = static_cast<int>(word) * 8 + std::countr_zero(bits) / 8;
          bits &= bits - 1;
          const int xx = x0 + lane;
          if (xx < x || count >= corners.size()) continue;
          corners[count++] = packKey(centre[xx], scan.level, xx, y);
        }
      }
    }
    std::uint8_t* recycled = above;
    above = centre;
    centre = below;
    below = recycled;
  }
  return static_cast<int>(count);
}

}  // namespace

int detectCornersNarrow(const CornerScan& scan, std::span<std::uint64_t> corners) {
  return detectCorners<U8x16>(scan, corners);
}

// The 32-lane detector. Where the compiler targets AVX2 anyway (the board-x86-64-v3 preset) it is plain code;
// in a generic x86-64 build it is compiled for AVX2 on its own and used only when the CPU has AVX2
// (wideVectorsAvailable). Elsewhere (AArch64: NEON has 16 lanes) there is none.
#if defined(__x86_64__) && !defined(__AVX2__)
#define CVISLAM_ORB_WIDE_BY_CPU_CHECK 1
__attribute__((target("avx2"))) int detectCornersWide(const CornerScan& scan, std::span<std::uint64_t> corners) {
  return detectCorners<U8x32>(scan, corners);
}
#elif defined(__AVX2__)
int detectCornersWide(const CornerScan& scan, std::span<std::uint64_t> corners) {
  return detectCorners<U8x32>(scan, corners);
}
#else
int detectCornersWide(const CornerScan& scan, std::span<std::uint64_t> corners) {
  return detectCorners<U8x16>(scan, corners);
}
#endif

bool wideVectorsAvailable() {
  const char* narrow = std::getenv("CVISLAM_ORB_NARROW");
  if (narrow != nullptr && std::strcmp(narrow, "1") == 0) return false;
#if defined(CVISLAM_ORB_WIDE_BY_CPU_CHECK)
  return __builtin_cpu_supports("avx2") != 0;
#elif defined(__AVX2__)
  return true;
#else
  return false;
#endif
}

}  // namespace cvislam::features::detail
