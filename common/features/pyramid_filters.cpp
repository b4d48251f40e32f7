#include "common/features/pyramid_filters.hpp"

#include <algorithm>
#include <cstddef>
#include <cstring>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

// GCC warns that passing 32-byte vectors by value changes the ABI without AVX. Every function here that does is
// internal to this file and inlined into its caller, so no call crosses the ABI.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

namespace cvislam::features::detail {

namespace {

// N lanes of 16 bits, and the N bytes they widen from (GCC takes no dependent vector_size: one per width).
template <int N>
struct Lanes;
template <>
struct Lanes<8> {
  using U16 = std::uint16_t __attribute__((vector_size(16)));
  using U8 = std::uint8_t __attribute__((vector_size(8)));
};
template <>
struct Lanes<16> {
  using U16 = std::uint16_t __attribute__((vector_size(32)));
  using U8 = std::uint8_t __attribute__((vector_size(16)));
};

template <int N>
[[gnu::always_inline]] inline typename Lanes<N>::U16 widen(const std::uint8_t* p) {
  typename Lanes<N>::U8 v;
  std::memcpy(&v, p, sizeof(v));
  return __builtin_convertvector(v, typename Lanes<N>::U16);
}

template <int N>
[[gnu::always_inline]] inline typename Lanes<N>::U16 load16(const std::uint16_t* p) {
  typename Lanes<N>::U16 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

template <int N>
[[gnu::always_inline]] inline void blurRows(const std::uint8_t* img, int w, int h, int y_begin, int y_end,
                                            std::uint8_t* out, std::uint16_t* v) {
  using U16 = typename Lanes<N>::U16;
  for (int y = std::max(0, y_begin); y < std::min(h, y_end); ++y) {
    std::array<const std::uint8_t*, 7> rows{};
    for (int i = 0; i < 7; ++i) {
      rows[static_cast<std::size_t>(i)] =
          img + static_cast<std::ptrdiff_t>(std::clamp(y + i - kBlurRadius, 0, h - 1)) * w;
    }
    // Vertical pass: the weights sum to 256, so 255 x 256 fits 16 bits; rounded back to 8 bits of range.
    int x = 0;
    for (; x + N <= w; x += N) {  // symmetric weights: pairs of rows share a multiplication
      U16 acc = (widen<N>(rows[0] + x) + widen<N>(rows[6] + x)) * kBlurWeights[0] +
                (widen<N>(rows[1] + x) + widen<N>(rows[5] + x)) * kBlurWeights[1] +
                (widen<N>(rows[2] + x) + widen<N>(rows[4] + x)) * kBlurWeights[2] +
                widen<N>(rows[3] + x) * kBlurWeights[3];
      acc = (acc + 128) >> 8;
      std::memcpy(v + x, &acc, sizeof(acc));
    }
    for (; x < w; ++x) {
      unsigned acc = 0;
      for (std::size_t i = 0; i < 7; ++i) acc += rows[i][x] * kBlurWeights[i];
      v[x] = static_cast<std::uint16_t>((acc + 128) >> 8);
    }
    // Horizontal pass.
    std::uint8_t* o = out + static_cast<std::ptrdiff_t>(y) * w;
    const auto scalar = [&](int xx) {
      unsigned acc = 0;
      for (int i = 0; i < 7; ++i)
        acc += v[std::clamp(xx + i - kBlurRadius, 0, w - 1)] * kBlurWeights[static_cast<std::size_t>(i)];
      o[xx] = static_cast<std::uint8_t>((acc + 128) >> 8);
    };
    x = 0;
    for (; x < std::min(kBlurRadius, w); ++x) scalar(x);
    for (; x + N + kBlurRadius <= w; x += N) {
      U16 acc = (load16<N>(v + x - 3) + load16<N>(v + x + 3)) * kBlurWeights[0] +
                (load16<N>(v + x - 2) + load16<N>(v + x + 2)) * kBlurWeights[1] +
                (load16<N>(v + x - 1) + load16<N>(v + x + 1)) * kBlurWeights[2] + load16<N>(v + x) * kBlurWeights[3];
      acc = (acc + 128) >> 8;
      const auto narrow = __builtin_convertvector(acc, typename Lanes<N>::U8);
      std::memcpy(o + x, &narrow, sizeof(narrow));
    }
    for (; x < w; ++x) scalar(x);
  }
}

template <int N>
[[gnu::always_inline]] inline void blendRows(const std::uint8_t* r0, const std::uint8_t* r1, std::uint16_t w0,
                                             std::uint16_t w1, int width, std::uint16_t* out) {
  int x = 0;
  for (; x + N <= width; x += N) {
    // 255 x 256 fits 16 bits; wrap-around at 256 x 256 cannot happen since the weights sum to 256.
    const typename Lanes<N>::U16 blended = widen<N>(r0 + x) * w0 + widen<N>(r1 + x) * w1;
    std::memcpy(out + x, &blended, sizeof(blended));
  }
  for (; x < width; ++x) out[x] = static_cast<std::uint16_t>(r0[x] * w0 + r1[x] * w1);
}

[[gnu::always_inline]] inline std::uint8_t resamplePixel(const std::uint16_t* row, std::int32_t i, std::int32_t w,
                                                         int step) {
  return static_cast<std::uint8_t>((static_cast<std::uint32_t>(row[i]) * static_cast<std::uint32_t>(256 - w) +
                                    static_cast<std::uint32_t>(row[i + step]) * static_cast<std::uint32_t>(w) +
                                    32768U) >>
                                   16U);
}

}  // namespace

void resampleRowNarrow(const std::uint16_t* row, const std::int32_t* index, const std::int32_t* weight, int step,
                       int width, std::uint8_t* out) {
  for (int x = 0; x < width; ++x) out[x] = resamplePixel(row, index[x], weight[x], step);
}

#if defined(__x86_64__)
// Eight pixels a step: one 32-bit gather at row + index fetches both taps (row[i] low, row[i + 1] high), and the
// sums (at most 65280 x 256 + 32768) fit 32-bit lanes.
__attribute__((target("avx2"))) void resampleRowWide(const std::uint16_t* row, const std::int32_t* index,
                                                     const std::int32_t* weight, int step, int width,
                                                     std::uint8_t* out) {
  int x = 0;
  if (step == 1) {
    const __m256i low_half = _mm256_set1_epi32(0xFFFF);
    const __m256i full = _mm256_set1_epi32(256);
    const __m256i half = _mm256_set1_epi32(32768);
    for (; x + 8 <= width; x += 8) {
      const __m256i i = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(index + x));
      const __m256i w = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(weight + x));
      const __m256i taps = _mm256_i32gather_epi32(reinterpret_cast<const int*>(row), i, 2);
      const __m256i left = _mm256_and_si256(taps, low_half);
      const __m256i right = _mm256_srli_epi32(taps, 16);
      const __m256i sum =
          _mm256_add_epi32(_mm256_mullo_epi32(left, _mm256_sub_epi32(full, w)), _mm256_mullo_epi32(right, w));
      const __m256i pixels = _mm256_srli_epi32(_mm256_add_epi32(sum, half), 16);  // 0..255 in each 32-bit lane
      // Narrow to bytes: within each 128-bit half, lanes 0-3 end up in its first 4 bytes.
      const __m256i words = _mm256_packus_epi32(pixels, pixels);
      const __m256i bytes = _mm256_packus_epi16(words, words);
      const auto first = static_cast<std::uint32_t>(_mm256_extract_epi32(bytes, 0));
      const auto second = static_cast<std::uint32_t>(_mm256_extract_epi32(bytes, 4));
      std::memcpy(out + x, &first, sizeof(first));
      std::memcpy(out + x + 4, &second, sizeof(second));
    }
  }
  for (; x < width; ++x) out[x] = resamplePixel(row, index[x], weight[x], step);
}
#else
void resampleRowWide(const std::uint16_t* row, const std::int32_t* index, const std::int32_t* weight, int step,
                     int width, std::uint8_t* out) {
  resampleRowNarrow(row, index, weight, step, width, out);
}
#endif

void blurRowsNarrow(const std::uint8_t* image, int width, int height, int y_begin, int y_end, std::uint8_t* out,
                    std::uint16_t* scratch) {
  blurRows<8>(image, width, height, y_begin, y_end, out, scratch);
}

void blendRowsNarrow(const std::uint8_t* upper, const std::uint8_t* lower, std::uint16_t upper_weight,
                     std::uint16_t lower_weight, int width, std::uint16_t* out) {
  blendRows<8>(upper, lower, upper_weight, lower_weight, width, out);
}

// As the corner detector (fast_corners.cpp): in a generic x86-64 build the 16-lane forms are compiled for AVX2 on
// their own and called only where the CPU has it; with AVX2 on anyway they are plain code; elsewhere (AArch64:
// NEON's registers hold 8 lanes of 16 bits) they are the narrow forms.
#if defined(__x86_64__) && !defined(__AVX2__)
#define CVISLAM_PYRAMID_WIDE_TARGET __attribute__((target("avx2")))
constexpr int kWideLanes = 16;
#elif defined(__AVX2__)
#define CVISLAM_PYRAMID_WIDE_TARGET
constexpr int kWideLanes = 16;
#else
#define CVISLAM_PYRAMID_WIDE_TARGET
constexpr int kWideLanes = 8;
#endif

CVISLAM_PYRAMID_WIDE_TARGET void blurRowsWide(const std::uint8_t* image, int width, int height, int y_begin, int y_end,
                                              std::uint8_t* out, std::uint16_t* scratch) {
  blurRows<kWideLanes>(image, width, height, y_begin, y_end, out, scratch);
}

CVISLAM_PYRAMID_WIDE_TARGET void blendRowsWide(const std::uint8_t* upper, const std::uint8_t* lower,
                                               std::uint16_t upper_weight, std::uint16_t lower_weight, int width,
                                               std::uint16_t* out) {
  blendRows<kWideLanes>(upper, lower, upper_weight, lower_weight, width, out);
}

}  // namespace cvislam::features::detail
