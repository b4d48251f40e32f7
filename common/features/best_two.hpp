// The nearest and second-nearest candidate by descriptor distance, for Lowe's ratio test. Every descriptor
// search (frame to frame, map to frame by projection, stereo and keyframe pairs, place recognition) keeps
// these two while it scans its candidates; each applies its own acceptance test to them.
#pragma once

#include <limits>

namespace cvislam::features {

template <typename Candidate>
struct BestTwo {
  // `worst`: the distance no candidate reaches (the default accepts any distance).
  explicit BestTwo(int worst = std::numeric_limits<int>::max(), Candidate none = Candidate{})
      : best(worst), second(worst), candidate(none), worst_(worst) {}

  // A strictly closer candidate replaces the best (which becomes the second); ties keep the first seen.
  void offer(int distance, Candidate c) {
    if (distance < best) {
      second = best;
      best = distance;
      candidate = c;
    } else if (distance < second) {
      second = distance;
    }
  }
  // Whether a second candidate was seen at all (without one the ratio test has nothing to compare with).
  [[nodiscard]] bool hasSecond() const { return second != worst_; }

  int best;
  int second;
  Candidate candidate;  // of `best`

 private:
  int worst_;
};

}  // namespace cvislam::features
