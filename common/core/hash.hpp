// FNV-1a, 64 bit: a small, stable hash of bytes, for checksums and cache keys (not for security). The vocabulary
// file's checksum and the simulator's plan fingerprint both use it.
#pragma once

#include <cstdint>
#include <string_view>

namespace cvislam {

class Fnv1a64 {
 public:
  void add(std::string_view bytes) {
    for (const char c : bytes) {
      hash_ ^= static_cast<std::uint8_t>(c);
      hash_ *= kPrime;
    }
  }
  [[nodiscard]] std::uint64_t value() const { return hash_; }

 private:
  static constexpr std::uint64_t kOffsetBasis = 0xCBF29CE484222325ULL;
  static constexpr std::uint64_t kPrime = 0x100000001B3ULL;
  std::uint64_t hash_ = kOffsetBasis;
};

inline std::uint64_t fnv1a64(std::string_view bytes) {
  Fnv1a64 hash;
  hash.add(bytes);
  return hash.value();
}

}  // namespace cvislam
