// The keyframe database of a mission (CVI-SLAM IV-A, after DBoW2's database): an inverted index from each
// vocabulary word to the keyframes that contain it, with their weights, over every keyframe of every map of the
// mission's stack. A query scores only the keyframes that share a word with it, restricted to one map (loop
// detection) or to every other map (map matching).
//
// Each keyframe's BoW vector and feature vector (the direct index) are kept here, so verification can match
// descriptors node by node without the vocabulary. Keyframes can be removed (redundancy removal) and moved to
// another map (a merge), and the index stays consistent (checkConsistency, for tests).
//
// Not thread-safe: the recognition worker owns it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/features/vocabulary.hpp"
#include "server_cloud/stack/map_content.hpp"

namespace cvislam::server::recognition {

struct DatabaseEntry {
  KeyframeId keyframe;
  MapId map = 0;
  features::BowVector bow;
  features::FeatureVector features;
};

struct BowCandidate {
  KeyframeId keyframe;
  MapId map = 0;
  double score = 0.0;    // bowScore with the query, in [0, 1]
  int common_words = 0;  // words both have
};

enum class QueryScope {
  kSameMap,    // loop detection: keyframes of `map` only
  kOtherMaps,  // map matching: keyframes of every map but `map`
};

struct DatabaseQuery {
  QueryScope scope = QueryScope::kSameMap;
  MapId map = 0;
  // Never returned (the query itself and its covisible neighbours, for loop detection). May be null.
  const std::unordered_set<KeyframeId>* exclude = nullptr;
  double min_score = 0.0;
  // Only keyframes sharing at least this fraction of the most words any keyframe in scope shares with the
  // query are scored (as ORB-SLAM does, to skip keyframes that share a handful of common words).
  double min_common_words_ratio = 0.8;
  std::size_t max_results = 50;  // the best by score
};

class KeyframeDatabase {
 public:
  // `word_count` is the vocabulary's; words outside it are a bug of the caller (asserted).
  explicit KeyframeDatabase(std::size_t word_count);

  // kAlreadyExists when the keyframe is held.
  Status add(const KeyframeId& keyframe, MapId map, features::BowVector bow, features::FeatureVector features);
  // kNotFound when the keyframe is not held.
  Status remove(const KeyframeId& keyframe);
  // Every keyframe of map `from` now belongs to map `to` (after a merge).
  void moveMap(MapId from, MapId to);

  [[nodiscard]] const DatabaseEntry* find(const KeyframeId& keyframe) const;
  // The best candidates by score, highest first (ties by keyframe id, so results are deterministic).
  [[nodiscard]] std::vector<BowCandidate> query(const features::BowVector& bow, const DatabaseQuery& query) const;

  [[nodiscard]] std::size_t size() const { return slots_by_keyframe_.size(); }
  // Heap bytes held (index, entries, their vectors), for the memory-per-keyframe figure.
  [[nodiscard]] std::size_t memoryBytes() const;
  // Every posting matches its entry's BoW vector and the other way round; for tests.
  [[nodiscard]] Status checkConsistency() const;

 private:
  struct Posting {
    std::uint32_t slot = 0;
    float weight = 0.0F;
  };
  std::vector<std::vector<Posting>> postings_;  // by word
  std::vector<DatabaseEntry> entries_;          // by slot; free slots have an empty bow and sit in free_slots_
  std::vector<std::uint8_t> used_;              // by slot
  std::vector<std::uint32_t> free_slots_;
  std::unordered_map<KeyframeId, std::uint32_t> slots_by_keyframe_;
};

}  // namespace cvislam::server::recognition
