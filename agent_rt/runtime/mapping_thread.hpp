// The agent's mapping thread: takes tracking's keyframes from iceoryx, applies what the server sent down (the
// link's `anchors` topic) between them, runs the mapper, and publishes the map snapshot for tracking and the
// delta for the link. Its counters (MappingStats) go into the agent's summary.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/runtime/agent.hpp"
#include "agent_rt/runtime/latency_profile.hpp"
#include "agent_rt/runtime/yield_requests.hpp"

namespace iox::popo {
class UserTrigger;
}  // namespace iox::popo

namespace cvislam::agent {

struct MappingStats {
  std::size_t keyframes = 0;
  std::uint64_t lost_messages = 0;
  double imu_initialised_at_s = -1.0;
  std::size_t new_maps = 0;
  // What the server sent down, as mapping applied it.
  std::size_t downlink_messages = 0;
  std::size_t downlink_stale = 0;
  std::size_t downlink_refused = 0;
  std::size_t downlink_skipped = 0;  // the covisible map was in another agent map, or the map was not ready
  std::string downlink_last_skip;
  std::size_t anchors_added = 0;
  std::size_t anchors_released = 0;
  int most_anchors_held = 0;
  std::size_t anchor_points_added = 0;
  std::size_t anchor_points_linked = 0;
  std::size_t anchor_updates = 0;
  std::size_t over_capacity = 0;
  std::size_t unknown_references = 0;
  std::size_t corrections_applied = 0;
  std::size_t corrections_deferred = 0;
  std::size_t corrections_skipped = 0;
  double largest_correction_m = 0.0;
  double largest_correction_deg = 0.0;
  std::size_t ba_with_anchors = 0;  // local BAs in which anchors' observations took part
  // Mapping behind (MapperOptions::yield_to_waiting_keyframes): local BAs left out, and cut short.
  std::size_t ba_skipped = 0;
  std::size_t ba_stopped_early = 0;
  std::size_t ba_yielded_to_tracking = 0;  // of those skipped or cut short: tracking had asked (YieldRequests)
  // The estimated camera-IMU time offset's correction after each keyframe: (keyframe t_ns, correction ns).
  std::vector<std::pair<std::int64_t, std::int64_t>> time_corrections;

  void add(const DownlinkReport& r) {
    ++downlink_messages;
    downlink_stale += r.stale ? 1 : 0;
    if (!r.skipped.empty()) {
      ++downlink_skipped;
      downlink_last_skip = r.skipped;
    }
    anchors_added += static_cast<std::size_t>(r.anchors_added);
    anchors_released += static_cast<std::size_t>(r.anchors_released);
    most_anchors_held = std::max(most_anchors_held, r.anchors_held);
    anchor_points_added += static_cast<std::size_t>(r.points_added);
    anchor_points_linked += static_cast<std::size_t>(r.points_linked);
    anchor_updates += static_cast<std::size_t>(r.anchor_poses_updated + r.points_updated);
    over_capacity += static_cast<std::size_t>(r.anchors_over_capacity + r.points_over_capacity);
    unknown_references += static_cast<std::size_t>(r.unknown_references);
    corrections_applied += static_cast<std::size_t>(r.corrections_applied);
    corrections_deferred += static_cast<std::size_t>(r.corrections_deferred);
    corrections_skipped += static_cast<std::size_t>(r.corrections_skipped);
    largest_correction_m = std::max(largest_correction_m, r.largest_correction_m);
    largest_correction_deg = std::max(largest_correction_deg, r.largest_correction_deg);
  }
  // summary.json's "downlink".
  [[nodiscard]] nlohmann::json downlinkJson() const;
};

// What the mapping thread shares with the rest of the agent: flags it reads, figures it writes.
struct MappingLoopShared {
  const std::atomic<bool>& tracking_done;
  const std::atomic<bool>& stop;
  std::atomic<bool>& ready;  // set once the snapshot (and delta) topics have their subscribers
  LatencyRecorder& receive;
  LatencyRecorder& local_ba;
  LatencyRecorder& mapping_total;
  MappingStats& stats;
  YieldRequests& yield_requests;
};

// Runs until tracking is done (or `stop`) and every keyframe it sent is processed; it waits on its iceoryx
// subscribers and on `tracking_done_trigger`, which tracking fires once it has set `tracking_done`. Local BA
// yields (MapperOptions::yield_to_waiting_keyframes) to a keyframe already queued, and to tracking's requests
// since the keyframe was taken (`yield_requests`).
void mappingThread(Mapper& mapper, const AgentOptions& options, iox::popo::UserTrigger& tracking_done_trigger,
                   const MappingLoopShared& shared);

}  // namespace cvislam::agent
