// Tracking asks mapping to cut its local BA short: when keyframes have been held back for long
// (FrameResult::keyframe_overdue), the map tracking searches falls behind the camera, and a BA that finishes its
// iterations only delays the keyframe tracking needs. ORB-SLAM's tracking sets its local mapper's abort flag for
// the same reason.
//
// A counter that only tracking increments and only mapping reads: mapping notes it when it takes a keyframe, and
// a request after that makes its local BA yield as a keyframe already queued does (MapperOptions::
// yield_to_waiting_keyframes). Lock-free, since the BA polls it from a Ceres iteration callback. Plain C++, so that
// tests use it without iceoryx.
#pragma once

#include <atomic>
#include <cstdint>

namespace cvislam::agent {

class YieldRequests {
 public:
  // Tracking's side.
  void request() { count_.fetch_add(1, std::memory_order_relaxed); }

  // Mapping's side: a keyframe was taken; requests from now on count.
  void keyframeTaken() { seen_ = count_.load(std::memory_order_relaxed); }
  // Whether tracking asked since the last keyframeTaken().
  [[nodiscard]] bool askedSinceKeyframeTaken() const { return count_.load(std::memory_order_relaxed) != seen_; }
  [[nodiscard]] std::uint64_t requests() const { return count_.load(std::memory_order_relaxed); }

 private:
  std::atomic<std::uint64_t> count_{0};
  std::uint64_t seen_ = 0;  // mapping's own
};

}  // namespace cvislam::agent
