// A hierarchical vocabulary of ORB descriptors (bag of binary words, after Galvez-Lopez and Tardos 2012, as
// CVI-SLAM's place recognition uses), for the server's keyframe database and loop/map-match verification.
//
// Training: hierarchical k-means with `branching` (k) children per node and `levels` (L) levels below the root.
// Each node's descriptors are split by k-means++ seeding (from a generator seeded by the training seed and the
// node's id, so the result does not depend on the thread count) and Hamming-distance k-means whose centres are
// the bitwise majority of their members. A node with k or fewer descriptors is not split further: it is a leaf
// (a word). Words are weighted by tf-idf: idf(w) = ln(training images / training images containing w).
//
// Use: a descriptor descends from the root to the closest child at every level, to a word. transform() gives
// the L1-normalised BoW vector (tf-idf weights) and the feature vector: for each node at `direct_level` (counted
// from the root, 0 = root), the features under it. Descriptor matching between two keyframes only compares
// features under the same node (the direct index).
//
// File format (little-endian, written and read by save()/load()): the magic "CVISLAMVOC", a format version, a
// UTF-8 provenance text (how the file was made: command, data, seed, tool version), k, L, the node count, then
// every node in breadth-first order (parent, 32-byte descriptor, idf weight for words) and a checksum of all the
// bytes before it. load() names the file and the problem for a missing, truncated, corrupt or wrong-version file.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "common/features/orb.hpp"

namespace cvislam::features {

using WordId = std::uint32_t;
using NodeId = std::uint32_t;

struct BowEntry {
  WordId word = 0;
  float weight = 0.0F;
};
// Sorted by word, each word once; weights are non-negative and sum to 1 (L1), or the vector is empty.
using BowVector = std::vector<BowEntry>;

struct NodeFeature {
  NodeId node = 0;
  std::uint16_t feature = 0;  // index into the keyframe's descriptors
};
// Sorted by node, then feature.
using FeatureVector = std::vector<NodeFeature>;

// L1 similarity of two L1-normalised BoW vectors, in [0, 1]: 1 - 0.5 * sum |a_w - b_w|.
double bowScore(const BowVector& a, const BowVector& b);

struct VocabularyTrainingOptions {
  int branching = 10;      // k
  int levels = 5;          // L, below the root
  std::uint64_t seed = 1;  // k-means++ seeding
  int max_iterations = 10;
  int threads = 2;  // the result does not depend on it
  // Called now and then during training with a one-line description of the progress.
  std::function<void(const std::string&)> progress;

  // Names the bad field.
  [[nodiscard]] Status validate() const;
};

class Vocabulary {
 public:
  // Trains on the descriptors of each training image (one vector per image; the idf counts images).
  // `provenance` is stored in the file's header. Fails when there are no descriptors.
  static Result<Vocabulary> train(const std::vector<std::vector<Descriptor>>& images,
                                  const VocabularyTrainingOptions& options, std::string provenance);
  static Result<Vocabulary> load(const std::filesystem::path& path);
  [[nodiscard]] Status save(const std::filesystem::path& path) const;

  Vocabulary(Vocabulary&&) noexcept;
  Vocabulary& operator=(Vocabulary&&) noexcept;
  ~Vocabulary();

  [[nodiscard]] int branching() const;
  [[nodiscard]] int levels() const;
  [[nodiscard]] std::size_t wordCount() const;
  [[nodiscard]] std::size_t nodeCount() const;
  [[nodiscard]] const std::string& provenance() const;

  // The word a descriptor falls in, and its idf weight.
  [[nodiscard]] WordId word(const Descriptor& descriptor) const;
  [[nodiscard]] float idf(WordId word) const;
  // The BoW vector of a keyframe's descriptors, and its feature vector at `direct_level` (0 = root,
  // clamped to levels()). `features` may be null.
  void transform(std::span<const Descriptor> descriptors, BowVector& bow, FeatureVector* features,
                 int direct_level) const;

 private:
  struct Impl;
  explicit Vocabulary(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::features
