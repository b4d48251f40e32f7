// The read side of the map service (proto/cvislam/v1/map_service.proto): what the server's missions and maps
// hold, as v1 messages. Plain C++ over the messages: service/map_service.cpp serves it over gRPC, tests call it
// directly.
//
// Locking: each function takes a map's read lock only to copy what it needs (MapSnapshot), never while it builds
// or sends messages, so a large GetMap delays ingest into that map by the copy alone.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/features/orb.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::v1 {
class ListMissionsResponse;
class ListMapsResponse;
class GetTrajectoryResponse;
class MapChunk;
}  // namespace cvislam::v1

namespace cvislam::server::maps {

void listMissions(const MissionRegistry& missions, v1::ListMissionsResponse& out);
// kNotFound names a mission the server does not hold.
Status listMaps(const MissionRegistry& missions, const std::string& mission, v1::ListMapsResponse& out);
// The agent's keyframes in every map of the mission, by time. kNotFound for an unknown mission, or an agent
// that has no keyframe in it.
Status getTrajectory(const MissionRegistry& missions, const std::string& mission, AgentId agent,
                     v1::GetTrajectoryResponse& out);

struct SnapshotOptions {
  bool observations = false;  // each keyframe's keypoints that observe a point
  bool descriptors = false;   // each point's descriptor
};

// One map as it was at one moment: the parts the map service sends, copied under the map's read lock.
struct MapSnapshot {
  struct Observation {
    std::uint16_t keypoint = 0;
    Eigen::Vector2f px = Eigen::Vector2f::Zero();  // cam0, as detected (distorted)
    MapPointId point;
  };
  struct Keyframe {
    KeyframeId id;
    std::uint32_t agent_map = 0;
    std::int64_t t_ns = 0;
    geometry::SE3d T_m_s;
    Eigen::Vector3d v_m = Eigen::Vector3d::Zero();
    imu::ImuBias bias;
    bool refined = false;
    std::uint32_t keypoints = 0;
    std::uint32_t observed_points = 0;
    std::vector<Observation> observations;  // with SnapshotOptions::observations
  };
  struct Point {
    MapPointId id;
    Eigen::Vector3d p_m = Eigen::Vector3d::Zero();
    KeyframeId reference;
    std::uint32_t observations = 0;
    features::Descriptor descriptor{};  // zero without SnapshotOptions::descriptors
  };

  std::string mission;
  MapId map_id = 0;
  MapOrigin origin;
  std::vector<AgentId> agents;
  std::size_t observations = 0;
  std::size_t covisibility_edges = 0;
  std::vector<Keyframe> keyframes;  // by id
  std::vector<Point> points;        // by id
  bool descriptors = false;
};

// kNotFound names an unknown mission or a map id the stack does not hold now (merged away or never made).
Result<MapSnapshot> snapshotMap(const MissionRegistry& missions, const std::string& mission, MapId map_id,
                                const SnapshotOptions& options = {});
// Every map of the mission, by id (none when it has none yet); kNotFound for an unknown mission.
Result<std::vector<MapSnapshot>> snapshotMission(const MissionRegistry& missions, const std::string& mission,
                                                 const SnapshotOptions& options = {});

// Cuts a snapshot into GetMap's chunks: chunk 0 carries the map's summary; then keyframes, then points, as
// many per chunk as fit into `max_chunk_bytes` of serialized message (an item larger than that goes alone, so
// every chunk makes progress). The last chunk says so.
class MapChunker {
 public:
  static constexpr std::size_t kDefaultChunkBytes = 1U << 20U;
  static constexpr std::size_t kMinChunkBytes = 4096;
  // gRPC clients receive at most 4 MiB per message unless they raise it: stay under that.
  static constexpr std::size_t kMaxChunkBytes = (4U << 20U) - 4096U;

  // kInvalidArgument when max_chunk_bytes is outside [kMinChunkBytes, kMaxChunkBytes] (0 takes the default).
  static Result<MapChunker> create(MapSnapshot snapshot, std::size_t max_chunk_bytes);

  // Fills the next chunk; false once the last one went.
  bool next(v1::MapChunk& chunk);

 private:
  MapChunker(MapSnapshot snapshot, std::size_t max_chunk_bytes)
      : snapshot_(std::move(snapshot)), max_bytes_(max_chunk_bytes) {}

  MapSnapshot snapshot_;
  std::size_t max_bytes_;
  std::uint32_t index_ = 0;
  std::size_t next_keyframe_ = 0;
  std::size_t next_point_ = 0;
  bool done_ = false;
};

}  // namespace cvislam::server::maps
