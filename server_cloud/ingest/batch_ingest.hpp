// Ingest of one MapBatch from an agent: decode, check every part against what the server holds of the agent,
// then apply it to the agent's server maps. A batch is applied whole or not at all: when a check fails,
// nothing has changed, and the error names the part and the id.
//
// Positions and states arrive in the agent's world frame and are stored in the server map's frame through
// the agent map's T_m_w (identity until a merge).
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "common/core/result.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::v1 {
class MapBatch;
}

namespace cvislam::server {

struct IngestLimits {
  int max_keypoints_per_keyframe = 4096;
  int max_imu_samples_per_keyframe = 20000;  // 100 s at 200 Hz
  std::uint32_t max_maps_per_agent = 1024;
};

struct IngestReport {
  int keyframes = 0;
  int points = 0;
  int observations = 0;
  int merges = 0;
  int keyframe_updates = 0;
  int point_updates = 0;
  int removed_points = 0;
  int removed_keyframes = 0;
  int maps_opened = 0;
  int duplicate_objects = 0;     // keyframes or points sent in full again: dropped
  int observations_refused = 0;  // a second keypoint of one keyframe on the same point: dropped
  int imu_links_missing = 0;     // the IMU predecessor is not held (or its samples do not cover the gap)
  double map_lock_wait_ms = 0;   // waiting for the write locks of the maps it touches
  std::vector<std::pair<MapId, KeyframeId>> added_keyframes;
  // For place recognition and the back-end: the keyframes added with their agent's refined state, and those sent
  // before their local BA (ServerKeyframe::awaiting_local_ba) whose update came in this batch.
  std::vector<std::pair<MapId, KeyframeId>> keyframes_ready;
  std::vector<KeyframeId> removed_keyframe_ids;
  std::vector<MapId> removed_keyframe_maps;  // the map each of removed_keyframe_ids was in
};

// What the store keeps of a batch: all of it but the live pose, which belongs to no map and differs each time an
// agent resends a batch after a reconnect (the store compares a resend's bytes with what it holds).
std::string storedBody(const v1::MapBatch& batch);

// `agent` is the caller's (locked) record of the agent; its sensors must be known (a Hello came first).
// `commit`, when set, runs once every check has passed and before anything changes (no map is locked then); when
// it fails, ingest returns its error and nothing has changed.
Result<IngestReport> ingestBatch(const v1::MapBatch& batch, AgentRecord& agent, MapStack& stack,
                                 const IngestLimits& limits, const std::function<Status()>& commit = {});

}  // namespace cvislam::server
