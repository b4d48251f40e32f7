// Deterministic random numbers for the simulator.
//
// std::uniform_real_distribution and std::normal_distribution are implementation-defined, so the same seed
// could give other numbers with another standard library. The simulator promises byte-identical output for
// the same seed, so it draws from std::mt19937_64 (fully specified by the standard) and maps the raw 64-bit
// words to numbers itself.
#pragma once

#include <cmath>
#include <cstdint>
#include <numbers>
#include <random>

namespace cvislam::sim {

// SplitMix64 finaliser: a well-mixed 64-bit hash, used to derive independent seeds and lattice values.
constexpr std::uint64_t mix64(std::uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27U)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31U);
}

// A seed for one purpose (stream) of one object (index), derived from the mission seed.
constexpr std::uint64_t deriveSeed(std::uint64_t seed, std::uint64_t stream, std::uint64_t index = 0) {
  return mix64(mix64(seed ^ mix64(stream)) + index);
}

class Rng {
 public:
  explicit Rng(std::uint64_t seed) : engine_(seed) {}

  // Uniform in [0, 1) with 53 random bits.
  double uniform() { return static_cast<double>(engine_() >> 11U) * 0x1.0p-53; }
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  // Uniform integer in [0, n).
  std::uint64_t index(std::uint64_t n) { return n == 0 ? 0 : engine_() % n; }
  // Standard normal by Box-Muller (one value per call; the second is dropped for simplicity).
  double normal() {
    const double u1 = 1.0 - uniform();  // (0, 1]
    const double u2 = uniform();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
  }

 private:
  std::mt19937_64 engine_;
};

}  // namespace cvislam::sim
