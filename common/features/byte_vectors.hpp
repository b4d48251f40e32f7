#pragma once
// Internal to common/features: small GCC/Clang vector types and helpers shared by the ORB extractor and the
// FAST detector. Not part of any module's interface.

#include <array>
#include <cstdint>
#include <cstring>

// GCC warns that passing 32-byte vectors by value changes the ABI where AVX is not enabled. These helpers are
// always inlined into their callers, so no call crosses that ABI.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

namespace cvislam::features::detail {

// Byte vectors (GCC/Clang vector extensions, no intrinsics): 16 lanes are SSE2 on x86-64 and NEON on AArch64;
// the corner detector also has a 32-lane form for AVX2 (fast_corners.cpp).

using U8x16 = std::uint8_t __attribute__((vector_size(16)));
using U8x32 = std::uint8_t __attribute__((vector_size(32)));
using U8x8 = std::uint8_t __attribute__((vector_size(8)));
using U16x8 = std::uint16_t __attribute__((vector_size(16)));
using F32x4 = float __attribute__((vector_size(16)));
using I32x4 = std::int32_t __attribute__((vector_size(16)));

template <class V>
[[gnu::always_inline]] inline V load(const std::uint8_t* p) {
  V v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
inline U16x8 widen8(const std::uint8_t* p) {
  U8x8 v;
  std::memcpy(&v, p, sizeof(v));
  return __builtin_convertvector(v, U16x8);
}
inline U16x8 load8x16(const std::uint16_t* p) {
  U16x8 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
template <class V>
[[gnu::always_inline]] inline V vmin(V a, V b) {
  return a < b ? a : b;
}
template <class V>
[[gnu::always_inline]] inline V vmax(V a, V b) {
  return a > b ? a : b;
}
// As function objects, so that they inline wherever they are passed (also into the AVX2-compiled detector).
struct Min {
  template <class V>
  [[gnu::always_inline]] V operator()(V a, V b) const {
    return vmin(a, b);
  }
};
struct Max {
  template <class V>
  [[gnu::always_inline]] V operator()(V a, V b) const {
    return vmax(a, b);
  }
};
template <class V>
[[gnu::always_inline]] inline V saturatingSub(V a, V b) {
  return a - vmin(a, b);
}
// The vector's bytes as 64-bit words.
template <class V>
[[gnu::always_inline]] inline std::array<std::uint64_t, sizeof(V) / 8> words(V v) {
  std::array<std::uint64_t, sizeof(V) / 8> w{};
  std::memcpy(w.data(), &v, sizeof(v));
  return w;
}
template <class V>
[[gnu::always_inline]] inline bool anyNonZero(V v) {
  std::uint64_t any = 0;
  for (const std::uint64_t w : words(v)) any |= w;
  return any != 0;
}

}  // namespace cvislam::features::detail

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
