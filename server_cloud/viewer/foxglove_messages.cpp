#include "server_cloud/viewer/foxglove_messages.hpp"

#include <array>
#include <cstring>

#include <nlohmann/json.hpp>

namespace cvislam::server::viewer {
namespace {

using nlohmann::json;

// Schema building blocks: an object whose listed properties are all required.
json object(std::string_view title, json properties) {
  json required = json::array();
  for (const auto& item : properties.items()) required.push_back(item.key());
  json out = {{"type", "object"}, {"properties", std::move(properties)}, {"required", std::move(required)}};
  if (!title.empty()) out["title"] = std::string(title);
  return out;
}
json number() {
  return {{"type", "number"}};
}
json integer() {
  return {{"type", "integer"}, {"minimum", 0}};
}
json text() {
  return {{"type", "string"}};
}
json boolean() {
  return {{"type", "boolean"}};
}
json arrayOf(json items) {
  return {{"type", "array"}, {"items", std::move(items)}};
}
json timeSchema() {
  return object("time", {{"sec", integer()}, {"nsec", {{"type", "integer"}, {"minimum", 0}, {"maximum", 999999999}}}});
}
json vector3Schema() {
  return object("foxglove.Vector3", {{"x", number()}, {"y", number()}, {"z", number()}});
}
json point3Schema() {
  return object("foxglove.Point3", {{"x", number()}, {"y", number()}, {"z", number()}});
}
json quaternionSchema() {
  return object("foxglove.Quaternion", {{"x", number()}, {"y", number()}, {"z", number()}, {"w", number()}});
}
json poseSchema() {
  return object("foxglove.Pose", {{"position", vector3Schema()}, {"orientation", quaternionSchema()}});
}
json colorSchema() {
  return object("foxglove.Color", {{"r", number()}, {"g", number()}, {"b", number()}, {"a", number()}});
}
json topLevel(json schema, std::string_view title) {
  schema["$schema"] = "https://json-schema.org/draft/2020-12/schema";
  schema["title"] = std::string(title);
  return schema;
}

json sceneUpdateSchema() {
  const json cube =
      object("foxglove.CubePrimitive", {{"pose", poseSchema()}, {"size", vector3Schema()}, {"color", colorSchema()}});
  const json line = object("foxglove.LinePrimitive", {{"type", {{"type", "integer"}, {"enum", {0, 1, 2}}}},
                                                      {"pose", poseSchema()},
                                                      {"thickness", number()},
                                                      {"scale_invariant", boolean()},
                                                      {"points", arrayOf(point3Schema())},
                                                      {"color", colorSchema()},
                                                      {"colors", arrayOf(colorSchema())},
                                                      {"indices", arrayOf(integer())}});
  const json key_value = object("foxglove.KeyValuePair", {{"key", text()}, {"value", text()}});
  const json entity =
      object("foxglove.SceneEntity", {{"timestamp", timeSchema()},
                                      {"frame_id", text()},
                                      {"id", text()},
                                      {"lifetime", object("duration", {{"sec", integer()}, {"nsec", integer()}})},
                                      {"frame_locked", boolean()},
                                      {"metadata", arrayOf(key_value)},
                                      {"arrows", arrayOf({{"type", "object"}})},
                                      {"cubes", arrayOf(cube)},
                                      {"spheres", arrayOf({{"type", "object"}})},
                                      {"cylinders", arrayOf({{"type", "object"}})},
                                      {"lines", arrayOf(line)},
                                      {"triangles", arrayOf({{"type", "object"}})},
                                      {"texts", arrayOf({{"type", "object"}})},
                                      {"models", arrayOf({{"type", "object"}})}});
  const json deletion =
      object("foxglove.SceneEntityDeletion",
             {{"timestamp", timeSchema()}, {"type", {{"type", "integer"}, {"enum", {0, 1}}}}, {"id", text()}});
  return object("", {{"deletions", arrayOf(deletion)}, {"entities", arrayOf(entity)}});
}

json pointCloudSchema() {
  const json field = object(
      "foxglove.PackedElementField",
      {{"name", text()}, {"offset", integer()}, {"type", {{"type", "integer"}, {"minimum", 0}, {"maximum", 8}}}});
  return object("", {{"timestamp", timeSchema()},
                     {"frame_id", text()},
                     {"pose", poseSchema()},
                     {"point_stride", integer()},
                     {"fields", arrayOf(field)},
                     {"data", {{"type", "string"}, {"contentEncoding", "base64"}}}});
}

json missionStatsSchema() {
  const json agent = object("", {{"agent", integer()},
                                 {"connected", boolean()},
                                 {"map", integer()},
                                 {"keyframes", integer()},
                                 {"up_bytes", integer()},
                                 {"down_bytes", integer()}});
  const json map =
      object("", {{"map", integer()}, {"keyframes", integer()}, {"points", integer()}, {"agents", arrayOf(integer())}});
  return object("", {{"timestamp", timeSchema()}, {"agents", arrayOf(agent)}, {"maps", arrayOf(map)}});
}

json stamp(std::int64_t t_unix_ns) {
  const std::int64_t t = t_unix_ns < 0 ? 0 : t_unix_ns;
  return {{"sec", t / 1000000000}, {"nsec", t % 1000000000}};
}
// Numbers as float: a viewer needs no more than float's 7 digits, and JSON prints a double with 17 (a third of a
// scene update's bytes).
json num(double v) {
  return static_cast<float>(v);
}
json vec(const Eigen::Vector3d& v) {
  return {{"x", num(v.x())}, {"y", num(v.y())}, {"z", num(v.z())}};
}
json quat(const Eigen::Quaterniond& q) {
  return {{"x", num(q.x())}, {"y", num(q.y())}, {"z", num(q.z())}, {"w", num(q.w())}};
}
json pose(const geometry::SE3d& T) {
  return {{"position", vec(T.translation())}, {"orientation", quat(T.so3().quaternion())}};
}
json colour(const Rgba& c) {
  return {{"r", c.r}, {"g", c.g}, {"b", c.b}, {"a", c.a}};
}

}  // namespace

std::string schemaJson(std::string_view name) {
  json schema;
  if (name == kLogSchema) {
    schema = object("", {{"timestamp", timeSchema()},
                         {"level", {{"type", "integer"}, {"minimum", 0}, {"maximum", 5}}},
                         {"message", text()},
                         {"name", text()},
                         {"file", text()},
                         {"line", integer()}});
  } else if (name == kSceneUpdateSchema) {
    schema = sceneUpdateSchema();
  } else if (name == kPointCloudSchema) {
    schema = pointCloudSchema();
  } else if (name == kPoseInFrameSchema) {
    schema = object("", {{"timestamp", timeSchema()}, {"frame_id", text()}, {"pose", poseSchema()}});
  } else if (name == kPosesInFrameSchema) {
    schema = object("", {{"timestamp", timeSchema()}, {"frame_id", text()}, {"poses", arrayOf(poseSchema())}});
  } else if (name == kFrameTransformSchema) {
    schema = object("", {{"timestamp", timeSchema()},
                         {"parent_frame_id", text()},
                         {"child_frame_id", text()},
                         {"translation", vector3Schema()},
                         {"rotation", quaternionSchema()}});
  } else if (name == kMissionStatsSchema) {
    schema = missionStatsSchema();
  } else {
    return {};
  }
  return topLevel(std::move(schema), name).dump();
}

Rgba agentColour(AgentId agent) {
  // Distinct on a dark background, the first ones most of all (most missions have few agents).
  static constexpr std::array<std::array<float, 3>, 10> kPalette = {{{0.95F, 0.33F, 0.31F},
                                                                     {0.27F, 0.62F, 0.96F},
                                                                     {0.40F, 0.82F, 0.36F},
                                                                     {0.98F, 0.76F, 0.20F},
                                                                     {0.74F, 0.45F, 0.95F},
                                                                     {0.20F, 0.85F, 0.80F},
                                                                     {0.98F, 0.55F, 0.18F},
                                                                     {0.95F, 0.45F, 0.75F},
                                                                     {0.65F, 0.80F, 0.25F},
                                                                     {0.55F, 0.60F, 1.00F}}};
  const auto& c = kPalette[agent % kPalette.size()];
  return {c[0], c[1], c[2], 1.0F};
}

std::string logMessage(std::int64_t t_unix_ns, LogLevel level, std::string_view message) {
  return json{{"timestamp", stamp(t_unix_ns)},
              {"level", static_cast<int>(level)},
              {"message", std::string(message)},
              {"name", "cvislam_server"},
              {"file", ""},
              {"line", 0}}
      .dump();
}

std::string poseInFrame(std::int64_t t_unix_ns, std::string_view frame_id, const geometry::SE3d& T_frame_body) {
  return json{{"timestamp", stamp(t_unix_ns)}, {"frame_id", std::string(frame_id)}, {"pose", pose(T_frame_body)}}
      .dump();
}

std::string posesInFrame(std::int64_t t_unix_ns, std::string_view frame_id,
                         const std::vector<geometry::SE3d>& T_frame_bodies) {
  json poses = json::array();
  for (const auto& T : T_frame_bodies) poses.push_back(pose(T));
  return json{{"timestamp", stamp(t_unix_ns)}, {"frame_id", std::string(frame_id)}, {"poses", std::move(poses)}}.dump();
}

std::string frameTransform(std::int64_t t_unix_ns, std::string_view parent_frame_id, std::string_view child_frame_id,
                           const geometry::SE3d& T_parent_child) {
  return json{{"timestamp", stamp(t_unix_ns)},
              {"parent_frame_id", std::string(parent_frame_id)},
              {"child_frame_id", std::string(child_frame_id)},
              {"translation", vec(T_parent_child.translation())},
              {"rotation", quat(T_parent_child.so3().quaternion())}}
      .dump();
}

std::string pointCloud(std::int64_t t_unix_ns, std::string_view frame_id, const std::vector<Eigen::Vector3f>& points) {
  std::vector<std::uint8_t> bytes(points.size() * 12);
  for (std::size_t i = 0; i < points.size(); ++i) {
    // Little-endian float32, as foxglove's packed fields are.
    std::memcpy(bytes.data() + 12 * i, points[i].data(), 12);
  }
  json fields = json::array();
  for (int i = 0; i < 3; ++i) {
    fields.push_back({{"name", std::string(1, static_cast<char>('x' + i))}, {"offset", 4 * i}, {"type", 7}});
  }
  return json{{"timestamp", stamp(t_unix_ns)},  {"frame_id", std::string(frame_id)},
              {"pose", pose(geometry::SE3d())}, {"point_stride", 12},
              {"fields", std::move(fields)},    {"data", base64(bytes.data(), bytes.size())}}
      .dump();
}

std::string keyframeEntityId(const KeyframeId& id) {
  return "kf/" + std::to_string(id.agent) + "/" + std::to_string(id.counter);
}

std::string sceneUpdate(std::int64_t t_unix_ns, const std::vector<KeyframeEntity>& entities,
                        const std::vector<std::string>& deleted_ids) {
  static constexpr double kCubeM = 0.06;
  json deletions = json::array();
  for (const std::string& id : deleted_ids) {
    deletions.push_back({{"timestamp", stamp(t_unix_ns)}, {"type", 0}, {"id", id}});
  }
  json out_entities = json::array();
  for (const KeyframeEntity& e : entities) {
    json cubes = json::array();
    cubes.push_back({{"pose", pose(e.T_frame_body)},
                     {"size", vec(Eigen::Vector3d::Constant(kCubeM))},
                     {"color", colour(agentColour(e.id.agent))}});
    json lines = json::array();
    if (!e.segments.empty()) {
      json points = json::array();
      for (const auto& p : e.segments) points.push_back(vec(p));
      lines.push_back({{"type", 2},  // LINE_LIST: each pair of points is a segment
                       {"pose", pose(geometry::SE3d())},
                       {"thickness", 1.0},
                       {"scale_invariant", true},
                       {"points", std::move(points)},
                       {"color", colour({0.6F, 0.6F, 0.6F, 0.6F})},
                       {"colors", json::array()},
                       {"indices", json::array()}});
    }
    out_entities.push_back({{"timestamp", stamp(t_unix_ns)},
                            {"frame_id", e.frame_id},
                            {"id", keyframeEntityId(e.id)},
                            {"lifetime", {{"sec", 0}, {"nsec", 0}}},
                            {"frame_locked", false},
                            {"metadata",
                             {{{"key", "agent"}, {"value", std::to_string(e.id.agent)}},
                              {{"key", "map"}, {"value", std::to_string(e.map)}}}},
                            {"arrows", json::array()},
                            {"cubes", std::move(cubes)},
                            {"spheres", json::array()},
                            {"cylinders", json::array()},
                            {"lines", std::move(lines)},
                            {"triangles", json::array()},
                            {"texts", json::array()},
                            {"models", json::array()}});
  }
  return json{{"deletions", std::move(deletions)}, {"entities", std::move(out_entities)}}.dump();
}

std::string missionStats(std::int64_t t_unix_ns, const MissionStatsMessage& stats) {
  json agents = json::array();
  for (const auto& a : stats.agents) {
    agents.push_back({{"agent", a.agent},
                      {"connected", a.connected},
                      {"map", a.map},
                      {"keyframes", a.keyframes},
                      {"up_bytes", a.up_bytes},
                      {"down_bytes", a.down_bytes}});
  }
  json maps = json::array();
  for (const auto& m : stats.maps) {
    maps.push_back({{"map", m.map}, {"keyframes", m.keyframes}, {"points", m.points}, {"agents", m.agents}});
  }
  return json{{"timestamp", stamp(t_unix_ns)}, {"agents", std::move(agents)}, {"maps", std::move(maps)}}.dump();
}

std::string base64(const std::uint8_t* data, std::size_t size) {
  static constexpr char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((size + 2) / 3 * 4);
  std::size_t i = 0;
  for (; i + 3 <= size; i += 3) {
    const std::uint32_t v = (std::uint32_t{data[i]} << 16U) | (std::uint32_t{data[i + 1]} << 8U) | data[i + 2];
    for (int shift = 18; shift >= 0; shift -= 6) out.push_back(kAlphabet[(v >> static_cast<unsigned>(shift)) & 63U]);
  }
  if (const std::size_t rest = size - i; rest > 0) {
    std::uint32_t v = std::uint32_t{data[i]} << 16U;
    if (rest == 2) v |= std::uint32_t{data[i + 1]} << 8U;
    out.push_back(kAlphabet[(v >> 18U) & 63U]);
    out.push_back(kAlphabet[(v >> 12U) & 63U]);
    out.push_back(rest == 2 ? kAlphabet[(v >> 6U) & 63U] : '=');
    out.push_back('=');
  }
  return out;
}

}  // namespace cvislam::server::viewer
