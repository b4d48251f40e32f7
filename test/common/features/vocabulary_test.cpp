// The ORB vocabulary: deterministic training (for a seed, whatever the thread count), the file (words and BoW
// vectors survive save and load; damaged files are refused, naming the file and the problem), the BoW and feature
// vectors' invariants, bowScore, and place recognition on real EuRoC V1_01 frames.
#include "common/features/vocabulary.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iterator>
#include <map>
#include <random>
#include <set>
#include <string>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "common/core/hash.hpp"
#include "common/dataset/euroc.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::features {
namespace {

using ::testing::HasSubstr;

// Descriptors around `prototypes` random centres, each with about 1 bit in `flip_one_in` flipped; one vector per
// image, each image drawing from a random subset of the centres (so that idf has something to tell apart).
std::vector<std::vector<Descriptor>> clusteredImages(std::uint64_t seed, int images, int per_image, int prototypes,
                                                     int flip_one_in = 16) {
  std::mt19937_64 rng(seed);
  std::vector<Descriptor> centres(static_cast<std::size_t>(prototypes));
  for (Descriptor& c : centres) {
    for (std::uint8_t& byte : c) byte = static_cast<std::uint8_t>(rng() & 0xFFU);
  }
  std::vector<std::vector<Descriptor>> out(static_cast<std::size_t>(images));
  for (auto& image : out) {
    const std::size_t first = rng() % centres.size();
    for (int i = 0; i < per_image; ++i) {
      Descriptor d = centres[(first + rng() % (centres.size() / 3 + 1)) % centres.size()];
      for (int bit = 0; bit < 256; ++bit) {
        if (rng() % static_cast<std::uint64_t>(flip_one_in) == 0)
          d[bit / 8] ^= static_cast<std::uint8_t>(1U << (bit % 8));
      }
      image.push_back(d);
    }
  }
  return out;
}

// 40 x 120 = 4800 descriptors: more than the 4096 above which a node's assignment step runs on several threads.
constexpr int kImages = 40;

VocabularyTrainingOptions smallOptions(int threads = 1) {
  VocabularyTrainingOptions options;
  options.branching = 4;
  options.levels = 4;
  options.seed = 5;
  options.threads = threads;
  return options;
}

std::string readBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

void writeBytes(const std::filesystem::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

// The file's checksum (FNV-1a 64 of everything before it), recomputed after a test edits the file on purpose.
void resealChecksum(std::string& bytes) {
  const std::uint64_t hash = fnv1a64(std::string_view(bytes).substr(0, bytes.size() - 8));
  for (std::size_t i = 0; i < 8; ++i) bytes[bytes.size() - 8 + i] = static_cast<char>((hash >> (8 * i)) & 0xFFU);
}

void putU32(std::string& bytes, std::size_t at, std::uint32_t v) {
  for (std::size_t i = 0; i < 4; ++i) bytes[at + i] = static_cast<char>((v >> (8 * i)) & 0xFFU);
}

// Where the header fields and the nodes start (see vocabulary.cpp for the layout).
struct Layout {
  std::size_t version = 10;
  std::size_t k = 0;
  std::size_t nodes = 0;
};
Layout layoutOf(const Vocabulary& v) {
  Layout l;
  l.k = 10 + 4 + 4 + v.provenance().size();
  l.nodes = l.k + 12;
  return l;
}

Vocabulary trainSmall(int threads = 1, std::string provenance = "unit test") {
  auto v = Vocabulary::train(clusteredImages(11, kImages, 120, 60), smallOptions(threads), std::move(provenance));
  EXPECT_TRUE(v.ok()) << v.error().toString();
  return std::move(v).value();
}

TEST(Vocabulary, TrainingIsDeterministicAndIndependentOfTheThreadCount) {
  cvislam::test::TempDir dir;
  std::vector<std::string> files;
  for (int threads : {1, 1, 2, 3}) {
    const Vocabulary v = trainSmall(threads);
    const auto path = dir / ("v" + std::to_string(files.size()) + ".cvvoc");
    ASSERT_TRUE(v.save(path).ok());
    files.push_back(readBytes(path));
  }
  ASSERT_GT(files.front().size(), 1000u);
  for (std::size_t i = 1; i < files.size(); ++i) EXPECT_EQ(files[i], files.front()) << "training " << i;

  // Another seed gives another tree.
  VocabularyTrainingOptions other = smallOptions();
  other.seed = 6;
  auto v = Vocabulary::train(clusteredImages(11, kImages, 120, 60), other, "unit test");
  ASSERT_TRUE(v.ok());
  ASSERT_TRUE(v->save(dir / "other.cvvoc").ok());
  EXPECT_NE(readBytes(dir / "other.cvvoc"), files.front());
}

TEST(Vocabulary, TreeHasTheRequestedShape) {
  const Vocabulary v = trainSmall();
  EXPECT_EQ(v.branching(), 4);
  EXPECT_EQ(v.levels(), 4);
  EXPECT_EQ(v.provenance(), "unit test");
  // 4800 descriptors: a full tree of 4^4 = 256 words is possible; the clusters give many, not all.
  EXPECT_GT(v.wordCount(), 60u);
  EXPECT_LE(v.wordCount(), 256u);
  EXPECT_GT(v.nodeCount(), v.wordCount());
  EXPECT_LE(v.nodeCount(), 1u + 4u + 16u + 64u + 256u);
  for (WordId w = 0; w < v.wordCount(); ++w) {
    EXPECT_GE(v.idf(w), 0.0F);
    EXPECT_LE(v.idf(w), static_cast<float>(std::log(static_cast<double>(kImages))) + 1e-5F);
  }
  EXPECT_EQ(v.idf(static_cast<WordId>(v.wordCount())), 0.0F);  // no such word
}

TEST(Vocabulary, FewDescriptorsGiveARootThatIsTheOnlyWord) {
  std::vector<std::vector<Descriptor>> images = clusteredImages(3, 2, 2, 4);  // 4 descriptors <= k
  auto v = Vocabulary::train(images, smallOptions(), "");
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(v->nodeCount(), 1u);
  EXPECT_EQ(v->wordCount(), 1u);
  EXPECT_EQ(v->word(images[0][0]), 0u);

  // All descriptors alike: k-means cannot split them, the root stays the only word.
  std::vector<std::vector<Descriptor>> same(3, std::vector<Descriptor>(50, images[0][0]));
  auto w = Vocabulary::train(same, smallOptions(), "");
  ASSERT_TRUE(w.ok());
  EXPECT_EQ(w->wordCount(), 1u);
}

TEST(Vocabulary, TrainingRefusesNoDataAndBadOptions) {
  auto none = Vocabulary::train({{}, {}}, smallOptions(), "");
  ASSERT_FALSE(none.ok());
  EXPECT_THAT(none.error().message(), HasSubstr("no descriptors"));
  VocabularyTrainingOptions bad = smallOptions();
  bad.branching = 1;
  auto refused = Vocabulary::train(clusteredImages(1, 2, 20, 4), bad, "");
  ASSERT_FALSE(refused.ok());
  EXPECT_THAT(refused.error().message(), HasSubstr("branching"));
  bad = smallOptions();
  bad.levels = 0;
  EXPECT_THAT(bad.validate().error().message(), HasSubstr("levels"));
  bad = smallOptions();
  bad.threads = 0;
  EXPECT_THAT(bad.validate().error().message(), HasSubstr("threads"));
  bad = smallOptions();
  bad.max_iterations = 0;
  EXPECT_THAT(bad.validate().error().message(), HasSubstr("max_iterations"));
}

TEST(Vocabulary, WordsIdfAndVectorsSurviveSaveAndLoad) {
  cvislam::test::TempDir dir;
  const Vocabulary v = trainSmall(2, "made by a unit test\nsecond line: \xC3\xA9");
  ASSERT_TRUE(v.save(dir / "v.cvvoc").ok());
  auto loaded = Vocabulary::load(dir / "v.cvvoc");
  ASSERT_TRUE(loaded.ok()) << loaded.error().toString();
  EXPECT_EQ(loaded->provenance(), v.provenance());
  EXPECT_EQ(loaded->branching(), v.branching());
  EXPECT_EQ(loaded->levels(), v.levels());
  EXPECT_EQ(loaded->nodeCount(), v.nodeCount());
  EXPECT_EQ(loaded->wordCount(), v.wordCount());
  for (WordId w = 0; w < v.wordCount(); ++w) EXPECT_EQ(loaded->idf(w), v.idf(w));

  // Training descriptors and new ones from other centres.
  const auto images = clusteredImages(11, kImages, 120, 60);
  const auto fresh = clusteredImages(99, 5, 100, 20, 4);
  for (const auto* set : {&images, &fresh}) {
    for (const auto& image : *set) {
      for (const Descriptor& d : image) ASSERT_EQ(loaded->word(d), v.word(d));
      for (int level : {0, 2, 4}) {
        BowVector a;
        BowVector b;
        FeatureVector fa;
        FeatureVector fb;
        v.transform(image, a, &fa, level);
        loaded->transform(image, b, &fb, level);
        ASSERT_EQ(a.size(), b.size());
        for (std::size_t i = 0; i < a.size(); ++i) {
          EXPECT_EQ(a[i].word, b[i].word);
          EXPECT_EQ(a[i].weight, b[i].weight);
        }
        ASSERT_EQ(fa.size(), fb.size());
        for (std::size_t i = 0; i < fa.size(); ++i) {
          EXPECT_EQ(fa[i].node, fb[i].node);
          EXPECT_EQ(fa[i].feature, fb[i].feature);
        }
      }
    }
  }
  // Saving what was loaded writes the same bytes.
  ASSERT_TRUE(loaded->save(dir / "again.cvvoc").ok());
  EXPECT_EQ(readBytes(dir / "again.cvvoc"), readBytes(dir / "v.cvvoc"));
}

TEST(Vocabulary, BowVectorIsSortedL1NormalisedTfIdf) {
  const Vocabulary v = trainSmall();
  const auto images = clusteredImages(11, kImages, 120, 60);
  for (const auto& image : images) {
    BowVector bow;
    v.transform(image, bow, nullptr, 0);
    ASSERT_FALSE(bow.empty());
    double sum = 0.0;
    for (std::size_t i = 0; i < bow.size(); ++i) {
      if (i > 0) {
        EXPECT_LT(bow[i - 1].word, bow[i].word);  // sorted, each word once
      }
      EXPECT_GT(bow[i].weight, 0.0F);
      sum += static_cast<double>(bow[i].weight);
    }
    EXPECT_NEAR(sum, 1.0, 1e-5);
  }
  // tf-idf by hand for one image: count(w) * idf(w), normalised.
  std::map<WordId, double> expected;
  double total = 0.0;
  for (const Descriptor& d : images[3]) {
    const WordId w = v.word(d);
    expected[w] += static_cast<double>(v.idf(w));
    total += static_cast<double>(v.idf(w));
  }
  std::erase_if(expected, [](const auto& entry) { return entry.second == 0.0; });
  BowVector bow;
  v.transform(images[3], bow, nullptr, 0);
  ASSERT_EQ(bow.size(), expected.size());
  std::size_t i = 0;
  for (const auto& [word, weight] : expected) {
    EXPECT_EQ(bow[i].word, word);
    EXPECT_NEAR(static_cast<double>(bow[i].weight), weight / total, 1e-6);
    ++i;
  }
  // No descriptors: an empty vector.
  v.transform({}, bow, nullptr, 0);
  EXPECT_TRUE(bow.empty());
}

TEST(Vocabulary, BowScoreIsOneForItselfZeroForDisjointAndSymmetric) {
  const BowVector a = {{1, 0.5F}, {2, 0.5F}};
  const BowVector b = {{2, 0.25F}, {3, 0.75F}};
  const BowVector c = {{4, 1.0F}};
  EXPECT_DOUBLE_EQ(bowScore(a, a), 1.0);
  EXPECT_DOUBLE_EQ(bowScore(a, b), 0.25);  // 1 - (0.5 + 0.25 + 0.75) / 2
  EXPECT_DOUBLE_EQ(bowScore(b, a), 0.25);
  EXPECT_DOUBLE_EQ(bowScore(a, c), 0.0);
  EXPECT_DOUBLE_EQ(bowScore(a, {}), 0.0);
  EXPECT_DOUBLE_EQ(bowScore({}, {}), 0.0);

  const Vocabulary v = trainSmall();
  const auto images = clusteredImages(11, kImages, 120, 60);
  std::vector<BowVector> bows(images.size());
  for (std::size_t i = 0; i < images.size(); ++i) v.transform(images[i], bows[i], nullptr, 0);
  for (std::size_t i = 0; i < bows.size(); ++i) {
    EXPECT_NEAR(bowScore(bows[i], bows[i]), 1.0, 1e-5);
    for (std::size_t j = 0; j < bows.size(); ++j) {
      const double s = bowScore(bows[i], bows[j]);
      EXPECT_GE(s, 0.0);
      EXPECT_LE(s, 1.0);
      EXPECT_EQ(s, bowScore(bows[j], bows[i]));
      // The merge equals 1 - 0.5 * sum |a - b| over the union of words.
      std::map<WordId, std::pair<double, double>> both;
      for (const BowEntry& e : bows[i]) both[e.word].first = static_cast<double>(e.weight);
      for (const BowEntry& e : bows[j]) both[e.word].second = static_cast<double>(e.weight);
      double l1 = 0.0;
      for (const auto& [word, w] : both) l1 += std::abs(w.first - w.second);
      EXPECT_NEAR(s, 1.0 - 0.5 * l1, 1e-5);
    }
  }
}

TEST(Vocabulary, FeatureVectorNodesLieOnTheWordsPaths) {
  const Vocabulary v = trainSmall();
  const auto image = clusteredImages(11, kImages, 120, 60)[7];
  std::vector<FeatureVector> by_level;
  for (int level = 0; level <= v.levels(); ++level) {
    BowVector bow;
    FeatureVector features;
    v.transform(image, bow, &features, level);
    ASSERT_EQ(features.size(), image.size());
    std::set<std::uint16_t> seen;
    for (std::size_t i = 0; i < features.size(); ++i) {
      if (i > 0) {
        EXPECT_TRUE(features[i - 1].node < features[i].node ||
                    (features[i - 1].node == features[i].node && features[i - 1].feature < features[i].feature));
      }
      EXPECT_LT(features[i].node, v.nodeCount());
      seen.insert(features[i].feature);
    }
    EXPECT_EQ(seen.size(), image.size());  // every feature once
    // Node of each feature, by feature.
    FeatureVector by_feature = features;
    std::sort(by_feature.begin(), by_feature.end(),
              [](const NodeFeature& a, const NodeFeature& b) { return a.feature < b.feature; });
    by_level.push_back(by_feature);
  }
  // Level 0 is the root; level 1 nodes are the root's children (ids 1..k).
  for (const NodeFeature& f : by_level[0]) EXPECT_EQ(f.node, 0u);
  for (const NodeFeature& f : by_level[1]) {
    EXPECT_GE(f.node, 1u);
    EXPECT_LE(f.node, 4u);
  }
  // The node at each level is a function of the word (it lies on the word's path); each level refines the one above
  // (same node below means same node above); at level L the node is the word's leaf, one node per word.
  for (std::size_t level = 0; level < by_level.size(); ++level) {
    std::map<WordId, NodeId> node_of_word;
    std::map<NodeId, NodeId> parent_level_node;
    std::map<NodeId, std::set<WordId>> words_of_node;
    for (std::size_t i = 0; i < image.size(); ++i) {
      const WordId w = v.word(image[i]);
      const NodeId n = by_level[level][i].node;
      const auto [it, inserted] = node_of_word.emplace(w, n);
      EXPECT_EQ(it->second, n) << "word " << w << " at level " << level;
      words_of_node[n].insert(w);
      if (level > 0) {
        const auto [p, fresh] = parent_level_node.emplace(n, by_level[level - 1][i].node);
        EXPECT_EQ(p->second, by_level[level - 1][i].node);
        EXPECT_GE(n, by_level[level - 1][i].node);  // breadth-first: deeper nodes have larger ids
      }
    }
    if (level == by_level.size() - 1) {
      for (const auto& [node, words] : words_of_node) EXPECT_EQ(words.size(), 1u) << "leaf " << node;
    }
  }
  // direct_level is clamped to [0, L].
  BowVector bow;
  FeatureVector low;
  FeatureVector high;
  v.transform(image, bow, &low, -3);
  v.transform(image, bow, &high, 99);
  for (const NodeFeature& f : low) EXPECT_EQ(f.node, 0u);
  FeatureVector at_l;
  v.transform(image, bow, &at_l, v.levels());
  ASSERT_EQ(high.size(), at_l.size());
  for (std::size_t i = 0; i < high.size(); ++i) EXPECT_EQ(high[i].node, at_l[i].node);
}

class VocabularyFile : public ::testing::Test {
 protected:
  void SetUp() override {
    vocabulary_ = std::make_unique<Vocabulary>(trainSmall());
    ASSERT_TRUE(vocabulary_->save(dir_ / "good.cvvoc").ok());
    good_ = readBytes(dir_ / "good.cvvoc");
    layout_ = layoutOf(*vocabulary_);
  }

  // Loads `bytes` written as `name`; expects an error naming the file and containing `problem`.
  void expectRefused(const std::string& name, const std::string& bytes, const std::string& problem) {
    writeBytes(dir_ / name, bytes);
    auto loaded = Vocabulary::load(dir_ / name);
    ASSERT_FALSE(loaded.ok()) << name;
    EXPECT_THAT(loaded.error().message(), HasSubstr((dir_ / name).string())) << name;
    EXPECT_THAT(loaded.error().message(), HasSubstr(problem)) << name;
  }

  cvislam::test::TempDir dir_;
  std::unique_ptr<Vocabulary> vocabulary_;
  std::string good_;
  Layout layout_;
};

TEST_F(VocabularyFile, MissingFileIsNamed) {
  auto loaded = Vocabulary::load(dir_ / "absent.cvvoc");
  ASSERT_FALSE(loaded.ok());
  EXPECT_EQ(loaded.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(loaded.error().message(), HasSubstr("absent.cvvoc"));
  EXPECT_THAT(loaded.error().message(), HasSubstr("no such vocabulary file"));
}

TEST_F(VocabularyFile, TruncatedCorruptAndForeignFilesAreRefused) {
  expectRefused("empty.cvvoc", "", "truncated");
  expectRefused("magic_only.cvvoc", good_.substr(0, 12), "truncated");
  expectRefused("half.cvvoc", good_.substr(0, good_.size() / 2), "truncated");
  expectRefused("no_checksum.cvvoc", good_.substr(0, good_.size() - 3), "truncated");
  expectRefused("longer.cvvoc", good_ + "xyz", "3 unexpected bytes");
  expectRefused("text.cvvoc", "k: 10\nlevels: 5\n", "not a cvislam vocabulary");

  std::string flipped = good_;
  flipped[good_.size() / 2] = static_cast<char>(flipped[good_.size() / 2] ^ 0x10);
  expectRefused("flipped.cvvoc", flipped, "checksum mismatch");

  std::string version = good_;
  putU32(version, layout_.version, 2);
  expectRefused("v2.cvvoc", version, "format version 2; this build reads version 1");
}

TEST_F(VocabularyFile, InconsistentTreesAreRefused) {
  // Valid checksums over trees that are not: the checks behind the checksum.
  std::string parent_ahead = good_;
  putU32(parent_ahead, layout_.nodes + 5 * 40, 9);  // node 5's parent after it
  resealChecksum(parent_ahead);
  expectRefused("parent_ahead.cvvoc", parent_ahead, "inconsistent tree: node 5 has parent 9");

  std::string out_of_range = good_;
  putU32(out_of_range, layout_.nodes + 3 * 40, 0x7FFFFFFF);
  resealChecksum(out_of_range);
  expectRefused("out_of_range.cvvoc", out_of_range, "inconsistent tree: node 3 has parent 2147483647");

  std::string small_k = good_;
  putU32(small_k, layout_.k, 2);  // the root has 4 children
  resealChecksum(small_k);
  expectRefused("small_k.cvvoc", small_k, "more than k = 2 children");

  std::string shallow = good_;
  putU32(shallow, layout_.k + 4, 1);  // L = 1, but the tree is deeper
  resealChecksum(shallow);
  expectRefused("shallow.cvvoc", shallow, "deeper than L = 1");

  std::string two_roots = good_;
  putU32(two_roots, layout_.nodes + 40, 0xFFFFFFFFU);
  resealChecksum(two_roots);
  expectRefused("two_roots.cvvoc", two_roots, "inconsistent tree: node 1 has parent none");

  std::string bad_k = good_;
  putU32(bad_k, layout_.k, 0);
  resealChecksum(bad_k);
  expectRefused("bad_k.cvvoc", bad_k, "k = 0");

  std::string negative_weight = good_;
  const std::size_t last = vocabulary_->nodeCount() - 1;                 // breadth-first: the last node is a word
  putU32(negative_weight, layout_.nodes + last * 40 + 36, 0xBF800000U);  // -1.0f
  resealChecksum(negative_weight);
  expectRefused("negative_weight.cvvoc", negative_weight, "weight");
}

TEST_F(VocabularyFile, SaveIntoAMissingFolderNamesTheFile) {
  const Status st = vocabulary_->save(dir_ / "no/such/folder/v.cvvoc");
  ASSERT_FALSE(st.ok());
  EXPECT_THAT(st.error().message(), HasSubstr("no/such/folder/v.cvvoc"));
}

// Real images: frames next to each other share far more words than frames 4.5 s apart.
TEST(VocabularyEuroc, ConsecutiveFramesScoreHigherThanDistantOnes) {
  CVISLAM_REQUIRE_DATA(seq_path, "euroc-v101-excerpt");
  dataset::EurocReaderOptions reader;
  reader.require_imu = false;
  auto seq = dataset::EurocSequence::open(seq_path, reader);
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  auto extractor = OrbExtractor::create({});
  ASSERT_TRUE(extractor.ok());
  std::vector<Keypoint> keypoints(500);
  std::vector<Descriptor> buffer(500);
  const auto extract = [&](int camera, std::size_t frame) {
    auto image = seq->loadImage(camera, frame);
    EXPECT_TRUE(image.ok());
    const int n = extractor->extract(image->pixels, image->width, image->height, keypoints, buffer);
    return std::vector<Descriptor>(buffer.begin(), buffer.begin() + n);
  };
  // Train on every 4th frame of cam1 (the test frames come from cam0, so they are unseen).
  std::vector<std::vector<Descriptor>> training;
  for (std::size_t f = 0; f < seq->cam1()->frames.size(); f += 4) training.push_back(extract(1, f));
  VocabularyTrainingOptions options;
  options.levels = 4;
  options.seed = 1;
  auto v = Vocabulary::train(training, options, "V1_01 excerpt cam1 every 4th frame");
  ASSERT_TRUE(v.ok()) << v.error().toString();

  const std::size_t frames = seq->cam0().frames.size();
  ASSERT_GE(frames, 95u);
  std::vector<BowVector> bows(frames);
  for (std::size_t f = 0; f < frames; f += 1) {
    if (f % 10 > 1 && f != 90 && f != 91) continue;  // frames 0, 1, 10, 11, ..., 90, 91
    v->transform(extract(0, f), bows[f], nullptr, 0);
  }
  // The excerpt's first 2.5 s swing back and forth over one view (frames 0-51 score about 0.6 with each other) and
  // its motion blurs some frames (20-21 score 0.43), so single pairs are compared with a margin and the rest on
  // average: consecutive frames against frames at least 3 s apart (about 0.3, the level of unrelated views of a
  // room this vocabulary was trained in).
  EXPECT_GT(bowScore(bows[0], bows[1]), 1.5 * bowScore(bows[0], bows[90]));
  EXPECT_GT(bowScore(bows[90], bows[91]), 1.2 * bowScore(bows[0], bows[90]));
  double near = 0.0;
  double far = 0.0;
  int far_pairs = 0;
  for (std::size_t a = 0; a <= 90; a += 10) {
    near += bowScore(bows[a], bows[a + 1]) / 10.0;
    for (std::size_t b = a + 60; b <= 90; b += 10) {
      far += bowScore(bows[a], bows[b]) + bowScore(bows[a + 1], bows[b + 1]);
      far_pairs += 2;
    }
  }
  far /= far_pairs;
  EXPECT_GT(near, 1.3 * far);
  RecordProperty("mean_consecutive_score", std::to_string(near));
  RecordProperty("mean_far_score", std::to_string(far));
}

}  // namespace
}  // namespace cvislam::features
