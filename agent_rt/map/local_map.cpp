#include "agent_rt/map/local_map.hpp"

#include <algorithm>
#include <limits>
#include <string>

namespace cvislam::agent {

using Eigen::Vector3d;

LocalMap::LocalMap(const geometry::SE3d& T_s_c)
    : T_s_c_(T_s_c), keyframes_(std::make_unique<KeyframePool>()), map_points_(std::make_unique<MapPointPool>()) {}

Result<PoolHandle> LocalMap::insertKeyframe(const KeyframeData& keyframe) {
  if (keyframe.keypoint_count > kMaxKeypointsPerKeyframe) {
    return Error{ErrorCode::kInvalidArgument, "keyframe " + keyframe.id.toString() + " has " +
                                                  std::to_string(keyframe.keypoint_count) + " keypoints, more than " +
                                                  std::to_string(kMaxKeypointsPerKeyframe)};
  }
  auto handle = keyframes_->insert(keyframe);
  if (!handle) {
    return Error{ErrorCode::kCapacityExceeded, "local map full: " + std::to_string(kMaxKeyframes) +
                                                   " keyframes; evict one before inserting " + keyframe.id.toString()};
  }
  KeyframeData& stored = *keyframes_->get(*handle);
  stored.has_map_point.fill(false);
  // Anchors stand outside the agent's own order (and do not age its young points): sequence 0.
  stored.sequence = keyframe.anchor ? 0 : next_sequence_++;
  return *handle;
}

void LocalMap::detach(PoolHandle keyframe, std::uint16_t keypoint) {
  KeyframeData* kf = keyframes_->get(keyframe);
  if (kf == nullptr || keypoint >= kf->keypoint_count || !kf->has_map_point[keypoint]) return;
  if (MapPointData* mp = map_points_->get(kf->map_point[keypoint]); mp != nullptr && mp->observation_count > 0) {
    --mp->observation_count;
  }
  kf->has_map_point[keypoint] = false;
}

Status LocalMap::removeKeyframe(PoolHandle keyframe, MapEventReason reason) {
  KeyframeData* kf = keyframes_->get(keyframe);
  if (kf == nullptr) return Error{ErrorCode::kNotFound, "removeKeyframe: stale or unknown keyframe handle"};
  // The keyframe goes first in the event order: its points that go with it follow.
  MapEvent gone;
  gone.type = MapEventType::kKeyframeRemoved;
  gone.reason = reason;
  gone.keyframe = kf->id;
  if (!kf->anchor) report(gone);
  for (std::uint16_t k = 0; k < kf->keypoint_count; ++k) {
    if (!kf->has_map_point[k]) continue;
    const PoolHandle point = kf->map_point[k];
    MapPointData* mp = map_points_->get(point);
    if (mp == nullptr) continue;
    if (mp->reference == keyframe) {
      // Re-anchor the point in another keyframe that observes it, keeping its world position.
      const auto p_w = pointInWorld(point);
      bool moved = false;
      keyframes_->forEach([&](PoolHandle other, KeyframeData& data) {
        if (moved || other == keyframe || !p_w.ok()) return;
        for (std::uint16_t j = 0; j < data.keypoint_count; ++j) {
          if (!data.has_map_point[j] || !(data.map_point[j] == point)) continue;
          const Vector3d p_c = (data.T_w_s * T_s_c_).inverse() * *p_w;
          if (p_c.z() <= 0.0) continue;
          mp->reference = other;
          mp->bearing_c = p_c.normalized();
          mp->inverse_depth = 1.0 / p_c.norm();
          moved = true;
          return;
        }
      });
      if (!moved) {
        // Its last observer leaves: the point leaves with it, for the same reason.
        if (Status status = removeMapPoint(point, reason); !status.ok()) return status;
        continue;
      }
    }
    detach(keyframe, k);
  }
  keyframes_->erase(keyframe);
  return Status::Ok();
}

Status LocalMap::evictOldestKeyframe() {
  PoolHandle oldest;
  std::uint64_t oldest_sequence = std::numeric_limits<std::uint64_t>::max();
  keyframes_->forEach([&](PoolHandle handle, const KeyframeData& kf) {
    if (!kf.anchor && kf.sequence < oldest_sequence) {
      oldest_sequence = kf.sequence;
      oldest = handle;
    }
  });
  if (oldest_sequence == std::numeric_limits<std::uint64_t>::max()) {
    return Error{ErrorCode::kNotFound, "no keyframe to evict: every keyframe in the local map is an anchor"};
  }
  return removeKeyframe(oldest, MapEventReason::kEvicted);
}

Result<PoolHandle> LocalMap::createMapPoint(PoolHandle reference, std::uint16_t keypoint, const Vector3d& bearing_c,
                                            double depth_m, MapPointId id) {
  KeyframeData* kf = keyframes_->get(reference);
  if (kf == nullptr) return Error{ErrorCode::kNotFound, "createMapPoint: stale or unknown reference keyframe"};
  if (keypoint >= kf->keypoint_count || kf->has_map_point[keypoint]) {
    return Error{ErrorCode::kInvalidArgument, "createMapPoint: keypoint " + std::to_string(keypoint) + " of keyframe " +
                                                  kf->id.toString() + " is out of range or taken"};
  }
  if (!(depth_m > 0.0) || !bearing_c.allFinite() || bearing_c.norm() < 1e-12) {
    return Error{ErrorCode::kInvalidArgument, "createMapPoint: depth must be > 0 and the bearing finite"};
  }
  MapPointData point;
  point.id = id;
  point.reference = reference;
  point.bearing_c = bearing_c.normalized();
  point.inverse_depth = 1.0 / depth_m;
  point.descriptor = kf->descriptors[keypoint];
  point.octave = kf->keypoints[keypoint].octave;
  point.created_at_sequence = next_sequence_ == 0 ? 0 : next_sequence_ - 1;
  point.observation_count = 1;
  point.most_observations = 1;
  auto handle = map_points_->insert(point);
  if (!handle) {
    return Error{ErrorCode::kCapacityExceeded,
                 "local map full: " + std::to_string(kMaxMapPoints) + " map points; cull before creating more"};
  }
  kf->map_point[keypoint] = *handle;
  kf->has_map_point[keypoint] = true;
  MapEvent created;
  created.type = MapEventType::kPointCreated;
  created.keypoint = keypoint;
  created.keyframe = kf->id;
  created.point = id;
  if (!kf->anchor) report(created);
  return *handle;
}

Status LocalMap::addObservation(PoolHandle keyframe, std::uint16_t keypoint, PoolHandle map_point) {
  KeyframeData* kf = keyframes_->get(keyframe);
  MapPointData* mp = map_points_->get(map_point);
  if (kf == nullptr || mp == nullptr) return Error{ErrorCode::kNotFound, "addObservation: stale or unknown handle"};
  if (keypoint >= kf->keypoint_count || kf->has_map_point[keypoint]) {
    return Error{ErrorCode::kInvalidArgument, "addObservation: keypoint " + std::to_string(keypoint) + " of keyframe " +
                                                  kf->id.toString() + " is out of range or taken"};
  }
  for (std::uint16_t k = 0; k < kf->keypoint_count; ++k) {
    if (kf->has_map_point[k] && kf->map_point[k] == map_point) {
      return Error{ErrorCode::kInvalidArgument, "addObservation: map point " + mp->id.toString() +
                                                    " is already observed by keyframe " + kf->id.toString()};
    }
  }
  kf->map_point[keypoint] = map_point;
  kf->has_map_point[keypoint] = true;
  ++mp->observation_count;
  mp->most_observations = std::max(mp->most_observations, mp->observation_count);
  MapEvent added;
  added.type = MapEventType::kObservationAdded;
  added.keypoint = keypoint;
  added.keyframe = kf->id;
  added.point = mp->id;
  if (!kf->anchor && !mp->from_server) report(added);
  return Status::Ok();
}

Result<int> LocalMap::mergeMapPoints(PoolHandle keep, PoolHandle drop) {
  MapPointData* kept = map_points_->get(keep);
  const MapPointData* dropped = map_points_->get(drop);
  if (kept == nullptr || dropped == nullptr)
    return Error{ErrorCode::kNotFound, "mergeMapPoints: stale or unknown handle"};
  if (keep == drop) return Error{ErrorCode::kInvalidArgument, "mergeMapPoints: a point cannot be merged into itself"};
  kept->visible += dropped->visible;
  kept->found += dropped->found;
  // One event says it all: the observations of `drop` move to `keep` (or go, where a keyframe has both).
  MapEvent merged;
  merged.type = MapEventType::kPointsMerged;
  merged.point = dropped->id;
  merged.other = kept->id;
  if (!kept->from_server && !dropped->from_server) report(merged);
  MapEventSink* const sink = events_;
  events_ = nullptr;  // the removal of `drop` below is part of the merge
  int moved = 0;
  keyframes_->forEach([&](PoolHandle h, KeyframeData& kf) {
    int drop_at = -1;
    bool observes_keep = false;
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (!kf.has_map_point[k]) continue;
      if (kf.map_point[k] == drop) drop_at = k;
      if (kf.map_point[k] == keep) observes_keep = true;
    }
    if (drop_at < 0) return;
    const auto k = static_cast<std::uint16_t>(drop_at);
    detach(h, k);
    if (!observes_keep) {
      kf.map_point[k] = keep;
      kf.has_map_point[k] = true;
      ++kept->observation_count;
      kept->most_observations = std::max(kept->most_observations, kept->observation_count);
      ++moved;
    }
  });
  const Status removed = removeMapPoint(drop);
  events_ = sink;
  if (!removed.ok()) return removed.error();
  return moved;
}

Status LocalMap::removeMapPoint(PoolHandle map_point, MapEventReason reason) {
  const MapPointData* mp = map_points_->get(map_point);
  if (mp == nullptr) return Error{ErrorCode::kNotFound, "removeMapPoint: stale or unknown handle"};
  MapEvent gone;
  gone.type = MapEventType::kPointRemoved;
  gone.reason = reason;
  gone.point = mp->id;
  if (!mp->from_server) report(gone);
  keyframes_->forEach([&](PoolHandle, KeyframeData& kf) {
    for (std::uint16_t k = 0; k < kf.keypoint_count; ++k) {
      if (kf.has_map_point[k] && kf.map_point[k] == map_point) kf.has_map_point[k] = false;
    }
  });
  map_points_->erase(map_point);
  return Status::Ok();
}

int LocalMap::cullMapPoints(const CullOptions& options) {
  const std::uint64_t newest = next_sequence_ == 0 ? 0 : next_sequence_ - 1;
  int removed = 0;
  map_points_->forEach([&](PoolHandle handle, const MapPointData& mp) {
    if (mp.from_server) return;  // the server's points leave with the anchors that brought them
    const bool rarely_found = mp.visible >= options.min_visible &&
                              static_cast<double>(mp.found) < options.min_found_ratio * static_cast<double>(mp.visible);
    const bool unconfirmed = newest >= mp.created_at_sequence + options.keyframes_to_prove &&
                             mp.observation_count < options.min_observations;
    if (rarely_found || unconfirmed) {
      // A point that was confirmed once and fell under the threshold because its observers left the bounded map
      // is still a good point: it leaves the local map, but whoever mirrors the map (the server) keeps it.
      const bool outlived = !rarely_found && mp.most_observations >= options.min_observations;
      if (removeMapPoint(handle, outlived ? MapEventReason::kEvicted : MapEventReason::kCulled).ok()) ++removed;
    }
  });
  return removed;
}

Result<Vector3d> LocalMap::pointInWorld(PoolHandle map_point) const {
  const MapPointData* mp = map_points_->get(map_point);
  if (mp == nullptr) return Error{ErrorCode::kNotFound, "pointInWorld: stale or unknown map point handle"};
  const KeyframeData* kf = keyframes_->get(mp->reference);
  if (kf == nullptr) return Error{ErrorCode::kInternal, "map point " + mp->id.toString() + " lost its reference"};
  if (!(mp->inverse_depth > 0.0)) {
    return Error{ErrorCode::kDegenerate, "map point " + mp->id.toString() + " is at infinity"};
  }
  return kf->T_w_s * (T_s_c_ * Vector3d(mp->bearing_c / mp->inverse_depth));
}

}  // namespace cvislam::agent
