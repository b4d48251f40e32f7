// The link's store: what of the agent's map goes to the server, and what the server has acknowledged.
//
// It mirrors the local map from mapping's deltas (keyframes in full, points, observations, merges, culls,
// states and positions) and keeps each object until the server has acknowledged it and it has left the local
// map; so it holds at most kLinkMaxKeyframes keyframes and kLinkMaxMapPoints points, allocated once. Every
// object remembers the batch that last carried it ("sent in batch N"). One rule then covers acknowledgements,
// reconnections and a server that lost its state: when the server says it holds every batch up to S, whatever
// was sent in a batch after S is sent again (a server that restarted empty says S = 0, and the agent's current
// map goes again in full).
//
// Nothing leaves the agent from a map whose world frame is not final yet (before the IMU initialisation), and
// objects that leave the local map before then are forgotten: their states would be in the old frame.
//
// Store full (the server away for long): the oldest keyframe that has left the local map is dropped, counted
// as lost; its points follow when no stored keyframe observes them.
//
// Not thread-safe: the link thread owns it.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "agent_rt/link/id_index.hpp"
#include "agent_rt/map/capacities.hpp"
#include "agent_rt/map/fixed_pool.hpp"
#include "agent_rt/messages/messages.hpp"
#include "common/core/ids.hpp"
#include "common/core/result.hpp"

namespace cvislam::v1 {
class MapBatch;
class KeyframeState;
}  // namespace cvislam::v1

namespace cvislam::agent {

struct LinkStoreOptions {
  // A keyframe's state goes again when it moved this far (or its velocity or biases changed).
  double keyframe_update_min_m = 1e-4;
  double keyframe_update_min_rad = 1e-4;
  // A map point's position goes again when it moved this far from the position last sent.
  double point_update_min_m = 0.005;

  [[nodiscard]] Status validate() const;
};

struct LinkStoreCounters {
  std::uint64_t deltas = 0;
  std::uint64_t deltas_lost = 0;        // gaps in mapping's delta sequence
  std::uint64_t delta_events_lost = 0;  // changes beyond a delta's capacity
  std::uint64_t keyframes_stored = 0;   // entered the store
  std::uint64_t keyframes_dropped = 0;  // left unsent or unacknowledged because the store was full
  std::uint64_t points_dropped = 0;
  std::uint64_t removals_dropped = 0;  // culls and merges not sent because the store of them was full
  std::uint64_t corrections_received = 0;
  // Batches the server had acknowledged and then, in a Welcome, said it does not hold (a server that restarted
  // without its store): their content was sent again, but the acknowledgement had been wrong.
  std::uint64_t acked_batches_lost = 0;
  // Welcomes that asked for content to be sent again (see onWelcome).
  std::uint64_t batches_to_resend = 0;
};

// What is waiting, for the progress line and the end of a run.
struct LinkBacklog {
  std::size_t keyframes_unsent = 0;   // in a ready map, never sent (since the server's last reset)
  std::size_t keyframes_unacked = 0;  // sent, not acknowledged yet
  std::size_t points_unsent = 0;
  std::size_t keyframes_held = 0;  // in the store
  std::size_t points_held = 0;
};

class LinkStore {
 public:
  // Allocates everything it will use (several MB: see kLinkMaxKeyframes).
  LinkStore(AgentId agent, const LinkStoreOptions& options);
  ~LinkStore();
  LinkStore(const LinkStore&) = delete;
  LinkStore& operator=(const LinkStore&) = delete;

  // Mapping's delta for one keyframe, in order.
  void onDelta(const MapDeltaMessage& delta);

  // The server holds every batch up to `stored` (a Welcome): anything sent in a later batch is sent again, and so
  // is anything sent from batch `resend_from` on when it is nonzero (the server holds other content under those
  // numbers than this agent last sent: an earlier attempt had committed unseen).
  void onWelcome(std::uint64_t stored, std::uint64_t resend_from = 0);
  // The server acknowledged every batch up to `acked`.
  void onAck(std::uint64_t acked);
  void onCorrections(int count) { counters_.corrections_received += static_cast<std::uint64_t>(count); }

  // Fills `batch` (cleared first) with what is due, oldest keyframes first, up to about `max_bytes`; every
  // object in it is marked sent in batch `sequence`. False (and `batch` empty) when nothing is due.
  bool buildBatch(std::uint64_t sequence, std::int64_t sensor_t_ns, std::size_t max_bytes, v1::MapBatch& batch);

  // Nothing unsent and everything acknowledged (the end of a mission may stop the link).
  [[nodiscard]] bool allAcknowledged() const;
  [[nodiscard]] LinkBacklog backlog() const;
  [[nodiscard]] const LinkStoreCounters& counters() const { return counters_; }
  [[nodiscard]] std::uint64_t acked() const { return acked_; }
  [[nodiscard]] std::int64_t newestSensorTime() const { return newest_t_ns_; }

  struct Keyframe;
  struct Point;
  struct Tombstone;

 private:
  Keyframe* keyframe(std::uint32_t counter);
  Point* point(std::uint32_t counter);
  [[nodiscard]] bool mapReady(std::uint32_t map_id) const;
  void setMapReady(std::uint32_t map_id, bool ready);
  void addKeyframe(const MapDeltaMessage& delta);
  void addPoint(const NewPointMsg& p, std::uint32_t map_id);
  void leaveLocalMapKeyframe(std::uint32_t counter);
  void leaveLocalMapPoint(std::uint32_t counter, bool culled);
  void mergePoints(std::uint32_t drop, std::uint32_t keep);
  void eraseKeyframe(PoolHandle handle);
  void erasePoint(PoolHandle handle);
  bool makeRoomForKeyframe();
  void addTombstone(const Tombstone& t);
  void forgetAcknowledged();
  [[nodiscard]] bool resolveReference(Point& p);
  [[nodiscard]] std::size_t tombstonesPending() const;

  // The bytes a batch holds so far (estimated for all but keyframes) against its limit. A batch takes at
  // least one item, however large.
  struct BatchBudget {
    std::size_t max_bytes = 0;
    std::size_t bytes = 16;
    bool content = false;
    [[nodiscard]] bool full() const { return content && bytes >= max_bytes; }
    void add(std::size_t n) {
      bytes += n;
      content = true;
    }
  };
  // The parts of a batch, in the order the server must apply them.
  void addNewKeyframes(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch);
  void addNewPoints(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch);
  void addObservations(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch);
  void addMergesAndCulls(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch);
  void addKeyframeUpdates(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch);
  void addPointUpdates(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch);

  AgentId agent_;
  LinkStoreOptions options_;
  std::unique_ptr<FixedPool<Keyframe, kLinkMaxKeyframes>> keyframes_;
  std::unique_ptr<FixedPool<Point, kLinkMaxMapPoints>> points_;
  std::unique_ptr<IdIndex<kLinkMaxKeyframes>> keyframe_index_;
  std::unique_ptr<IdIndex<kLinkMaxMapPoints>> point_index_;
  std::unique_ptr<std::array<Tombstone, kLinkMaxMapPoints>> tombstones_;
  std::size_t tombstone_count_ = 0;
  std::array<std::pair<std::uint32_t, bool>, 64> map_ready_{};  // (map id, ready), a ring of recent maps
  std::size_t map_ready_count_ = 0;
  std::vector<PoolHandle> order_;             // scratch, reserved once: keyframes by counter
  std::vector<std::uint32_t> order_scratch_;  // scratch, reserved once: counters to erase
  std::uint64_t expected_delta_ = 0;
  bool seen_delta_ = false;
  std::uint64_t delta_stamp_ = 0;
  std::uint64_t forget_pass_ = 0;
  std::uint64_t acked_ = 0;
  std::uint64_t last_sent_ = 0;  // the newest batch built
  std::int64_t newest_t_ns_ = 0;
  LinkStoreCounters counters_;
};

}  // namespace cvislam::agent
