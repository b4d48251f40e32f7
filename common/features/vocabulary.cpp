// The hierarchical ORB vocabulary: training by hierarchical Hamming k-means, lookup, BoW and feature vectors, and
// the binary file (see vocabulary.hpp for the interface and the format in outline).
//
// The tree is kept as flat arrays indexed by node id. Ids are breadth-first, so the children of a node are
// contiguous and in the order of their parents: lookup reads k packed descriptors per level, one cache-friendly
// run each. Words are the leaves, numbered in node order.
//
// Training grows the tree a level at a time. Every node of a level is split on its own, by k-means++ seeding from a
// std::mt19937_64 seeded with (training seed, node id) and Hamming k-means with bitwise-majority centres, until no
// assignment changes or max_iterations. Threads share out the nodes of a level; a level with fewer nodes than
// threads (the root) splits its nodes one after the other, each with a parallel assignment step. Either way every
// node's split is the same integer arithmetic on the same members in the same order, so the tree does not depend
// on the thread count. The random numbers come straight from the generator's 64-bit output (no std::
// distribution, whose algorithm the standard leaves to the library), so the tree is the same on every platform.
//
// Decisions the header leaves open:
//   - A node that k-means cannot split into two non-empty clusters (all its descriptors alike) is a leaf too.
//   - idf(w) = ln(N / n_w), N the training images with at least one descriptor, n_w how many of them have a
//     descriptor whose lookup gives w. A word that no training image looks up (possible: lookup descends to the
//     closest centre, which is not always the cluster the descriptor was trained in) counts as seen once, n_w = 1,
//     so it gets ln(N), the largest weight: it is at least as rare as any word seen, and a weight of 0 would make
//     every descriptor that falls in it invisible. A word in every image gets ln(1) = 0: it tells images apart
//     no more than a word in none of them would.
//   - transform() leaves out words whose weight is 0, and gives an empty vector when every weight is 0 (or there
//     are no descriptors). The feature vector covers the first 65,536 descriptors (its index is 16-bit).
//   - bowScore() of an empty vector with anything is 0 (sum of min(a_w, b_w) over common words).
//
// File layout (all integers little-endian, floats as their IEEE-754 bits):
//   "CVISLAMVOC" (10 bytes), u32 format version (1), u32 provenance length in bytes, the provenance (UTF-8),
//   u32 k, u32 L, u32 node count, then per node in breadth-first order: u32 parent (0xFFFFFFFF for the root),
//   32 descriptor bytes, f32 weight (idf for words, 0 for inner nodes); then u64 FNV-1a of every byte before it.
#include "common/features/vocabulary.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <limits>
#include <random>
#include <string_view>
#include <system_error>
#include <thread>
#include <utility>

#include "common/core/hash.hpp"

namespace cvislam::features {

namespace {

constexpr std::string_view kMagic = "CVISLAMVOC";
constexpr std::uint32_t kFormatVersion = 1;
constexpr std::uint32_t kNoParent = 0xFFFFFFFFU;
constexpr WordId kNoWord = 0xFFFFFFFFU;
constexpr std::size_t kNodeBytes = 4 + 32 + 4;
constexpr std::size_t kChecksumBytes = 8;
constexpr int kMaxBranching = 1000;
constexpr int kMaxLevels = 32;
constexpr std::size_t kMaxFeatureIndex = 0xFFFF;

// A descriptor as four 64-bit words, for XOR and popcount.
struct Bits {
  std::array<std::uint64_t, 4> w{};
};

Bits pack(const Descriptor& d) {
  Bits b;
  std::memcpy(b.w.data(), d.data(), sizeof(b.w));
  return b;
}

Descriptor unpack(const Bits& b) {
  Descriptor d;
  std::memcpy(d.data(), b.w.data(), sizeof(b.w));
  return d;
}

inline int distance(const Bits& a, const Bits& b) {
  return std::popcount(a.w[0] ^ b.w[0]) + std::popcount(a.w[1] ^ b.w[1]) + std::popcount(a.w[2] ^ b.w[2]) +
         std::popcount(a.w[3] ^ b.w[3]);
}

// Per-bit counts of ones over a set of descriptors, and its size: the bitwise majority comes from them.
struct BitCounts {
  std::array<std::uint32_t, 256> ones{};
  std::uint32_t size = 0;

  void add(const Bits& b) {
    for (std::size_t word = 0; word < 4; ++word) {
      const std::uint64_t x = b.w[word];
      for (std::size_t bit = 0; bit < 64; ++bit) ones[word * 64 + bit] += static_cast<std::uint32_t>((x >> bit) & 1U);
    }
    ++size;
  }
  void add(const BitCounts& other) {
    for (std::size_t i = 0; i < ones.size(); ++i) ones[i] += other.ones[i];
    size += other.size;
  }
  // A bit is set when more than half of the descriptors have it (a tie gives 0).
  [[nodiscard]] Bits majority() const {
    Bits b;
    for (std::size_t i = 0; i < ones.size(); ++i) {
      if (2U * ones[i] > size) b.w[i / 64] |= std::uint64_t{1} << (i % 64);
    }
    return b;
  }
};

// Runs work(t) for t in [0, threads): t = 0 on the calling thread, the others on new threads. A share whose thread
// cannot be started runs on the calling thread afterwards, so the work gets done either way.
template <typename Work>
void runOnThreads(int threads, const Work& work) {
  std::vector<std::thread> pool;
  std::vector<int> left_over;
  for (int t = 1; t < threads; ++t) {
    try {
      pool.emplace_back([&work, t] { work(t); });
    } catch (const std::system_error&) {
      left_over.push_back(t);
    }
  }
  work(0);
  for (std::thread& thread : pool) thread.join();
  for (int t : left_over) work(t);
}

// [begin, end) of share t of n items split into `shares` contiguous pieces.
std::pair<std::size_t, std::size_t> shareOf(std::size_t n, int shares, int t) {
  const auto s = static_cast<std::size_t>(shares);
  const auto i = static_cast<std::size_t>(t);
  return {n * i / s, n * (i + 1) / s};
}

// Lookup: from the root to the closest child at every level (the first on a tie), until a node without children.
// x86-64 code built for no particular CPU (the project sets no -march) makes each popcount a library call; the
// lookup gets a second version using the POPCNT instruction, picked when the program loads if the CPU has it
// (75 instead of 520 ns per word with the shipped vocabulary), so builds stay portable. Not under ThreadSanitizer:
// the version is picked by a resolver that the loader runs before the TSan runtime is up, and the instrumented
// resolver crashes every program that links the vocabulary.
#if defined(__x86_64__) && defined(__has_attribute) && !defined(__SANITIZE_THREAD__)
#if __has_attribute(target_clones)
#define CVISLAM_VOCABULARY_POPCNT_CLONES __attribute__((target_clones("popcnt", "default")))
#endif
#endif
#ifndef CVISLAM_VOCABULARY_POPCNT_CLONES
#define CVISLAM_VOCABULARY_POPCNT_CLONES
#endif

CVISLAM_VOCABULARY_POPCNT_CLONES
NodeId descendTree(const Bits* descriptors, const NodeId* first_child, const std::uint32_t* child_count, const Bits& d,
                   int level, NodeId& at_level) {
  NodeId node = 0;
  at_level = 0;
  int node_depth = 0;
  while (child_count[node] > 0) {
    const NodeId first = first_child[node];
    const NodeId end = first + child_count[node];
    NodeId best = first;
    int best_distance = distance(d, descriptors[first]);
    for (NodeId c = first + 1; c < end; ++c) {
      const int dc = distance(d, descriptors[c]);
      if (dc < best_distance) {
        best_distance = dc;
        best = c;
      }
    }
    node = best;
    if (++node_depth <= level) at_level = node;
  }
  return node;
}

struct Cluster {
  Bits centre;
  std::vector<std::uint32_t> members;  // indices into the training descriptors, ascending
};

// Splits `members` (indices into `data`) into at most k clusters by k-means++ seeding and Hamming k-means.
// Returns nothing when the node cannot be split into two non-empty clusters.
std::vector<Cluster> splitNode(const std::vector<Bits>& data, const std::vector<std::uint32_t>& members, int k,
                               int max_iterations, std::uint64_t seed, NodeId node, int threads) {
  const std::size_t n = members.size();
  const auto clusters = static_cast<std::size_t>(k);
  std::seed_seq seed_sequence{static_cast<std::uint32_t>(seed), static_cast<std::uint32_t>(seed >> 32U), node};
  std::mt19937_64 rng(seed_sequence);

  // k-means++: the first centre uniformly, each next with probability proportional to D^2, D the Hamming
  // distance to the closest centre chosen so far.
  std::vector<Bits> centres;
  centres.reserve(clusters);
  centres.push_back(data[members[rng() % n]]);
  std::vector<std::uint32_t> closest(n);
  for (std::size_t i = 0; i < n; ++i) {
    closest[i] = static_cast<std::uint32_t>(distance(data[members[i]], centres.front()));
  }
  while (centres.size() < clusters) {
    std::uint64_t total = 0;
    for (std::uint32_t d : closest) total += std::uint64_t{d} * d;
    if (total == 0) break;  // every descriptor equals a centre already
    const std::uint64_t target = rng() % total;
    std::size_t pick = 0;
    for (std::uint64_t sum = 0; pick < n; ++pick) {
      sum += std::uint64_t{closest[pick]} * closest[pick];
      if (sum > target) break;
    }
    centres.push_back(data[members[pick]]);
    for (std::size_t i = 0; i < n; ++i) {
      closest[i] = std::min(closest[i], static_cast<std::uint32_t>(distance(data[members[i]], centres.back())));
    }
  }
  if (centres.size() < 2) return {};
  const std::size_t used = centres.size();

  // Lloyd iterations: assign each descriptor to its closest centre (the first on a tie), then make each centre the
  // bitwise majority of its members. A cluster left empty keeps its centre.
  const int shares = n >= 4096 ? std::max(1, threads) : 1;
  std::vector<std::uint32_t> assignment(n, std::numeric_limits<std::uint32_t>::max());
  std::vector<std::vector<BitCounts>> counts(static_cast<std::size_t>(shares), std::vector<BitCounts>(used));
  std::vector<std::size_t> changed(static_cast<std::size_t>(shares));
  for (int iteration = 0; iteration < max_iterations; ++iteration) {
    runOnThreads(shares, [&](int t) {
      const auto [begin, end] = shareOf(n, shares, t);
      std::vector<BitCounts>& mine = counts[static_cast<std::size_t>(t)];
      std::fill(mine.begin(), mine.end(), BitCounts{});
      std::size_t moved = 0;
      for (std::size_t i = begin; i < end; ++i) {
        const Bits& d = data[members[i]];
        std::uint32_t best = 0;
        int best_distance = distance(d, centres[0]);
        for (std::size_t c = 1; c < used; ++c) {
          const int dc = distance(d, centres[c]);
          if (dc < best_distance) {
            best_distance = dc;
            best = static_cast<std::uint32_t>(c);
          }
        }
        if (assignment[i] != best) ++moved;
        assignment[i] = best;
        mine[best].add(d);
      }
      changed[static_cast<std::size_t>(t)] = moved;
    });
    std::size_t moved = 0;
    for (std::size_t m : changed) moved += m;
    if (moved == 0) break;  // the centres are already the majority of these very members
    for (std::size_t c = 0; c < used; ++c) {
      BitCounts total;
      for (const auto& share : counts) total.add(share[c]);
      if (total.size > 0) centres[c] = total.majority();
    }
  }

  std::vector<Cluster> result(used);
  for (std::size_t c = 0; c < used; ++c) result[c].centre = centres[c];
  for (std::size_t i = 0; i < n; ++i) result[assignment[i]].members.push_back(members[i]);
  std::erase_if(result, [](const Cluster& c) { return c.members.empty(); });
  if (result.size() < 2) return {};
  return result;
}

// ---------------------------------------------------------------------------------------------------------------
// Little-endian bytes and the checksum.

void putU32(std::string& out, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xFFU));
}

void putU64(std::string& out, std::uint64_t v) {
  for (int i = 0; i < 8; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xFFU));
}

std::uint32_t getU32(const std::string& in, std::size_t at) {
  std::uint32_t v = 0;
  for (std::size_t i = 0; i < 4; ++i) v |= std::uint32_t{static_cast<std::uint8_t>(in[at + i])} << (8 * i);
  return v;
}

std::uint64_t getU64(const std::string& in, std::size_t at) {
  std::uint64_t v = 0;
  for (std::size_t i = 0; i < 8; ++i) v |= std::uint64_t{static_cast<std::uint8_t>(in[at + i])} << (8 * i);
  return v;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------------
// The tree.

struct Vocabulary::Impl {
  int branching = 0;
  int levels = 0;
  std::string provenance;
  // Per node, by id:
  std::vector<NodeId> parent;
  std::vector<Bits> descriptor;
  std::vector<float> weight;  // idf for words, 0 for inner nodes
  std::vector<NodeId> first_child;
  std::vector<std::uint32_t> child_count;
  std::vector<std::uint8_t> depth;
  std::vector<WordId> node_word;  // kNoWord for inner nodes
  // Per word:
  std::vector<NodeId> word_node;

  // Derives children, depths and words from `parent`, checking that it is a breadth-first tree of branching k
  // and depth at most L. The message says what is inconsistent.
  [[nodiscard]] Status index() {
    const std::size_t count = parent.size();
    if (count == 0) return Error{ErrorCode::kDataError, "the tree has no nodes"};
    if (parent[0] != kNoParent) return Error{ErrorCode::kDataError, "node 0 (the root) has a parent"};
    first_child.assign(count, 0);
    child_count.assign(count, 0);
    depth.assign(count, 0);
    node_word.assign(count, kNoWord);
    word_node.clear();
    for (std::size_t i = 1; i < count; ++i) {
      const NodeId p = parent[i];
      if (p >= i) {
        return Error{ErrorCode::kDataError, "node " + std::to_string(i) + " has parent " +
                                                (p == kNoParent ? std::string("none") : std::to_string(p)) +
                                                ", which does not come before it"};
      }
      if (i > 1 && p < parent[i - 1]) {
        return Error{ErrorCode::kDataError, "node " + std::to_string(i) + " is out of breadth-first order (parent " +
                                                std::to_string(p) + " after parent " + std::to_string(parent[i - 1]) +
                                                ")"};
      }
      if (child_count[p] == 0) first_child[p] = static_cast<NodeId>(i);
      if (++child_count[p] > static_cast<std::uint32_t>(branching)) {
        return Error{ErrorCode::kDataError,
                     "node " + std::to_string(p) + " has more than k = " + std::to_string(branching) + " children"};
      }
      depth[i] = static_cast<std::uint8_t>(depth[p] + 1);
      if (depth[i] > levels) {
        return Error{ErrorCode::kDataError,
                     "node " + std::to_string(i) + " lies deeper than L = " + std::to_string(levels) + " levels"};
      }
    }
    for (std::size_t i = 0; i < count; ++i) {
      if (child_count[i] > 0) continue;
      if (!std::isfinite(weight[i]) || weight[i] < 0.0F) {
        return Error{ErrorCode::kDataError, "word node " + std::to_string(i) + " has weight " +
                                                std::to_string(weight[i]) + "; idf weights are finite and >= 0"};
      }
      node_word[i] = static_cast<WordId>(word_node.size());
      word_node.push_back(static_cast<NodeId>(i));
    }
    return Status::Ok();
  }

  // The leaf a descriptor descends to; `at_level` gets the node it passes at depth `level`, or the leaf when that
  // lies shallower.
  NodeId descend(const Bits& d, int level, NodeId& at_level) const {
    return descendTree(descriptor.data(), first_child.data(), child_count.data(), d, level, at_level);
  }

  [[nodiscard]] std::size_t fileSize() const {
    return kMagic.size() + 4 + 4 + provenance.size() + 3 * 4 + parent.size() * kNodeBytes + kChecksumBytes;
  }
};

// ---------------------------------------------------------------------------------------------------------------
// Scores and options.

double bowScore(const BowVector& a, const BowVector& b) {
  // For L1-normalised a and b, |a - b| = a + b - 2 min(a, b) summed over all words is 2 - 2 sum min(a, b), so
  // 1 - 0.5 sum |a - b| = sum over the common words of min(a, b).
  double score = 0.0;
  auto i = a.begin();
  auto j = b.begin();
  while (i != a.end() && j != b.end()) {
    if (i->word < j->word) {
      ++i;
    } else if (j->word < i->word) {
      ++j;
    } else {
      score += static_cast<double>(std::min(i->weight, j->weight));
      ++i;
      ++j;
    }
  }
  return std::clamp(score, 0.0, 1.0);
}

Status VocabularyTrainingOptions::validate() const {
  const auto bad = [](const std::string& what) {
    return Error{ErrorCode::kInvalidArgument, "vocabulary training options: " + what};
  };
  if (branching < 2 || branching > kMaxBranching) return bad("branching (k) must be 2 to 1000");
  if (levels < 1 || levels > kMaxLevels) return bad("levels (L) must be 1 to 32");
  if (max_iterations < 1) return bad("max_iterations must be >= 1");
  if (threads < 1 || threads > 256) return bad("threads must be 1 to 256");
  return Status::Ok();
}

// ---------------------------------------------------------------------------------------------------------------
// Training.

Result<Vocabulary> Vocabulary::train(const std::vector<std::vector<Descriptor>>& images,
                                     const VocabularyTrainingOptions& options, std::string provenance) {
  if (Status st = options.validate(); !st) return st.error();
  using Clock = std::chrono::steady_clock;
  const Clock::time_point start = Clock::now();
  const auto report = [&](const std::string& line) {
    if (!options.progress) return;
    const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
    char elapsed[32];
    std::snprintf(elapsed, sizeof(elapsed), " (%.1f s)", seconds);
    options.progress(line + elapsed);
  };

  std::vector<Bits> data;
  std::size_t images_with_descriptors = 0;
  for (const auto& image : images) {
    for (const Descriptor& d : image) data.push_back(pack(d));
    if (!image.empty()) ++images_with_descriptors;
  }
  if (data.empty()) return Error{ErrorCode::kInvalidArgument, "vocabulary training: no descriptors to train on"};
  if (data.size() > std::numeric_limits<std::uint32_t>::max()) {
    return Error{ErrorCode::kInvalidArgument, "vocabulary training: more than 2^32 - 1 descriptors"};
  }

  auto impl = std::make_unique<Impl>();
  Impl& m = *impl;
  m.branching = options.branching;
  m.levels = options.levels;
  m.provenance = std::move(provenance);
  const auto k = static_cast<std::size_t>(options.branching);

  struct Pending {
    NodeId id = 0;
    std::vector<std::uint32_t> members;
  };
  std::vector<Pending> level(1);
  level.front().members.resize(data.size());
  for (std::size_t i = 0; i < data.size(); ++i) level.front().members[i] = static_cast<std::uint32_t>(i);
  {
    BitCounts all;
    for (const Bits& d : data) all.add(d);
    m.parent.push_back(kNoParent);
    m.descriptor.push_back(all.majority());
  }
  if (data.size() <= k) level.clear();
  report("training on " + std::to_string(data.size()) + " descriptors from " + std::to_string(images.size()) +
         " images: k = " + std::to_string(options.branching) + ", L = " + std::to_string(options.levels) + ", seed " +
         std::to_string(options.seed) + ", " + std::to_string(options.threads) + " thread(s)");

  for (int depth = 0; depth < options.levels && !level.empty(); ++depth) {
    std::vector<std::vector<Cluster>> splits(level.size());
    const auto split = [&](std::size_t i, int threads) {
      splits[i] = splitNode(data, level[i].members, options.branching, options.max_iterations, options.seed,
                            level[i].id, threads);
    };
    if (level.size() >= static_cast<std::size_t>(options.threads)) {
      std::atomic<std::size_t> next{0};
      runOnThreads(options.threads, [&](int) {
        for (std::size_t i = next++; i < level.size(); i = next++) split(i, 1);
      });
    } else {
      for (std::size_t i = 0; i < level.size(); ++i) split(i, options.threads);
    }
    std::vector<Pending> next_level;
    std::size_t leaves_here = 0;
    for (std::size_t i = 0; i < level.size(); ++i) {
      if (splits[i].empty()) ++leaves_here;  // all alike: the node stays a leaf
      for (Cluster& cluster : splits[i]) {
        const auto id = static_cast<NodeId>(m.parent.size());
        m.parent.push_back(level[i].id);
        m.descriptor.push_back(cluster.centre);
        if (cluster.members.size() > k && depth + 1 < options.levels) {
          next_level.push_back({id, std::move(cluster.members)});
        } else {
          ++leaves_here;
        }
      }
      std::vector<Cluster>().swap(splits[i]);
      std::vector<std::uint32_t>().swap(level[i].members);
    }
    report("level " + std::to_string(depth + 1) + " of " + std::to_string(options.levels) + ": split " +
           std::to_string(level.size()) + " node(s); " + std::to_string(m.parent.size()) + " nodes so far, " +
           std::to_string(leaves_here) + " new word(s), " + std::to_string(next_level.size()) + " node(s) to split");
    level = std::move(next_level);
  }

  m.weight.assign(m.parent.size(), 0.0F);
  if (Status st = m.index(); !st) {
    return Error{ErrorCode::kInternal, "vocabulary training built an inconsistent tree: " + st.error().message()};
  }

  // idf from the words the training descriptors look up, counting each image once per word.
  const std::size_t words = m.word_node.size();
  const int shares = std::max(1, std::min(options.threads, static_cast<int>(images.size())));
  std::vector<std::vector<std::uint32_t>> image_counts(static_cast<std::size_t>(shares));
  runOnThreads(shares, [&](int t) {
    std::vector<std::uint32_t>& counts = image_counts[static_cast<std::size_t>(t)];
    counts.assign(words, 0);
    std::vector<std::size_t> last_image(words, std::numeric_limits<std::size_t>::max());
    const auto [begin, end] = shareOf(images.size(), shares, t);
    NodeId unused = 0;
    for (std::size_t image = begin; image < end; ++image) {
      for (const Descriptor& d : images[image]) {
        const WordId w = m.node_word[m.descend(pack(d), 0, unused)];
        if (last_image[w] != image) {
          last_image[w] = image;
          ++counts[w];
        }
      }
    }
  });
  std::size_t unseen = 0;
  for (std::size_t w = 0; w < words; ++w) {
    std::uint64_t seen = 0;
    for (const auto& counts : image_counts) seen += counts[w];
    if (seen == 0) ++unseen;
    m.weight[m.word_node[w]] = static_cast<float>(
        std::log(static_cast<double>(images_with_descriptors) / static_cast<double>(std::max<std::uint64_t>(seen, 1))));
  }
  report("done: " + std::to_string(m.parent.size()) + " nodes, " + std::to_string(words) + " words (" +
         std::to_string(unseen) + " looked up by no training image)");
  return Vocabulary(std::move(impl));
}

// ---------------------------------------------------------------------------------------------------------------
// The file.

Status Vocabulary::save(const std::filesystem::path& path) const {
  const Impl& m = *impl_;
  std::string bytes;
  bytes.reserve(m.fileSize());
  bytes.append(kMagic);
  putU32(bytes, kFormatVersion);
  putU32(bytes, static_cast<std::uint32_t>(m.provenance.size()));
  bytes.append(m.provenance);
  putU32(bytes, static_cast<std::uint32_t>(m.branching));
  putU32(bytes, static_cast<std::uint32_t>(m.levels));
  putU32(bytes, static_cast<std::uint32_t>(m.parent.size()));
  for (std::size_t i = 0; i < m.parent.size(); ++i) {
    putU32(bytes, m.parent[i]);
    const Descriptor d = unpack(m.descriptor[i]);
    bytes.append(reinterpret_cast<const char*>(d.data()), d.size());
    putU32(bytes, std::bit_cast<std::uint32_t>(m.weight[i]));
  }
  putU64(bytes, fnv1a64(bytes));

  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) {
    return Error{ErrorCode::kIoError,
                 path.string() + ": cannot open the vocabulary file for writing: " + std::strerror(errno)};
  }
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  out.close();
  if (!out) return Error{ErrorCode::kIoError, path.string() + ": writing the vocabulary failed"};
  return Status::Ok();
}

Result<Vocabulary> Vocabulary::load(const std::filesystem::path& path) {
  const auto fail = [&path](ErrorCode code, const std::string& problem) {
    return Error{code, path.string() + ": " + problem};
  };
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return fail(ErrorCode::kNotFound, "no such vocabulary file");
  if (std::filesystem::is_directory(path, ec)) return fail(ErrorCode::kInvalidArgument, "is a folder, not a file");
  const std::uintmax_t file_size = std::filesystem::file_size(path, ec);
  if (ec) return fail(ErrorCode::kIoError, "cannot get its size: " + ec.message());
  std::string bytes(static_cast<std::size_t>(file_size), '\0');
  {
    std::ifstream in(path, std::ios::binary);
    if (!in) return fail(ErrorCode::kIoError, std::string("cannot open: ") + std::strerror(errno));
    in.read(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    if (static_cast<std::uintmax_t>(in.gcount()) != file_size) return fail(ErrorCode::kIoError, "read failed");
  }

  const auto truncated = [&](const std::string& where) {
    return fail(ErrorCode::kDataError,
                "truncated: the file ends (after " + std::to_string(bytes.size()) + " bytes) inside " + where);
  };
  if (bytes.size() < kMagic.size() || std::string_view(bytes).substr(0, kMagic.size()) != kMagic) {
    if (bytes.size() < kMagic.size() && kMagic.substr(0, bytes.size()) == bytes) return truncated("the magic");
    return fail(ErrorCode::kDataError, "not a cvislam vocabulary (the file does not start with \"CVISLAMVOC\")");
  }
  std::size_t at = kMagic.size();
  if (bytes.size() < at + 8) return truncated("the header");
  const std::uint32_t version = getU32(bytes, at);
  if (version != kFormatVersion) {
    return fail(ErrorCode::kFailedPrecondition, "vocabulary format version " + std::to_string(version) +
                                                    "; this build reads version " + std::to_string(kFormatVersion));
  }
  const std::uint32_t provenance_size = getU32(bytes, at + 4);
  at += 8;
  if (bytes.size() - at < std::uint64_t{provenance_size} + 12) return truncated("the header");
  auto impl = std::make_unique<Impl>();
  Impl& m = *impl;
  m.provenance = bytes.substr(at, provenance_size);
  at += provenance_size;
  const std::uint32_t branching = getU32(bytes, at);
  const std::uint32_t levels = getU32(bytes, at + 4);
  const std::uint32_t node_count = getU32(bytes, at + 8);
  at += 12;
  const std::uint64_t expected = at + std::uint64_t{node_count} * kNodeBytes + kChecksumBytes;
  if (bytes.size() < expected) {
    return fail(ErrorCode::kDataError, "truncated: " + std::to_string(bytes.size()) +
                                           " bytes, but its header announces " + std::to_string(node_count) +
                                           " nodes, which need " + std::to_string(expected) + " bytes");
  }
  if (bytes.size() > expected) {
    return fail(ErrorCode::kDataError, std::to_string(bytes.size() - expected) +
                                           " unexpected bytes after the checksum (the header announces " +
                                           std::to_string(node_count) + " nodes, " + std::to_string(expected) +
                                           " bytes)");
  }
  const std::uint64_t stored = getU64(bytes, bytes.size() - kChecksumBytes);
  if (stored != fnv1a64(std::string_view(bytes).substr(0, bytes.size() - kChecksumBytes))) {
    return fail(ErrorCode::kDataError, "checksum mismatch: the file is corrupt");
  }
  if (branching < 2 || branching > static_cast<std::uint32_t>(kMaxBranching) || levels < 1 ||
      levels > static_cast<std::uint32_t>(kMaxLevels)) {
    return fail(ErrorCode::kDataError, "inconsistent vocabulary: k = " + std::to_string(branching) +
                                           ", L = " + std::to_string(levels) + " (k must be 2 to 1000, L 1 to 32)");
  }
  m.branching = static_cast<int>(branching);
  m.levels = static_cast<int>(levels);
  m.parent.resize(node_count);
  m.descriptor.resize(node_count);
  m.weight.resize(node_count);
  for (std::size_t i = 0; i < node_count; ++i, at += kNodeBytes) {
    m.parent[i] = getU32(bytes, at);
    std::memcpy(m.descriptor[i].w.data(), bytes.data() + at + 4, 32);
    m.weight[i] = std::bit_cast<float>(getU32(bytes, at + 36));
  }
  if (Status st = m.index(); !st) return fail(ErrorCode::kDataError, "inconsistent tree: " + st.error().message());
  return Vocabulary(std::move(impl));
}

// ---------------------------------------------------------------------------------------------------------------
// Use.

Vocabulary::Vocabulary(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Vocabulary::Vocabulary(Vocabulary&&) noexcept = default;
Vocabulary& Vocabulary::operator=(Vocabulary&&) noexcept = default;
Vocabulary::~Vocabulary() = default;

int Vocabulary::branching() const {
  return impl_->branching;
}
int Vocabulary::levels() const {
  return impl_->levels;
}
std::size_t Vocabulary::wordCount() const {
  return impl_->word_node.size();
}
std::size_t Vocabulary::nodeCount() const {
  return impl_->parent.size();
}
const std::string& Vocabulary::provenance() const {
  return impl_->provenance;
}

WordId Vocabulary::word(const Descriptor& descriptor) const {
  NodeId unused = 0;
  return impl_->node_word[impl_->descend(pack(descriptor), 0, unused)];
}

float Vocabulary::idf(WordId word) const {
  return word < impl_->word_node.size() ? impl_->weight[impl_->word_node[word]] : 0.0F;
}

void Vocabulary::transform(std::span<const Descriptor> descriptors, BowVector& bow, FeatureVector* features,
                           int direct_level) const {
  const Impl& m = *impl_;
  bow.clear();
  if (features != nullptr) features->clear();
  if (descriptors.empty()) return;
  const int level = std::clamp(direct_level, 0, m.levels);
  std::vector<WordId> words(descriptors.size());
  if (features != nullptr) features->reserve(std::min(descriptors.size(), kMaxFeatureIndex + 1));
  for (std::size_t i = 0; i < descriptors.size(); ++i) {
    NodeId at_level = 0;
    words[i] = m.node_word[m.descend(pack(descriptors[i]), level, at_level)];
    if (features != nullptr && i <= kMaxFeatureIndex) {
      features->push_back({at_level, static_cast<std::uint16_t>(i)});
    }
  }
  if (features != nullptr) {
    // Features are in ascending order already; a stable sort by node keeps them so within a node.
    std::stable_sort(features->begin(), features->end(),
                     [](const NodeFeature& a, const NodeFeature& b) { return a.node < b.node; });
  }

  // tf-idf: (occurrences / features) * idf, then L1 normalisation.
  std::sort(words.begin(), words.end());
  const double total_features = static_cast<double>(descriptors.size());
  std::vector<double> weights;
  weights.reserve(words.size());
  double sum = 0.0;
  for (std::size_t i = 0; i < words.size();) {
    std::size_t j = i;
    while (j < words.size() && words[j] == words[i]) ++j;
    const double w = static_cast<double>(j - i) / total_features * static_cast<double>(idf(words[i]));
    if (w > 0.0) {
      bow.push_back({words[i], 0.0F});
      weights.push_back(w);
      sum += w;
    }
    i = j;
  }
  if (!(sum > 0.0)) {
    bow.clear();
    return;
  }
  for (std::size_t i = 0; i < bow.size(); ++i) bow[i].weight = static_cast<float>(weights[i] / sum);
}

}  // namespace cvislam::features
