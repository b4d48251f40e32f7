// The agent's YAML config: sections mirror the Options structs. Unknown keys are errors, so that a typo does
// not silently leave a default in place.
#include <set>
#include <string>

#include "agent_rt/runtime/agent.hpp"
#include "common/config/yaml_section.hpp"

namespace cvislam::agent {

using config::YamlSection;

Status loadAgentConfig(const std::filesystem::path& file, AgentOptions& o) {
  auto loaded =
      config::loadSections(file.string(), {"agent", "imu", "orb", "tracking", "mapping", "runtime", "link", "threads"});
  if (!loaded) return loaded.error();
  const YAML::Node& root = *loaded;
  auto section = [&](const char* name) { return YamlSection(root[name], name); };
  const auto in_file = [&](const Status& s) { return s.ok() ? s : Status(s.error().withContext(file.string())); };

  YamlSection agent = section("agent");
  int agent_id = o.agent;
  std::string mode = toString(o.mode);
  agent.read("id", agent_id);
  agent.read("mode", mode);
  if (Status s = agent.finish(); !s.ok()) return in_file(s);
  if (agent_id < 0 || agent_id > 65535)
    return in_file(Error{ErrorCode::kInvalidArgument, "agent.id must be in [0, 65535]"});
  o.agent = static_cast<AgentId>(agent_id);
  auto parsed_mode = parseAgentMode(mode);
  if (!parsed_mode) return in_file(parsed_mode.error());
  o.mode = *parsed_mode;

  YamlSection imu = section("imu");
  imu.read("use", o.use_imu);
  imu.read("noise_inflation", o.imu_noise_inflation);
  imu.read("init_keyframes", o.mapping.imu_init_keyframes);
  imu.read("init_max_keyframes", o.mapping.imu_init_max_keyframes);
  imu.read("init_min_keyframes", o.mapping.imu_init_min_keyframes);
  imu.read("init_scale_agreement", o.mapping.imu_init_scale_agreement);
  imu.read("init_full_window_keyframes", o.mapping.imu_init_full_window_keyframes);
  imu.read("estimate_time_offset", o.mapping.ba.estimate_time_offset);
  imu.read("max_time_offset_s", o.mapping.ba.max_time_offset_s);
  if (Status s = imu.finish(); !s.ok()) return in_file(s);

  YamlSection orb = section("orb");
  orb.read("max_features", o.tracking.orb.max_features);
  orb.read("pyramid_levels", o.tracking.orb.pyramid_levels);
  orb.read("scale_factor", o.tracking.orb.scale_factor);
  orb.read("fast_threshold", o.tracking.orb.fast_threshold);
  orb.read("grid_columns", o.tracking.orb.grid_columns);
  orb.read("grid_rows", o.tracking.orb.grid_rows);
  if (Status s = orb.finish(); !s.ok()) return in_file(s);

  YamlSection tracking = section("tracking");
  tracking.read("search_radius_px", o.tracking.search_radius_px);
  tracking.read("refine_radius_px", o.tracking.refine_radius_px);
  tracking.read("max_descriptor_distance", o.tracking.search.max_distance);
  tracking.read("match_ratio", o.tracking.search.ratio);
  tracking.read("relocalisation_radius_px", o.tracking.relocalisation_radius_px);
  tracking.read("max_frames_between_keyframes", o.tracking.keyframe.max_frames_between);
  tracking.read("max_keyframe_interval_s", o.tracking.keyframe.max_interval_s);
  tracking.read("init_max_frames_between_keyframes", o.tracking.initialisation_max_frames_between);
  tracking.read("min_coverage_ratio", o.tracking.keyframe.min_coverage_ratio);
  tracking.read("min_tracked_points", o.tracking.keyframe.min_tracked_points);
  tracking.read("max_lost_frames", o.tracking.max_lost_frames);
  tracking.read("max_dead_reckoning_s", o.tracking.max_dead_reckoning_s);
  tracking.read("min_inliers", o.tracking.pose.min_inliers);
  tracking.read("max_pose_leverage", o.tracking.pose.max_leverage);
  tracking.read("motion_ba_keyframes", o.tracking.motion_ba_keyframes);
  tracking.read("back_off_when_mapping_busy", o.tracking.lag.back_off);
  tracking.read("max_pending_keyframes", o.tracking.lag.max_pending_keyframes);
  tracking.read("min_tracked_points_when_busy", o.tracking.lag.min_tracked_points_when_busy);
  tracking.read("yield_request_after_s", o.tracking.lag.yield_request_after_s);
  if (Status s = tracking.finish(); !s.ok()) return in_file(s);

  YamlSection mapping = section("mapping");
  mapping.read("max_keyframes", o.mapping.max_keyframes);
  mapping.read("place_keyframes", o.mapping.retention.place_keyframes);
  mapping.read("place_angle_weight_m", o.mapping.retention.angle_weight_m);
  mapping.read("ba_window", o.mapping.ba.window);
  mapping.read("return_full_window_keyframes", o.mapping.return_full_window_keyframes);
  mapping.read("ba_iterations", o.mapping.ba.max_iterations);
  mapping.read("yield_to_waiting_keyframes", o.mapping.yield_to_waiting_keyframes);
  mapping.read("min_covisible", o.mapping.ba.min_covisible);
  mapping.read("triangulation_neighbours", o.mapping.triangulation_neighbours);
  mapping.read("stereo_max_depth_m", o.mapping.stereo.max_depth_m);
  mapping.read("stereo_in_ba", o.mapping.stereo.use_in_ba);
  if (Status s = mapping.finish(); !s.ok()) return in_file(s);

  YamlSection runtime = section("runtime");
  std::string pace = toString(o.pace);
  std::string roudi = o.roudi == RouDiMode::kEmbedded ? "embedded" : "external";
  runtime.read("pace", pace);
  runtime.read("rate", o.rate);
  runtime.read("live_imu_wait_s", o.live_imu_wait_s);
  runtime.read("live_record_frames", o.live_record_frames);
  runtime.read("roudi", roudi);
  runtime.read("progress_interval_s", o.progress_interval_s);
  if (Status s = runtime.finish(); !s.ok()) return in_file(s);
  auto parsed_pace = parsePace(pace);
  if (!parsed_pace) return in_file(parsed_pace.error());
  o.pace = *parsed_pace;
  auto parsed_roudi = parseRouDiMode(roudi);
  if (!parsed_roudi) return in_file(parsed_roudi.error());
  o.roudi = *parsed_roudi;

  YamlSection link = section("link");
  link.read("server", o.link.server);
  link.read("mission", o.link.mission);
  link.read("max_rate_hz", o.link.max_rate_hz);
  link.read("max_batch_bytes", o.link.max_batch_bytes);
  link.read("uplink_window_s", o.link.pacer.window_s);
  link.read("keepalive_timeout_ms", o.link.keepalive_timeout_ms);
  link.read("point_update_min_m", o.link.store.point_update_min_m);
  link.read("keyframe_before_local_ba", o.link.keyframe_before_local_ba);
  link.read("reconnect_max_s", o.link.reconnect_max_s);
  link.read("flush_timeout_s", o.link.flush_timeout_s);
  link.read("use_anchors", o.mapping.downlink.use_anchors);
  link.read("max_anchor_keyframes", o.mapping.downlink.max_anchor_keyframes);
  link.read("max_anchor_points", o.mapping.downlink.max_anchor_points);
  link.read("apply_corrections", o.mapping.downlink.apply_corrections);
  if (Status s = link.finish(); !s.ok()) return in_file(s);
  if (Status s = in_file(o.link.validate()); !s.ok()) return s;

  YamlSection threads = section("threads");
  threads.read("priorities", o.threads.enabled);
  threads.read("lower_others_with_realtime", o.threads.lower_others_with_realtime);
  constexpr int kThreads = 5;
  std::string cpu_text[kThreads];
  ThreadSchedule* schedules[kThreads] = {&o.threads.tracking, &o.threads.loader, &o.threads.mapping, &o.threads.link,
                                         &o.threads.propagation};
  const char* names[kThreads] = {"tracking", "loader", "mapping", "link", "propagation"};
  std::string keys[kThreads][3];
  for (int i = 0; i < kThreads; ++i) {
    keys[i][0] = std::string(names[i]) + "_nice";
    keys[i][1] = std::string(names[i]) + "_realtime_priority";
    keys[i][2] = std::string(names[i]) + "_cpus";
    threads.read(keys[i][0].c_str(), schedules[i]->nice);
    threads.read(keys[i][1].c_str(), schedules[i]->realtime_priority);
    threads.read(keys[i][2].c_str(), cpu_text[i]);
  }
  if (Status s = threads.finish(); !s.ok()) return in_file(s);
  for (int i = 0; i < kThreads; ++i) {
    if (cpu_text[i].empty()) continue;
    auto cpus = parseCpuList(cpu_text[i]);
    if (!cpus) return in_file(cpus.error().withContext("threads." + keys[i][2]));
    schedules[i]->cpus = std::move(cpus).value();
  }
  return in_file(o.threads.validate());
}

}  // namespace cvislam::agent
