#include "agent_rt/link/link_store.hpp"

#include <algorithm>
#include <cmath>
#include <optional>
#include <string>

#include "agent_rt/messages/conversions.hpp"
#include "common/trace/trace.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::agent {

struct LinkStore::Keyframe {
  struct Imu {
    std::int64_t t_ns = 0;
    std::array<float, 3> gyro{};
    std::array<float, 3> accel{};
  };
  KeyframeId id;
  std::uint32_t map_id = 0;
  std::int64_t t_ns = 0;
  KeyframeStateMsg state;        // the newest
  KeyframeStateMsg sent_state;   // as last sent
  std::uint64_t full_sent = 0;   // the batch that carried it in full; 0: not (or not again) sent
  std::uint64_t state_sent = 0;  // the batch that carried sent_state; 0: to send again
  std::uint64_t stamp = 0;       // the last delta that listed it in the local map
  bool in_local_map = true;
  // `state` is tracking's: the keyframe came before its local BA (MapDeltaMessage::keyframe_before_local_ba).
  bool before_local_ba = false;
  bool has_imu_from = false;
  std::uint32_t imu_from = 0;
  std::uint16_t keypoint_count = 0;
  std::array<KeypointMsg, kMaxKeypointsPerKeyframe> keypoints{};
  std::array<std::array<std::uint8_t, 32>, kMaxKeypointsPerKeyframe> descriptors{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> has_right{};
  std::array<std::array<float, 2>, kMaxKeypointsPerKeyframe> right_px{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> right_octave{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> has_obs{};
  std::array<std::uint32_t, kMaxKeypointsPerKeyframe> obs{};  // map point counters (this agent's)
  std::array<std::uint64_t, kMaxKeypointsPerKeyframe> obs_sent{};
  std::uint32_t imu_count = 0;
  std::array<Imu, kMaxImuSamplesPerKeyframe> imu{};
};

struct LinkStore::Point {
  std::uint32_t counter = 0;
  std::uint32_t reference = 0;  // keyframe counter
  std::uint32_t map_id = 0;
  std::array<float, 3> p_w{};
  std::array<float, 3> sent_p_w{};
  std::array<std::uint8_t, 32> descriptor{};
  std::uint8_t octave = 0;
  std::uint64_t full_sent = 0;
  std::uint64_t pos_sent = 0;
  std::uint64_t stamp = 0;
  std::uint64_t pinned = 0;  // the forget pass that found it still needed (an observation or merge to send)
  bool in_local_map = true;
};

// A cull or a merge of a point the server may hold, until the server has acknowledged it.
struct LinkStore::Tombstone {
  bool merge = false;
  std::uint32_t point = 0;
  std::uint32_t keep = 0;             // merge only
  std::uint64_t point_full_sent = 0;  // the batch that gave the server the point
  std::uint64_t sent = 0;
};

namespace {

bool stateChanged(const KeyframeStateMsg& a, const KeyframeStateMsg& b, const LinkStoreOptions& o) {
  const geometry::SE3d Ta = fromMsg(a.T_w_s);
  const geometry::SE3d Tb = fromMsg(b.T_w_s);
  if ((Ta.translation() - Tb.translation()).norm() > o.keyframe_update_min_m) return true;
  if ((Ta.so3().inverse() * Tb.so3()).log().norm() > o.keyframe_update_min_rad) return true;
  if ((toVector3(a.v_w) - toVector3(b.v_w)).norm() > 1e-3) return true;
  for (std::size_t i = 0; i < 6; ++i) {
    if (std::abs(a.bias[i] - b.bias[i]) > 1e-5) return true;
  }
  return false;
}

float distance(const std::array<float, 3>& a, const std::array<float, 3>& b) {
  const float dx = a[0] - b[0];
  const float dy = a[1] - b[1];
  const float dz = a[2] - b[2];
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// What to give up when a pool is full: an object that has left the local map, an acknowledged one first, then the
// oldest by `age`. Nothing when every object is still in the local map.
struct Eviction {
  PoolHandle handle;
  bool acked = false;
};
template <typename Pool, typename Age>
std::optional<Eviction> evictionCandidate(const Pool& pool, std::uint64_t acked, Age age) {
  std::optional<Eviction> best;
  std::int64_t best_age = 0;
  pool.forEach([&](PoolHandle h, const auto& object) {
    if (object.in_local_map) return;
    const bool is_acked = object.full_sent != 0 && object.full_sent <= acked;
    const std::int64_t a = age(object);
    if (!best || (is_acked && !best->acked) || (is_acked == best->acked && a < best_age)) {
      best = Eviction{h, is_acked};
      best_age = a;
    }
  });
  return best;
}

void writeState(std::uint32_t counter, const KeyframeStateMsg& m, v1::KeyframeState* out) {
  wire::toProto(counter, wire::KeyframeStateValues{fromMsg(m.T_w_s), toVector3(m.v_w), biasFromMsg(m.bias)}, out);
}

// A new keyframe whole: state, IMU since the previous keyframe, keypoints with packed descriptors, and its
// stereo matches.
void writeKeyframe(const LinkStore::Keyframe& kf, v1::Keyframe& k) {
  k.set_counter(kf.id.counter);
  k.set_agent_map(kf.map_id);
  k.set_t_ns(kf.t_ns);
  writeState(kf.id.counter, kf.state, k.mutable_state());
  if (kf.before_local_ba) k.set_before_local_ba(true);
  if (kf.has_imu_from) k.set_imu_from(kf.imu_from);
  v1::ImuSamples& imu = *k.mutable_imu();
  std::int64_t previous = kf.t_ns;
  for (std::uint32_t i = 0; i < kf.imu_count; ++i) {
    const LinkStore::Keyframe::Imu& s = kf.imu[i];
    imu.add_dt_ns(s.t_ns - previous);
    previous = s.t_ns;
    for (int a = 0; a < 3; ++a) {
      imu.add_gyro(s.gyro[static_cast<std::size_t>(a)]);
      imu.add_accel(s.accel[static_cast<std::size_t>(a)]);
    }
  }
  v1::Keypoints& kp = *k.mutable_keypoints();
  std::string* octave = kp.mutable_octave();
  std::string* angle = kp.mutable_angle();
  octave->resize(kf.keypoint_count);
  angle->resize(kf.keypoint_count);
  kp.mutable_xy()->Reserve(2 * kf.keypoint_count);
  kp.mutable_descriptors()->Reserve(4 * kf.keypoint_count);
  v1::StereoMatches& right = *k.mutable_right();
  for (std::uint16_t i = 0; i < kf.keypoint_count; ++i) {
    kp.add_xy(kf.keypoints[i].x);
    kp.add_xy(kf.keypoints[i].y);
    (*octave)[i] = static_cast<char>(kf.keypoints[i].octave);
    (*angle)[i] = static_cast<char>(wire::encodeAngle(kf.keypoints[i].angle_deg));
    wire::packDescriptor(kf.descriptors[i].data(), kp.mutable_descriptors());
    if (kf.has_right[i] != 0) {
      right.add_keypoint(i);
      right.add_xy(kf.right_px[i][0]);
      right.add_xy(kf.right_px[i][1]);
      right.mutable_octave()->push_back(static_cast<char>(kf.right_octave[i]));
    }
  }
}

}  // namespace

Status LinkStoreOptions::validate() const {
  if (!(keyframe_update_min_m >= 0.0) || !(keyframe_update_min_rad >= 0.0) || !(point_update_min_m >= 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "link: update thresholds must be >= 0"};
  }
  return Status::Ok();
}

LinkStore::LinkStore(AgentId agent, const LinkStoreOptions& options)
    : agent_(agent),
      options_(options),
      keyframes_(std::make_unique<FixedPool<Keyframe, kLinkMaxKeyframes>>()),
      points_(std::make_unique<FixedPool<Point, kLinkMaxMapPoints>>()),
      keyframe_index_(std::make_unique<IdIndex<kLinkMaxKeyframes>>()),
      point_index_(std::make_unique<IdIndex<kLinkMaxMapPoints>>()),
      tombstones_(std::make_unique<std::array<Tombstone, kLinkMaxMapPoints>>()) {
  order_.reserve(kLinkMaxKeyframes);
  order_scratch_.reserve(kLinkMaxMapPoints);
}

LinkStore::~LinkStore() = default;

LinkStore::Keyframe* LinkStore::keyframe(std::uint32_t counter) {
  const PoolHandle* h = keyframe_index_->find(counter);
  return h == nullptr ? nullptr : keyframes_->get(*h);
}

LinkStore::Point* LinkStore::point(std::uint32_t counter) {
  const PoolHandle* h = point_index_->find(counter);
  return h == nullptr ? nullptr : points_->get(*h);
}

bool LinkStore::mapReady(std::uint32_t map_id) const {
  const std::size_t n = std::min(map_ready_count_, map_ready_.size());
  for (std::size_t i = 0; i < n; ++i) {
    if (map_ready_[i].first == map_id) return map_ready_[i].second;
  }
  return false;
}

void LinkStore::setMapReady(std::uint32_t map_id, bool ready) {
  // Keyframes of a map whose frame is not final wait in the store; a trace tells that wait from the link's.
  if (ready && !mapReady(map_id)) trace::instant("map_ready", {{"map", map_id}});
  const std::size_t n = std::min(map_ready_count_, map_ready_.size());
  for (std::size_t i = 0; i < n; ++i) {
    if (map_ready_[i].first == map_id) {
      map_ready_[i].second = ready;
      return;
    }
  }
  map_ready_[map_ready_count_ % map_ready_.size()] = {map_id, ready};
  ++map_ready_count_;
}

void LinkStore::eraseKeyframe(PoolHandle handle) {
  Keyframe* kf = keyframes_->get(handle);
  if (kf == nullptr) return;
  keyframe_index_->erase(kf->id.counter);
  keyframes_->erase(handle);
}

void LinkStore::erasePoint(PoolHandle handle) {
  Point* p = points_->get(handle);
  if (p == nullptr) return;
  point_index_->erase(p->counter);
  points_->erase(handle);
}

bool LinkStore::makeRoomForKeyframe() {
  const auto victim = evictionCandidate(*keyframes_, acked_, [](const Keyframe& kf) { return kf.t_ns; });
  if (!victim) return false;
  if (!victim->acked) ++counters_.keyframes_dropped;
  eraseKeyframe(victim->handle);
  return true;
}

void LinkStore::addKeyframe(const MapDeltaMessage& d) {
  const std::uint32_t c = d.keyframe.id.counter;
  if (keyframe(c) != nullptr) return;
  if (keyframes_->full() && !makeRoomForKeyframe()) {
    ++counters_.keyframes_dropped;
    return;
  }
  const auto handle = keyframes_->acquire();
  if (!handle) return;
  Keyframe& kf = *keyframes_->get(*handle);
  kf.id = d.keyframe.id;
  kf.map_id = d.keyframe_map_id;
  kf.t_ns = d.keyframe.t_ns;
  kf.state = d.keyframe;
  kf.sent_state = d.keyframe;
  kf.full_sent = 0;
  kf.state_sent = 0;
  kf.stamp = delta_stamp_;
  kf.in_local_map = true;
  kf.before_local_ba = d.keyframe_before_local_ba != 0;
  kf.has_imu_from = d.has_imu_link != 0 && d.imu_from.agent == agent_;
  kf.imu_from = d.imu_from.counter;
  kf.keypoint_count = std::min<std::uint16_t>(d.keypoint_count, kMaxKeypointsPerKeyframe);
  for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
    kf.keypoints[k] = d.keypoints[k];
    kf.descriptors[k] = d.descriptors[k];
    kf.has_right[k] = d.has_right[k];
    kf.right_px[k] = d.right_px[k];
    kf.right_octave[k] = d.right_octave[k];
    kf.has_obs[k] = d.has_observation[k] != 0 && d.observation[k].agent == agent_ ? 1 : 0;
    kf.obs[k] = d.observation[k].counter;
    kf.obs_sent[k] = 0;
  }
  kf.imu_count = std::min<std::uint32_t>(d.imu_count, kMaxImuSamplesPerKeyframe);
  for (std::uint32_t i = 0; i < kf.imu_count; ++i) {
    const ImuSampleMsg& s = d.imu[i];
    kf.imu[i] = {s.t_ns,
                 {static_cast<float>(s.gyro[0]), static_cast<float>(s.gyro[1]), static_cast<float>(s.gyro[2])},
                 {static_cast<float>(s.accel[0]), static_cast<float>(s.accel[1]), static_cast<float>(s.accel[2])}};
  }
  keyframe_index_->insert(c, *handle);
  ++counters_.keyframes_stored;
}

void LinkStore::addPoint(const NewPointMsg& n, std::uint32_t map_id) {
  if (point(n.id.counter) != nullptr) return;
  if (points_->full()) {
    const auto victim = evictionCandidate(*points_, acked_, [](const Point& p) { return std::int64_t{p.counter}; });
    if (!victim || !victim->acked) ++counters_.points_dropped;
    if (!victim) return;
    erasePoint(victim->handle);
  }
  const auto handle = points_->acquire();
  if (!handle) return;
  Point& p = *points_->get(*handle);
  p.counter = n.id.counter;
  p.reference = n.reference.counter;
  p.map_id = map_id;
  p.p_w = n.p_w;
  p.sent_p_w = n.p_w;
  p.descriptor = n.descriptor;
  p.octave = n.octave;
  p.full_sent = 0;
  p.pos_sent = 0;
  p.stamp = delta_stamp_;
  p.pinned = 0;
  p.in_local_map = true;
  point_index_->insert(p.counter, *handle);
}

void LinkStore::addTombstone(const Tombstone& t) {
  auto& stones = *tombstones_;
  if (tombstone_count_ == stones.size()) {
    std::move(stones.begin() + 1, stones.end(), stones.begin());  // the oldest goes
    --tombstone_count_;
    ++counters_.removals_dropped;
  }
  stones[tombstone_count_++] = t;
}

void LinkStore::leaveLocalMapKeyframe(std::uint32_t counter) {
  const PoolHandle* h = keyframe_index_->find(counter);
  if (h == nullptr) return;
  Keyframe& kf = *keyframes_->get(*h);
  kf.in_local_map = false;
  // Before its map's frame is final, nothing of it may leave the agent: forget it.
  if (!mapReady(kf.map_id)) eraseKeyframe(*h);
}

void LinkStore::leaveLocalMapPoint(std::uint32_t counter, bool culled) {
  const PoolHandle* h = point_index_->find(counter);
  if (h == nullptr) return;
  Point& p = *points_->get(*h);
  if (culled) {
    if (p.full_sent != 0) addTombstone({false, p.counter, 0, p.full_sent, 0});
    erasePoint(*h);
    return;
  }
  p.in_local_map = false;
  if (!mapReady(p.map_id)) erasePoint(*h);
}

void LinkStore::mergePoints(std::uint32_t drop, std::uint32_t keep) {
  // The stored keyframes see what the server's merge will do: links to `drop` become links to `keep`, except
  // in a keyframe that observes `keep` already, where the `drop` link goes.
  keyframes_->forEach([&](PoolHandle, Keyframe& kf) {
    int drop_at = -1;
    bool observes_keep = false;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_obs[k] == 0) continue;
      if (kf.obs[k] == drop) drop_at = k;
      if (kf.obs[k] == keep) observes_keep = true;
    }
    if (drop_at < 0) return;
    const auto k = static_cast<std::size_t>(drop_at);
    if (observes_keep) {
      kf.has_obs[k] = 0;
    } else {
      kf.obs[k] = keep;
    }
  });
  // A merge still waiting for `drop` to reach the server as the kept point now keeps `keep` instead.
  auto& stones = *tombstones_;
  for (std::size_t i = 0; i < tombstone_count_; ++i) {
    if (stones[i].merge && stones[i].sent == 0 && stones[i].keep == drop) stones[i].keep = keep;
  }
  const PoolHandle* h = point_index_->find(drop);
  if (h == nullptr) return;
  const Point& d = *points_->get(*h);
  if (d.full_sent != 0) addTombstone({true, drop, keep, d.full_sent, 0});
  erasePoint(*h);
}

void LinkStore::onDelta(const MapDeltaMessage& d) {
  ++counters_.deltas;
  if (seen_delta_ && d.sequence > expected_delta_) counters_.deltas_lost += d.sequence - expected_delta_;
  seen_delta_ = true;
  expected_delta_ = d.sequence + 1;
  counters_.delta_events_lost += d.events_lost;
  newest_t_ns_ = std::max(newest_t_ns_, d.t_ns);
  ++delta_stamp_;

  const bool own_keyframe = d.has_keyframe != 0 && d.keyframe.id.agent == agent_;
  if (own_keyframe) addKeyframe(d);
  for (std::uint16_t i = 0; i < d.new_point_count; ++i) {
    const NewPointMsg& n = d.new_points[i];
    if (n.id.agent != agent_) continue;
    const Keyframe* reference = keyframe(n.reference.counter);
    addPoint(n, reference != nullptr ? reference->map_id : d.map_id);
  }
  const auto link = [&](const MapEvent& e) {
    if (own_keyframe && e.keyframe == d.keyframe.id) return;  // its links come whole, as they are now
    if (e.keyframe.agent != agent_ || e.point.agent != agent_) return;
    Keyframe* kf = keyframe(e.keyframe.counter);
    if (kf == nullptr || point(e.point.counter) == nullptr || e.keypoint >= kf->keypoint_count) return;
    kf->has_obs[e.keypoint] = 1;
    kf->obs[e.keypoint] = e.point.counter;
    kf->obs_sent[e.keypoint] = 0;
  };
  for (std::uint16_t i = 0; i < d.event_count; ++i) {
    const MapEvent& e = d.events[i];
    switch (e.type) {
      case MapEventType::kPointCreated:
      case MapEventType::kObservationAdded:
        link(e);
        break;
      case MapEventType::kPointsMerged:
        if (e.point.agent == agent_ && e.other.agent == agent_) mergePoints(e.point.counter, e.other.counter);
        break;
      case MapEventType::kPointRemoved:
        if (e.point.agent == agent_) leaveLocalMapPoint(e.point.counter, e.reason == MapEventReason::kCulled);
        break;
      case MapEventType::kKeyframeRemoved:
        if (e.keyframe.agent == agent_) leaveLocalMapKeyframe(e.keyframe.counter);
        break;
    }
  }

  // States and positions of everything in the local map now; what is not listed has left it.
  for (std::uint16_t i = 0; i < d.keyframe_count; ++i) {
    const KeyframeStateMsg& m = d.keyframes[i];
    if (m.id.agent != agent_) continue;
    if (Keyframe* kf = keyframe(m.id.counter)) {
      kf->state = m;
      kf->stamp = delta_stamp_;
      kf->in_local_map = true;
      if (kf->before_local_ba && !(own_keyframe && m.id == d.keyframe.id)) {
        // Any later delta comes after the keyframe's local BA. The server holds the keyframe back from fusion and
        // recognition until it hears this state, so it goes even when the BA barely moved it.
        kf->before_local_ba = false;
        kf->state_sent = 0;
      }
    }
  }
  for (std::uint32_t i = 0; i < d.point_count; ++i) {
    const DeltaPointMsg& m = d.points[i];
    if (m.id.agent != agent_) continue;
    if (Point* p = point(m.id.counter)) {
      p->p_w = m.p_w;
      p->stamp = delta_stamp_;
      p->in_local_map = true;
    }
  }
  std::vector<std::uint32_t>& gone = order_scratch_;
  gone.clear();
  keyframes_->forEach([&](PoolHandle, const Keyframe& kf) {
    if (kf.in_local_map && kf.stamp != delta_stamp_) gone.push_back(kf.id.counter);
  });
  for (std::uint32_t c : gone) leaveLocalMapKeyframe(c);
  gone.clear();
  points_->forEach([&](PoolHandle, const Point& p) {
    if (p.in_local_map && p.stamp != delta_stamp_) gone.push_back(p.counter);
  });
  for (std::uint32_t c : gone) leaveLocalMapPoint(c, false);
  // Readiness last: what left the local map in this very delta was judged by the map's state before it (an
  // object that left while the IMU initialisation ran still has a state in the old frame, and is forgotten).
  setMapReady(d.map_id, d.ready != 0);
  forgetAcknowledged();
}

void LinkStore::onWelcome(std::uint64_t stored, std::uint64_t resend_from) {
  if (stored < acked_) counters_.acked_batches_lost += acked_ - stored;
  acked_ = stored;
  if (resend_from != 0 && resend_from <= stored) {
    ++counters_.batches_to_resend;
    stored = resend_from - 1;  // what was sent from there on is not known to be held: it goes again
  }
  keyframes_->forEach([&](PoolHandle, Keyframe& kf) {
    if (kf.full_sent > stored) {
      kf.full_sent = 0;
      kf.state_sent = 0;
      std::fill_n(kf.obs_sent.begin(), kf.keypoint_count, 0);
      return;
    }
    if (kf.state_sent > stored) kf.state_sent = 0;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.obs_sent[k] > stored) kf.obs_sent[k] = 0;
    }
  });
  points_->forEach([&](PoolHandle, Point& p) {
    if (p.full_sent > stored) {
      p.full_sent = 0;
      p.pos_sent = 0;
    } else if (p.pos_sent > stored) {
      p.pos_sent = 0;
    }
  });
  auto& stones = *tombstones_;
  std::size_t kept = 0;
  for (std::size_t i = 0; i < tombstone_count_; ++i) {
    Tombstone t = stones[i];
    if (t.point_full_sent > stored) continue;  // the server never got the point: nothing to undo
    if (t.sent > stored) t.sent = 0;
    stones[kept++] = t;
  }
  tombstone_count_ = kept;
}

void LinkStore::onAck(std::uint64_t acked) {
  acked_ = std::max(acked_, acked);
  forgetAcknowledged();
}

void LinkStore::forgetAcknowledged() {
  const auto acknowledged = [&](std::uint64_t sent) { return sent != 0 && sent <= acked_; };
  std::vector<std::uint32_t>& done = order_scratch_;
  done.clear();
  keyframes_->forEach([&](PoolHandle, const Keyframe& kf) {
    if (kf.in_local_map || !acknowledged(kf.full_sent) || !acknowledged(kf.state_sent)) return;
    if (stateChanged(kf.state, kf.sent_state, options_)) return;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_obs[k] != 0 && !acknowledged(kf.obs_sent[k])) return;
    }
    done.push_back(kf.id.counter);
  });
  for (std::uint32_t c : done) {
    if (const PoolHandle* h = keyframe_index_->find(c)) eraseKeyframe(*h);
  }
  // Points that something still to be acknowledged refers to stay: an observation of a stored keyframe, or a
  // merge into them (else the observation would be dropped, or the merge become a removal).
  ++forget_pass_;
  keyframes_->forEach([&](PoolHandle, const Keyframe& kf) {
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_obs[k] == 0 || acknowledged(kf.obs_sent[k])) continue;
      if (Point* p = point(kf.obs[k])) p->pinned = forget_pass_;
    }
  });
  for (std::size_t i = 0; i < tombstone_count_; ++i) {
    const Tombstone& t = (*tombstones_)[i];
    if (!t.merge || acknowledged(t.sent)) continue;
    if (Point* p = point(t.keep)) p->pinned = forget_pass_;
  }
  done.clear();
  points_->forEach([&](PoolHandle, const Point& p) {
    if (p.in_local_map || p.pinned == forget_pass_ || !acknowledged(p.full_sent) || !acknowledged(p.pos_sent)) return;
    done.push_back(p.counter);
  });
  for (std::uint32_t c : done) {
    if (const PoolHandle* h = point_index_->find(c)) erasePoint(*h);
  }
  auto& stones = *tombstones_;
  std::size_t kept = 0;
  for (std::size_t i = 0; i < tombstone_count_; ++i) {
    if (!acknowledged(stones[i].sent)) stones[kept++] = stones[i];
  }
  tombstone_count_ = kept;
}

bool LinkStore::resolveReference(Point& p) {
  if (const Keyframe* kf = keyframe(p.reference); kf != nullptr && kf->map_id == p.map_id) return true;
  bool found = false;
  keyframes_->forEach([&](PoolHandle, const Keyframe& kf) {
    if (found || kf.map_id != p.map_id) return;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_obs[k] != 0 && kf.obs[k] == p.counter) {
        p.reference = kf.id.counter;
        found = true;
        return;
      }
    }
  });
  return found;
}

bool LinkStore::buildBatch(std::uint64_t sequence, std::int64_t sensor_t_ns, std::size_t max_bytes,
                           v1::MapBatch& batch) {
  batch.Clear();
  batch.set_sequence(sequence);
  batch.set_sensor_time_ns(sensor_t_ns);
  BatchBudget budget;
  budget.max_bytes = max_bytes;

  order_.clear();
  keyframes_->forEach([&](PoolHandle h, const Keyframe&) { order_.push_back(h); });
  std::sort(order_.begin(), order_.end(), [&](PoolHandle a, PoolHandle b) {
    return keyframes_->get(a)->id.counter < keyframes_->get(b)->id.counter;
  });
  addNewKeyframes(sequence, budget, batch);
  addNewPoints(sequence, budget, batch);
  addObservations(sequence, budget, batch);
  addMergesAndCulls(sequence, budget, batch);
  addKeyframeUpdates(sequence, budget, batch);
  addPointUpdates(sequence, budget, batch);
  if (budget.content) last_sent_ = sequence;
  return budget.content;
}

// 1. New keyframes, oldest first.
void LinkStore::addNewKeyframes(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch) {
  for (PoolHandle h : order_) {
    if (budget.full()) break;
    Keyframe& kf = *keyframes_->get(h);
    if (kf.full_sent != 0 || !mapReady(kf.map_id)) continue;
    v1::Keyframe& k = *batch.add_keyframes();
    writeKeyframe(kf, k);
    kf.full_sent = sequence;
    kf.state_sent = sequence;
    kf.sent_state = kf.state;
    budget.add(k.ByteSizeLong());
  }
}

// 2. New points whose reference keyframe the server holds (or gets in this batch). A point no stored
// keyframe observes any more cannot be placed on the server: it is dropped.
void LinkStore::addNewPoints(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch) {
  std::vector<std::uint32_t>& unplaceable = order_scratch_;
  unplaceable.clear();
  points_->forEach([&](PoolHandle, Point& p) {
    if (budget.full() || p.full_sent != 0 || !mapReady(p.map_id)) return;
    if (!resolveReference(p)) {
      unplaceable.push_back(p.counter);
      return;
    }
    const Keyframe* reference = keyframe(p.reference);
    if (reference->full_sent == 0) return;  // later, with its keyframe
    v1::MapPoint& m = *batch.add_points();
    m.set_counter(p.counter);
    m.set_reference_keyframe(p.reference);
    m.add_p_w(p.p_w[0]);
    m.add_p_w(p.p_w[1]);
    m.add_p_w(p.p_w[2]);
    wire::packDescriptor(p.descriptor.data(), m.mutable_orb());
    m.set_octave(p.octave);
    p.full_sent = sequence;
    p.pos_sent = sequence;
    p.sent_p_w = p.p_w;
    budget.add(64);
  });
  for (std::uint32_t c : unplaceable) {
    if (const PoolHandle* h = point_index_->find(c)) erasePoint(*h);
    ++counters_.points_dropped;
  }
}

// 3. Observations of keyframes the server holds, of points it holds.
void LinkStore::addObservations(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch) {
  for (PoolHandle h : order_) {
    if (budget.full()) break;
    Keyframe& kf = *keyframes_->get(h);
    if (kf.full_sent == 0) continue;
    v1::Observations* o = nullptr;
    for (std::uint16_t i = 0; i < kf.keypoint_count; ++i) {
      if (kf.has_obs[i] == 0 || kf.obs_sent[i] != 0) continue;
      const Point* p = point(kf.obs[i]);
      if (p == nullptr) {
        kf.has_obs[i] = 0;  // the point is gone (culled, or dropped from the store)
        continue;
      }
      if (p->full_sent == 0 || p->map_id != kf.map_id) continue;
      if (o == nullptr) {
        o = batch.add_observations();
        o->set_keyframe(kf.id.counter);
        budget.add(4);
      }
      o->add_keypoint(i);
      o->add_point(kf.obs[i]);
      kf.obs_sent[i] = sequence;
      budget.add(5);
    }
  }
}

// 4. Merges and culls of points the server holds.
void LinkStore::addMergesAndCulls(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch) {
  auto& stones = *tombstones_;
  for (std::size_t i = 0; i < tombstone_count_ && !budget.full(); ++i) {
    Tombstone& t = stones[i];
    if (t.sent != 0) continue;
    if (t.merge) {
      const Point* keep = point(t.keep);
      if (keep != nullptr && keep->full_sent == 0) continue;  // after `keep` reaches the server
      if (keep != nullptr) {
        batch.mutable_merges()->add_drop(t.point);
        batch.mutable_merges()->add_keep(t.keep);
      } else {
        batch.add_removed_points(t.point);  // `keep` went meanwhile: the server drops `drop`
      }
    } else {
      batch.add_removed_points(t.point);
    }
    t.sent = sequence;
    budget.add(6);
  }
}

// 5. Keyframe states that changed since they were sent.
void LinkStore::addKeyframeUpdates(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch) {
  for (PoolHandle h : order_) {
    if (budget.full()) break;
    Keyframe& kf = *keyframes_->get(h);
    if (kf.full_sent == 0 || kf.full_sent == sequence) continue;
    if (kf.state_sent != 0 && !stateChanged(kf.state, kf.sent_state, options_)) continue;
    writeState(kf.id.counter, kf.state, batch.add_keyframe_updates());
    kf.sent_state = kf.state;
    kf.state_sent = sequence;
    budget.add(100);
  }
}

// 6. Point positions that moved since they were sent.
void LinkStore::addPointUpdates(std::uint64_t sequence, BatchBudget& budget, v1::MapBatch& batch) {
  v1::PointPositions* positions = nullptr;
  points_->forEach([&](PoolHandle, Point& p) {
    if (budget.full() || p.full_sent == 0 || p.full_sent == sequence) return;
    if (p.pos_sent != 0 && distance(p.p_w, p.sent_p_w) <= static_cast<float>(options_.point_update_min_m)) return;
    if (positions == nullptr) positions = batch.mutable_point_updates();
    positions->add_point(p.counter);
    positions->add_p_w(p.p_w[0]);
    positions->add_p_w(p.p_w[1]);
    positions->add_p_w(p.p_w[2]);
    p.sent_p_w = p.p_w;
    p.pos_sent = sequence;
    budget.add(16);
  });
}

bool LinkStore::allAcknowledged() const {
  if (last_sent_ > acked_) return false;
  const LinkBacklog b = backlog();
  return b.keyframes_unsent == 0 && b.keyframes_unacked == 0 && b.points_unsent == 0 && tombstonesPending() == 0;
}

std::size_t LinkStore::tombstonesPending() const {
  std::size_t n = 0;
  for (std::size_t i = 0; i < tombstone_count_; ++i) n += (*tombstones_)[i].sent == 0 ? 1 : 0;
  return n;
}

LinkBacklog LinkStore::backlog() const {
  LinkBacklog b;
  b.keyframes_held = keyframes_->size();
  b.points_held = points_->size();
  keyframes_->forEach([&](PoolHandle, const Keyframe& kf) {
    if (!mapReady(kf.map_id) && kf.full_sent == 0) return;
    if (kf.full_sent == 0) {
      ++b.keyframes_unsent;
    } else if (kf.full_sent > acked_) {
      ++b.keyframes_unacked;
    }
  });
  points_->forEach([&](PoolHandle, const Point& p) {
    if (p.full_sent == 0 && mapReady(p.map_id)) ++b.points_unsent;
  });
  return b;
}

}  // namespace cvislam::agent
