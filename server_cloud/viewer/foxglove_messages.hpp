// The foxglove.* messages the viewer and the recordings carry, JSON-encoded, and the JSON Schemas advertised with
// them. Foxglove, Lichtblick and deploy/viewer read these by schema name; the schemas list the fields that this
// server writes, so that a generic client (or a test with a schema validator) can check every message.
// Plain C++ (no network): the live endpoint, the MCAP recorder and cvislam_mapctl share it.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include <Eigen/Core>

#include "common/core/ids.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::server::viewer {

// Schema names: the foxglove ones, and one of ours for the traffic and count figures.
inline constexpr const char* kLogSchema = "foxglove.Log";
inline constexpr const char* kSceneUpdateSchema = "foxglove.SceneUpdate";
inline constexpr const char* kPointCloudSchema = "foxglove.PointCloud";
inline constexpr const char* kPoseInFrameSchema = "foxglove.PoseInFrame";
inline constexpr const char* kPosesInFrameSchema = "foxglove.PosesInFrame";
inline constexpr const char* kFrameTransformSchema = "foxglove.FrameTransform";
inline constexpr const char* kMissionStatsSchema = "cvislam.MissionStats";

// The JSON Schema (draft 2020-12) of one of the schemas above; empty for an unknown name.
std::string schemaJson(std::string_view schema_name);

struct Rgba {
  float r = 1.0F;
  float g = 1.0F;
  float b = 1.0F;
  float a = 1.0F;
};
// Each agent's colour. deploy/viewer/viewer.js holds the same palette, so that the browser viewer and a Foxglove
// layout show an agent alike.
Rgba agentColour(AgentId agent);

enum class LogLevel : int { kInfo = 2, kWarning = 3, kError = 4 };
std::string logMessage(std::int64_t t_unix_ns, LogLevel level, std::string_view text);

std::string poseInFrame(std::int64_t t_unix_ns, std::string_view frame_id, const geometry::SE3d& T_frame_body);
std::string posesInFrame(std::int64_t t_unix_ns, std::string_view frame_id,
                         const std::vector<geometry::SE3d>& T_frame_bodies);
std::string frameTransform(std::int64_t t_unix_ns, std::string_view parent_frame_id, std::string_view child_frame_id,
                           const geometry::SE3d& T_parent_child);
// x, y, z as float32, 12 bytes a point, base64 in the JSON.
std::string pointCloud(std::int64_t t_unix_ns, std::string_view frame_id, const std::vector<Eigen::Vector3f>& points);

// One keyframe as a scene entity: a cube at its pose in its map's frame, and line segments (pairs of points in that
// frame) to the keyframes it is drawn linked to.
struct KeyframeEntity {
  KeyframeId id;
  std::uint32_t map = 0;
  std::string frame_id;
  geometry::SE3d T_frame_body;
  std::vector<Eigen::Vector3d> segments;  // 2 points per segment
};
// Entity ids: "kf/AGENT/COUNTER".
std::string keyframeEntityId(const KeyframeId& id);
std::string sceneUpdate(std::int64_t t_unix_ns, const std::vector<KeyframeEntity>& entities,
                        const std::vector<std::string>& deleted_ids);

struct MissionStatsMessage {
  struct Agent {
    AgentId agent = 0;
    bool connected = false;
    std::uint32_t map = 0;  // the server map its newest agent map is in (0: none yet)
    std::uint64_t keyframes = 0;
    std::uint64_t up_bytes = 0;
    std::uint64_t down_bytes = 0;
  };
  struct Map {
    std::uint32_t map = 0;
    std::uint64_t keyframes = 0;
    std::uint64_t points = 0;
    std::vector<AgentId> agents;
  };
  std::vector<Agent> agents;
  std::vector<Map> maps;
};
std::string missionStats(std::int64_t t_unix_ns, const MissionStatsMessage& stats);

// Standard base64 (RFC 4648, with padding), as JSON carries foxglove's bytes fields.
std::string base64(const std::uint8_t* data, std::size_t size);

}  // namespace cvislam::server::viewer
