// Mapping's backlog as tracking sees it: the keyframes tracking has published and mapping has not
// yet taken, and what tracking does about them. On a board with one free core mapping falls behind; tracking
// then keeps tracking on the newest snapshot with the IMU, makes a keyframe only when it would otherwise be
// lost (ORB-SLAM's "local mapping busy" rule), and never lets the backlog grow past a bound.
//
// Tracking numbers its keyframe messages 0, 1, 2, ...; mapping's snapshots say how many of them it has taken.
// A keyframe is pending from its publication until a snapshot counts it, or until answer_timeout_s has passed
// (mapping refused it, or has stopped): a lost answer must not stop keyframes for good.
//
// A keyframe held back for long is overdue: the map tracking searches falls behind the camera, and tracking asks
// mapping to cut its local BA short (ORB-SLAM's local mapping aborts its BA the same way). Only once it has been
// held back for yield_request_after_s of sequence time, so that a mapper that keeps up is never interrupted.
//
// Plain state on the stack of the tracker: no allocation, no clock of its own (callers pass steady-clock times).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

#include "common/core/result.hpp"

namespace cvislam::agent {

// What tracking does while mapping is behind (keyframes published and not yet answered by a snapshot).
struct MappingLagOptions {
  // While mapping is busy, a keyframe only when tracking would otherwise be lost (fewer than
  // min_tracked_points_when_busy tracked), and lost frames do not count towards a new map: tracking goes on with
  // the newest snapshot and the IMU until mapping answers. false: the keyframe rules ignore mapping.
  bool back_off = true;
  int min_tracked_points_when_busy = 15;  // the paper's keyframe threshold; ours is 30 with an idle mapper
  int max_pending_keyframes = 2;          // no keyframe while this many are unanswered: the backlog stays bounded
  // A keyframe unanswered for this long (wall clock) stops counting: mapping refused it or has stopped.
  double answer_timeout_s = 5.0;
  // Keyframes held back without a break for this long (sequence time, from the first one held back since the last
  // keyframe published) ask mapping to cut its local BA short. 0: at once, as ORB-SLAM does; a mapper that keeps
  // up would then be interrupted too, and realtime runs would no longer repeat --pace sync.
  double yield_request_after_s = 0.1;

  [[nodiscard]] Status validate() const;
};

// The backlog's state for one frame's decisions.
struct MappingPressure {
  int pending = 0;    // keyframes published and not yet answered
  bool busy = false;  // back-off on and something pending: keyframes only when needed, lost frames are not counted
  bool full = false;  // back-off on and max_pending_keyframes pending: no keyframe at all
};

// What to do with a keyframe the keyframe rules asked for.
struct KeyframeGate {
  bool publish = true;
  bool needs_mapping = false;  // deferred although tracking needed it: the caller should let mapping run
};

class MappingBacklog {
 public:
  // Publication times are kept for this many keyframes; max_pending_keyframes may be at most half of it.
  static constexpr std::size_t kCapacity = 64;

  explicit MappingBacklog(const MappingLagOptions& options) : options_(options) {}

  // Numbers the next keyframe message and records when it left (steady clock); returns its sequence number.
  std::uint64_t publish(std::int64_t steady_ns);
  // From a snapshot: mapping has taken this many keyframe messages (never goes backwards).
  void taken(std::uint64_t keyframes_taken);

  [[nodiscard]] std::uint64_t published() const { return next_sequence_; }
  [[nodiscard]] int pending(std::int64_t now_ns) const;
  [[nodiscard]] MappingPressure pressure(std::int64_t now_ns) const;
  // The rule for a keyframe the rules asked for, given how many map points the frame tracked.
  [[nodiscard]] KeyframeGate gate(const MappingPressure& pressure, int tracked_points) const;
  // A keyframe the rules asked for was held back at sequence time t_ns. True when keyframes have been held back
  // since at least yield_request_after_s before it (with no keyframe published in between): mapping should yield.
  bool heldBack(std::int64_t t_ns);

 private:
  MappingLagOptions options_;
  std::uint64_t next_sequence_ = 0;
  std::uint64_t taken_ = 0;
  std::array<std::int64_t, kCapacity> publish_steady_ns_{};  // by sequence modulo kCapacity
  bool holding_back_ = false;                                // a keyframe was held back since the last one published
  std::int64_t held_back_since_ns_ = 0;                      // sequence time of the first of them
};

}  // namespace cvislam::agent
