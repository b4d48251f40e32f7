// Brute-force descriptor matching, declared in orb.hpp.
#include <bit>
#include <cstring>
#include <limits>
#include <span>

#include "common/features/best_two.hpp"
#include "common/features/orb.hpp"

namespace cvislam::features {

int hammingDistance(const Descriptor& a, const Descriptor& b) {
  int bits = 0;
  for (std::size_t i = 0; i < a.size(); i += 8) {
    std::uint64_t x = 0;
    std::uint64_t y = 0;
    std::memcpy(&x, a.data() + i, 8);
    std::memcpy(&y, b.data() + i, 8);
    bits += std::popcount(x ^ y);
  }
  return bits;
}

int matchDescriptors(std::span<const Descriptor> query, std::span<const Descriptor> train, const MatchOptions& options,
                     std::span<DescriptorMatch> matches) {
  int count = 0;
  for (std::size_t q = 0; q < query.size() && static_cast<std::size_t>(count) < matches.size(); ++q) {
    BestTwo<std::size_t> nearest;
    for (std::size_t t = 0; t < train.size(); ++t) nearest.offer(hammingDistance(query[q], train[t]), t);
    const int best = nearest.best;
    const std::size_t best_train = nearest.candidate;
    if (best > options.max_distance) continue;
    if (nearest.hasSecond() && static_cast<float>(best) > options.ratio * static_cast<float>(nearest.second)) {
      continue;
    }
    if (options.mutual) {
      bool is_mutual = true;
      for (std::size_t other = 0; other < query.size() && is_mutual; ++other) {
        if (other != q && hammingDistance(query[other], train[best_train]) < best) is_mutual = false;
      }
      if (!is_mutual) continue;
    }
    matches[static_cast<std::size_t>(count++)] = {static_cast<int>(q), static_cast<int>(best_train), best};
  }
  return count;
}

}  // namespace cvislam::features
