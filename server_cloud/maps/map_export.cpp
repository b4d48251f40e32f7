#include "server_cloud/maps/map_export.hpp"

#include <algorithm>
#include <cinttypes>
#include <cstdarg>
#include <cstdio>
#include <limits>
#include <map>

#include <nlohmann/json.hpp>

namespace cvislam::server::maps {

namespace {

__attribute__((format(printf, 2, 3))) void append(std::string& out, const char* format, ...) {
  char line[256];
  va_list args;
  va_start(args, format);
  const int n = std::vsnprintf(line, sizeof(line), format, args);
  va_end(args);
  if (n > 0) out.append(line, std::min<std::size_t>(static_cast<std::size_t>(n), sizeof(line) - 1));
}

std::string ply(const MapSnapshot& s) {
  std::string out;
  out.reserve(64 * s.points.size() + 256);
  out += "ply\nformat ascii 1.0\n";
  out += "comment cvislam map " + std::to_string(s.map_id) + " of mission " + s.mission + ", frame M, metres\n";
  append(out, "element vertex %zu\n", s.points.size());
  out += "property float x\nproperty float y\nproperty float z\nproperty uint observations\nend_header\n";
  for (const auto& p : s.points) append(out, "%.5f %.5f %.5f %u\n", p.p_m.x(), p.p_m.y(), p.p_m.z(), p.observations);
  return out;
}

std::string tum(const std::vector<const MapSnapshot::Keyframe*>& keyframes) {
  std::string out;
  out.reserve(96 * keyframes.size());
  for (const auto* kf : keyframes) {
    const Eigen::Vector3d& t = kf->T_m_s.translation();
    const Eigen::Quaterniond& q = kf->T_m_s.quaternion();
    const std::int64_t s = kf->t_ns / 1000000000;
    const std::int64_t ns = kf->t_ns % 1000000000;
    append(out, "%" PRId64 ".%09" PRId64 " %.6f %.6f %.6f %.9f %.9f %.9f %.9f\n", s, ns, t.x(), t.y(), t.z(), q.x(),
           q.y(), q.z(), q.w());
  }
  return out;
}

std::string summary(const MapSnapshot& s) {
  nlohmann::ordered_json j;
  j["mission"] = s.mission;
  j["map_id"] = s.map_id;
  j["frame"] = {{"origin_agent", s.origin.agent}, {"origin_agent_map", s.origin.agent_map}};
  j["agents"] = s.agents;
  j["keyframes"] = s.keyframes.size();
  j["points"] = s.points.size();
  j["observations"] = s.observations;
  j["covisibility_edges"] = s.covisibility_edges;
  std::size_t refined = 0;
  std::map<AgentId, std::size_t> per_agent;
  std::int64_t t0 = std::numeric_limits<std::int64_t>::max();
  std::int64_t t1 = std::numeric_limits<std::int64_t>::min();
  for (const auto& kf : s.keyframes) {
    refined += kf.refined ? 1 : 0;
    ++per_agent[kf.id.agent];
    t0 = std::min(t0, kf.t_ns);
    t1 = std::max(t1, kf.t_ns);
  }
  j["refined_keyframes"] = refined;
  nlohmann::ordered_json by_agent = nlohmann::ordered_json::object();
  for (const auto& [agent, n] : per_agent) by_agent[std::to_string(agent)] = n;
  j["keyframes_per_agent"] = by_agent;
  if (!s.keyframes.empty()) j["time_span_s"] = {static_cast<double>(t0) * 1e-9, static_cast<double>(t1) * 1e-9};
  if (!s.points.empty()) {
    Eigen::Vector3d lo = s.points.front().p_m;
    Eigen::Vector3d hi = lo;
    for (const auto& p : s.points) {
      lo = lo.cwiseMin(p.p_m);
      hi = hi.cwiseMax(p.p_m);
    }
    j["points_bounding_box_m"] = {{"min", {lo.x(), lo.y(), lo.z()}}, {"max", {hi.x(), hi.y(), hi.z()}}};
  }
  return j.dump(2) + "\n";
}

}  // namespace

std::vector<ExportedFile> exportMaps(const std::vector<MapSnapshot>& snapshots) {
  std::vector<ExportedFile> files;
  for (const MapSnapshot& s : snapshots) {
    const std::string m = std::to_string(s.map_id);
    files.push_back({"map" + m + ".ply", ply(s)});
    std::map<AgentId, std::vector<const MapSnapshot::Keyframe*>> per_agent;
    for (const auto& kf : s.keyframes) per_agent[kf.id.agent].push_back(&kf);
    for (auto& [agent, keyframes] : per_agent) {
      std::sort(keyframes.begin(), keyframes.end(),
                [](const auto* a, const auto* b) { return a->t_ns != b->t_ns ? a->t_ns < b->t_ns : a->id < b->id; });
      files.push_back({"keyframes_agent" + std::to_string(agent) + "_map" + m + ".txt", tum(keyframes)});
    }
    files.push_back({"map" + m + ".json", summary(s)});
  }
  return files;
}

}  // namespace cvislam::server::maps
