// The depths of the agent's iceoryx channels and the message pools they need (see ChannelDepths). Plain C++, so
// that tests and the pool set-up read the same numbers without iceoryx headers.
#pragma once

#include <algorithm>
#include <cstdint>

#include "agent_rt/tracking/mapping_backlog.hpp"

namespace cvislam::agent {

// How deep each channel's subscriber queue is, and so how many chunks its message pool needs: the queue, plus
// the samples the reader holds, plus the writer's loan, plus one spare. A chunk is as large as its message (a
// keyframe carries the right image: 0.4 MB at EuRoC size; a snapshot 0.7 MB), and RouDi touches every chunk of a
// pool when it starts, so each one is resident for the agent's whole life.
struct ChannelDepths {
  // Mapping's keyframe queue. With the back-off, tracking keeps at most lag.max_pending_keyframes unanswered
  // (until answer_timeout_s): twice that, and 8 at least. Without it the backlog is not bounded: 32, and beyond
  // that the oldest keyframe is dropped (mapping counts the gap).
  std::uint32_t keyframes = 32;
  std::uint32_t snapshots = 8;  // tracking's queue; tracking drains it every frame and adopts each one in order
  std::uint32_t deltas = 16;    // the link's queue of map deltas
  std::uint32_t anchors = 8;    // mapping's queue of downlink messages

  static ChannelDepths forLag(const MappingLagOptions& lag) {
    ChannelDepths d;
    if (lag.back_off)
      d.keyframes = std::max<std::uint32_t>(8, 2 * static_cast<std::uint32_t>(lag.max_pending_keyframes));
    return d;
  }
  [[nodiscard]] std::uint32_t keyframeChunks() const { return keyframes + 3; }  // mapping holds 1, tracking loans 1
  [[nodiscard]] std::uint32_t snapshotChunks() const { return snapshots + 4; }  // tracking holds 2, mapping loans 1
  [[nodiscard]] std::uint32_t deltaChunks() const { return deltas + 3; }        // the link holds 1, mapping loans 1
  [[nodiscard]] std::uint32_t anchorChunks() const { return anchors + 3; }      // mapping holds 1, the link loans 1
};

}  // namespace cvislam::agent
