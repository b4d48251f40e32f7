#include "agent_rt/tracking/mapping_backlog.hpp"

#include <algorithm>
#include <cmath>
#include <string>

namespace cvislam::agent {

Status MappingLagOptions::validate() const {
  constexpr int kMaxPending = static_cast<int>(MappingBacklog::kCapacity) / 2;
  if (max_pending_keyframes < 1 || max_pending_keyframes > kMaxPending) {
    return Error{ErrorCode::kInvalidArgument,
                 "tracker: lag.max_pending_keyframes = " + std::to_string(max_pending_keyframes) + " must be in [1, " +
                     std::to_string(kMaxPending) + "]"};
  }
  if (min_tracked_points_when_busy < 0) {
    return Error{ErrorCode::kInvalidArgument, "tracker: lag.min_tracked_points_when_busy must be >= 0"};
  }
  if (!(answer_timeout_s > 0.0) || !std::isfinite(answer_timeout_s)) {
    return Error{ErrorCode::kInvalidArgument, "tracker: lag.answer_timeout_s must be > 0"};
  }
  if (!(yield_request_after_s >= 0.0) || !std::isfinite(yield_request_after_s)) {
    return Error{ErrorCode::kInvalidArgument,
                 "tracker: lag.yield_request_after_s must be a finite number of seconds >= 0 (0: ask at once)"};
  }
  return Status::Ok();
}

std::uint64_t MappingBacklog::publish(std::int64_t steady_ns) {
  publish_steady_ns_[next_sequence_ % kCapacity] = steady_ns;
  holding_back_ = false;
  return next_sequence_++;
}

void MappingBacklog::taken(std::uint64_t keyframes_taken) {
  taken_ = std::max(taken_, keyframes_taken);
}

int MappingBacklog::pending(std::int64_t now_ns) const {
  const auto timeout_ns = static_cast<std::int64_t>(options_.answer_timeout_s * 1e9);
  // Older than the ring: long past any timeout a valid configuration allows to matter.
  const std::uint64_t first = std::max(taken_, next_sequence_ > kCapacity ? next_sequence_ - kCapacity : 0);
  int count = 0;
  for (std::uint64_t q = first; q < next_sequence_; ++q) {
    if (now_ns - publish_steady_ns_[q % kCapacity] < timeout_ns) ++count;
  }
  return count;
}

MappingPressure MappingBacklog::pressure(std::int64_t now_ns) const {
  MappingPressure p;
  p.pending = pending(now_ns);
  p.busy = options_.back_off && p.pending > 0;
  p.full = options_.back_off && p.pending >= options_.max_pending_keyframes;
  return p;
}

KeyframeGate MappingBacklog::gate(const MappingPressure& pressure, int tracked_points) const {
  const bool needed = tracked_points < options_.min_tracked_points_when_busy;
  KeyframeGate g;
  if (pressure.full || (pressure.busy && !needed)) {
    g.publish = false;
    g.needs_mapping = needed;
  }
  return g;
}

bool MappingBacklog::heldBack(std::int64_t t_ns) {
  if (!holding_back_) {
    holding_back_ = true;
    held_back_since_ns_ = t_ns;
  }
  return t_ns - held_back_since_ns_ >= std::llround(options_.yield_request_after_s * 1e9);
}

}  // namespace cvislam::agent
