#include "server_cloud/recognition/keyframe_database.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include "common/core/check.hpp"

namespace cvislam::server::recognition {

KeyframeDatabase::KeyframeDatabase(std::size_t word_count) : postings_(word_count) {}

Status KeyframeDatabase::add(const KeyframeId& keyframe, MapId map, features::BowVector bow,
                             features::FeatureVector features) {
  if (slots_by_keyframe_.contains(keyframe)) {
    return Error(ErrorCode::kAlreadyExists, "keyframe " + keyframe.toString() + " is already in the database");
  }
  std::uint32_t slot = 0;
  if (!free_slots_.empty()) {
    slot = free_slots_.back();
    free_slots_.pop_back();
  } else {
    slot = static_cast<std::uint32_t>(entries_.size());
    entries_.emplace_back();
    used_.push_back(0);
  }
  for (const features::BowEntry& e : bow) {
    CVISLAM_CHECK(e.word < postings_.size(), "a word outside the vocabulary");
    postings_[e.word].push_back(Posting{slot, e.weight});
  }
  entries_[slot] = DatabaseEntry{keyframe, map, std::move(bow), std::move(features)};
  used_[slot] = 1;
  slots_by_keyframe_.emplace(keyframe, slot);
  return {};
}

Status KeyframeDatabase::remove(const KeyframeId& keyframe) {
  const auto it = slots_by_keyframe_.find(keyframe);
  if (it == slots_by_keyframe_.end()) {
    return Error(ErrorCode::kNotFound, "keyframe " + keyframe.toString() + " is not in the database");
  }
  const std::uint32_t slot = it->second;
  DatabaseEntry& entry = entries_[slot];
  for (const features::BowEntry& e : entry.bow) {
    std::vector<Posting>& list = postings_[e.word];
    const auto p = std::find_if(list.begin(), list.end(), [slot](const Posting& q) { return q.slot == slot; });
    CVISLAM_CHECK(p != list.end(), "a posting to remove that the list does not hold");
    *p = list.back();  // order inside a posting list does not matter
    list.pop_back();
  }
  entry = DatabaseEntry{};
  used_[slot] = 0;
  free_slots_.push_back(slot);
  slots_by_keyframe_.erase(it);
  return {};
}

void KeyframeDatabase::moveMap(MapId from, MapId to) {
  for (std::size_t slot = 0; slot < entries_.size(); ++slot) {
    if (used_[slot] != 0 && entries_[slot].map == from) entries_[slot].map = to;
  }
}

const DatabaseEntry* KeyframeDatabase::find(const KeyframeId& keyframe) const {
  const auto it = slots_by_keyframe_.find(keyframe);
  return it == slots_by_keyframe_.end() ? nullptr : &entries_[it->second];
}

std::vector<BowCandidate> KeyframeDatabase::query(const features::BowVector& bow, const DatabaseQuery& query) const {
  // For L1-normalised vectors, 1 - 0.5 sum |a - b| = sum over the common words of min(a, b): only the postings
  // of the query's words contribute.
  std::vector<float> score(entries_.size(), 0.0F);
  std::vector<int> common(entries_.size(), 0);
  std::vector<std::uint32_t> touched;
  const auto in_scope = [&](MapId map) {
    return query.scope == QueryScope::kSameMap ? map == query.map : map != query.map;
  };
  for (const features::BowEntry& e : bow) {
    if (e.word >= postings_.size()) continue;
    for (const Posting& p : postings_[e.word]) {
      if (!in_scope(entries_[p.slot].map)) continue;
      if (common[p.slot] == 0) touched.push_back(p.slot);
      ++common[p.slot];
      score[p.slot] += std::min(e.weight, p.weight);
    }
  }
  const auto excluded = [&](std::uint32_t slot) {
    return query.exclude != nullptr && query.exclude->contains(entries_[slot].keyframe);
  };
  int most_common = 0;
  for (const std::uint32_t slot : touched) {
    if (!excluded(slot)) most_common = std::max(most_common, common[slot]);
  }
  const int min_common =
      static_cast<int>(std::ceil(query.min_common_words_ratio * static_cast<double>(most_common) - 1e-9));
  std::vector<BowCandidate> out;
  for (const std::uint32_t slot : touched) {
    if (excluded(slot) || common[slot] < min_common) continue;
    const double s = static_cast<double>(score[slot]);
    if (s < query.min_score) continue;
    out.push_back(BowCandidate{entries_[slot].keyframe, entries_[slot].map, s, common[slot]});
  }
  std::sort(out.begin(), out.end(), [](const BowCandidate& a, const BowCandidate& b) {
    return a.score != b.score ? a.score > b.score : a.keyframe < b.keyframe;
  });
  if (out.size() > query.max_results) out.resize(query.max_results);
  return out;
}

std::size_t KeyframeDatabase::memoryBytes() const {
  std::size_t bytes = postings_.capacity() * sizeof(std::vector<Posting>);
  for (const std::vector<Posting>& list : postings_) bytes += list.capacity() * sizeof(Posting);
  bytes += entries_.capacity() * sizeof(DatabaseEntry) + used_.capacity() + free_slots_.capacity() * 4;
  for (const DatabaseEntry& e : entries_) {
    bytes += e.bow.capacity() * sizeof(features::BowEntry) + e.features.capacity() * sizeof(features::NodeFeature);
  }
  // An unordered_map node holds the pair and a next pointer (and the cached hash in libstdc++); plus buckets.
  bytes += slots_by_keyframe_.size() * (sizeof(std::pair<const KeyframeId, std::uint32_t>) + 2 * sizeof(void*)) +
           slots_by_keyframe_.bucket_count() * sizeof(void*);
  return bytes;
}

Status KeyframeDatabase::checkConsistency() const {
  std::size_t postings = 0;
  for (std::size_t word = 0; word < postings_.size(); ++word) {
    for (const Posting& p : postings_[word]) {
      if (p.slot >= entries_.size() || used_[p.slot] == 0) {
        return Error(ErrorCode::kInternal, "word " + std::to_string(word) + " lists a free slot");
      }
      const features::BowVector& bow = entries_[p.slot].bow;
      const auto e = std::lower_bound(bow.begin(), bow.end(), word,
                                      [](const features::BowEntry& a, std::size_t w) { return a.word < w; });
      if (e == bow.end() || e->word != word || e->weight != p.weight) {
        return Error(ErrorCode::kInternal, "word " + std::to_string(word) + " lists keyframe " +
                                               entries_[p.slot].keyframe.toString() + " without that word");
      }
      ++postings;
    }
  }
  std::size_t words = 0;
  for (const auto& [keyframe, slot] : slots_by_keyframe_) {
    if (slot >= entries_.size() || used_[slot] == 0 || entries_[slot].keyframe != keyframe) {
      return Error(ErrorCode::kInternal, "keyframe " + keyframe.toString() + " points at a wrong slot");
    }
    words += entries_[slot].bow.size();
  }
  if (words != postings) {
    return Error(ErrorCode::kInternal,
                 std::to_string(words) + " words in the entries but " + std::to_string(postings) + " postings");
  }
  return {};
}

}  // namespace cvislam::server::recognition
