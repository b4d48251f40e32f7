// The keyframe database: add, query by scope, exclusion and score, remove and move keyframes between maps, with
// the inverted index checked against the entries after every change.
#include "server_cloud/recognition/keyframe_database.hpp"

#include <random>
#include <unordered_set>

#include <gtest/gtest.h>

namespace cvislam::server::recognition {
namespace {

// An L1-normalised BoW vector with equal weights over the given words.
features::BowVector bowOf(std::vector<features::WordId> words) {
  std::sort(words.begin(), words.end());
  words.erase(std::unique(words.begin(), words.end()), words.end());
  features::BowVector bow;
  for (const features::WordId w : words) bow.push_back({w, 1.0F / static_cast<float>(words.size())});
  return bow;
}

KeyframeId kf(AgentId agent, std::uint32_t counter) {
  return KeyframeId{agent, counter};
}

TEST(KeyframeDatabase, ScoresOnlyTheSharedWordsAndRanksByScore) {
  KeyframeDatabase db(100);
  ASSERT_TRUE(db.add(kf(0, 0), 0, bowOf({1, 2, 3, 4}), {}).ok());
  ASSERT_TRUE(db.add(kf(0, 1), 0, bowOf({1, 2, 3, 9}), {}).ok());
  ASSERT_TRUE(db.add(kf(0, 2), 0, bowOf({1, 7, 8, 9}), {}).ok());
  ASSERT_TRUE(db.add(kf(0, 3), 0, bowOf({50, 51}), {}).ok());
  ASSERT_TRUE(db.checkConsistency().ok());

  DatabaseQuery q;
  q.min_common_words_ratio = 0.0;
  const auto out = db.query(bowOf({1, 2, 3, 4}), q);
  ASSERT_EQ(out.size(), 3U);  // kf 3 shares no word
  EXPECT_EQ(out[0].keyframe, kf(0, 0));
  EXPECT_NEAR(out[0].score, 1.0, 1e-6);
  EXPECT_EQ(out[1].keyframe, kf(0, 1));
  EXPECT_NEAR(out[1].score, 0.75, 1e-6);
  EXPECT_EQ(out[1].common_words, 3);
  EXPECT_NEAR(out[2].score, 0.25, 1e-6);

  // The score is the L1 score the vocabulary defines.
  EXPECT_NEAR(out[1].score, features::bowScore(bowOf({1, 2, 3, 4}), bowOf({1, 2, 3, 9})), 1e-6);

  q.min_score = 0.5;
  EXPECT_EQ(db.query(bowOf({1, 2, 3, 4}), q).size(), 2U);
  q.min_score = 0.0;
  q.min_common_words_ratio = 0.8;  // at least 0.8 * 4 shared words
  EXPECT_EQ(db.query(bowOf({1, 2, 3, 4}), q).size(), 1U);
}

TEST(KeyframeDatabase, ScopesSameMapOrOtherMapsAndExcludes) {
  KeyframeDatabase db(100);
  ASSERT_TRUE(db.add(kf(0, 0), 0, bowOf({1, 2}), {}).ok());
  ASSERT_TRUE(db.add(kf(0, 1), 0, bowOf({1, 2}), {}).ok());
  ASSERT_TRUE(db.add(kf(1, 0), 1, bowOf({1, 2}), {}).ok());
  ASSERT_TRUE(db.add(kf(2, 0), 2, bowOf({1, 2}), {}).ok());

  DatabaseQuery q;
  q.map = 0;
  q.scope = QueryScope::kSameMap;
  const std::unordered_set<KeyframeId> exclude{kf(0, 1)};
  q.exclude = &exclude;
  auto out = db.query(bowOf({1, 2}), q);
  ASSERT_EQ(out.size(), 1U);
  EXPECT_EQ(out[0].keyframe, kf(0, 0));

  q.scope = QueryScope::kOtherMaps;
  out = db.query(bowOf({1, 2}), q);
  ASSERT_EQ(out.size(), 2U);
  EXPECT_EQ(out[0].map + out[1].map, 3U);

  // A merge moves map 2 into map 1: map matching from map 1 no longer sees it, loop detection in map 1 does.
  db.moveMap(2, 1);
  q.map = 1;
  q.exclude = nullptr;
  out = db.query(bowOf({1, 2}), q);
  ASSERT_EQ(out.size(), 2U);
  for (const auto& c : out) EXPECT_EQ(c.map, 0U);
  q.scope = QueryScope::kSameMap;
  EXPECT_EQ(db.query(bowOf({1, 2}), q).size(), 2U);
}

TEST(KeyframeDatabase, RemoveKeepsTheIndexConsistentAndReusesSlots) {
  std::mt19937_64 rng(42);
  std::uniform_int_distribution<features::WordId> word(0, 999);
  KeyframeDatabase db(1000);
  for (std::uint32_t i = 0; i < 200; ++i) {
    std::vector<features::WordId> words;
    for (int k = 0; k < 60; ++k) words.push_back(word(rng));
    ASSERT_TRUE(db.add(kf(1, i), i % 3, bowOf(words), {}).ok());
  }
  ASSERT_TRUE(db.checkConsistency().ok());
  const std::size_t full_memory = db.memoryBytes();
  for (std::uint32_t i = 0; i < 200; i += 2) ASSERT_TRUE(db.remove(kf(1, i)).ok());
  EXPECT_EQ(db.size(), 100U);
  ASSERT_TRUE(db.checkConsistency().ok()) << db.checkConsistency().error().message();
  EXPECT_EQ(db.find(kf(1, 4)), nullptr);
  ASSERT_NE(db.find(kf(1, 5)), nullptr);

  // A removed keyframe is never returned; the others still are, with their full score.
  DatabaseQuery q;
  q.min_common_words_ratio = 0.0;
  q.max_results = 1000;
  for (const MapId map : {0U, 1U, 2U}) {
    q.map = map;
    for (const auto& c : db.query(db.find(kf(1, 5))->bow, q)) EXPECT_EQ(c.keyframe.counter % 2, 1U);
  }
  q.map = 5 % 3;
  const auto out = db.query(db.find(kf(1, 5))->bow, q);
  ASSERT_FALSE(out.empty());
  EXPECT_EQ(out[0].keyframe, kf(1, 5));
  EXPECT_NEAR(out[0].score, 1.0, 1e-5);

  // Freed slots are reused: adding back as many keyframes does not grow the memory.
  for (std::uint32_t i = 0; i < 200; i += 2) {
    std::vector<features::WordId> words;
    for (int k = 0; k < 60; ++k) words.push_back(word(rng));
    ASSERT_TRUE(db.add(kf(2, i), 0, bowOf(words), {}).ok());
  }
  ASSERT_TRUE(db.checkConsistency().ok());
  EXPECT_LE(db.memoryBytes(), full_memory + full_memory / 5);
}

TEST(KeyframeDatabase, RefusesDuplicatesAndUnknownRemovals) {
  KeyframeDatabase db(10);
  ASSERT_TRUE(db.add(kf(0, 0), 0, bowOf({1}), {}).ok());
  const Status dup = db.add(kf(0, 0), 0, bowOf({2}), {});
  ASSERT_FALSE(dup.ok());
  EXPECT_EQ(dup.error().code(), ErrorCode::kAlreadyExists);
  const Status missing = db.remove(kf(0, 9));
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code(), ErrorCode::kNotFound);
  EXPECT_NE(missing.error().message().find("0:9"), std::string::npos);
  EXPECT_TRUE(db.checkConsistency().ok());
}

}  // namespace
}  // namespace cvislam::server::recognition
