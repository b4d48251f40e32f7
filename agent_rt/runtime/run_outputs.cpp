#include "agent_rt/runtime/run_outputs.hpp"

#include <cstdio>
#include <fstream>

#include <nlohmann/json.hpp>

#include "common/dataset/trajectory_io.hpp"

namespace cvislam::agent {
namespace {

// summary.json.
nlohmann::json summaryJson(const AgentRunSummary& summary, const AgentOptions& options, const RunSetup& setup,
                           const MappingStats& mapping_stats) {
  nlohmann::json j = {{"frames", summary.frames},
                      {"tracked_frames", summary.tracked_frames},
                      {"keyframes", summary.keyframes},
                      {"new_maps", summary.new_maps},
                      {"lost_frames", summary.lost_frames},
                      {"unreadable_frames", summary.unreadable_frames},
                      {"imu_gaps", summary.imu_gaps},
                      {"dropped_keyframes", summary.dropped_keyframes},
                      {"deferred_keyframes", summary.deferred_keyframes},
                      {"frames_needing_mapping", summary.frames_needing_mapping},
                      {"most_pending_keyframes", summary.most_pending_keyframes},
                      {"mapping_yield_requests", summary.mapping_yield_requests},
                      {"local_ba_skipped", summary.local_ba_skipped},
                      {"local_ba_stopped_early", summary.local_ba_stopped_early},
                      {"local_ba_yielded_to_tracking", summary.local_ba_yielded_to_tracking},
                      {"imu_initialised_at_s", summary.imu_initialised_at_s},
                      {"tracking_initialised_at_s", summary.tracking_initialised_at_s},
                      {"mean_tracked_points", summary.mean_tracked_points},
                      {"mode", setup.stereo ? "stereo" : "mono"},
                      {"imu_noise_inflation", setup.imu_noise_inflation},
                      {"time_offset",
                       {{"estimated", summary.time_offset_estimated},
                        {"calibrated_ms", summary.time_offset_calibrated_ms},
                        {"final_ms", summary.time_offset_ms}}},
                      {"interrupted", summary.interrupted},
                      {"state_messages_not_sent", summary.state_messages_not_sent},
                      {"wall_s", summary.wall_s}};
  if (summary.live) {
    const FeedFaults& f = summary.live_faults;
    j["live"] = {{"stream", options.embedded_input ? "(embedded)" : options.live},
                 {"frames_lost", f.frames_lost},
                 {"frames_out_of_order", f.frames_out_of_order},
                 {"messages_malformed", f.messages_malformed},
                 {"imu_lost", f.imu_lost},
                 {"imu_out_of_order", f.imu_out_of_order},
                 {"imu_overflow", f.imu_overflow},
                 {"imu_wait_timeouts", f.imu_wait_timeouts},
                 {"stalls", f.stalls},
                 {"driver_restarts", f.driver_restarts},
                 {"frames_not_recorded", summary.frames_not_recorded}};
  }
  if (summary.link_enabled) {
    j["link"] = {
        {"server", options.link.server},
        {"mission", options.link.mission},
        {"flushed", summary.link.flushed},
        {"connections", summary.link.connections},
        {"acked_sequence", summary.link.acked_sequence},
        {"keyframes_unacknowledged", summary.link.backlog.keyframes_unsent + summary.link.backlog.keyframes_unacked},
        {"keyframes_dropped", summary.link.store.keyframes_dropped},
        {"deltas_lost", summary.link.store.deltas_lost},
        {"up_bytes", summary.link.up_bytes},
        {"down_bytes", summary.link.down_bytes}};
    j["downlink"] = mapping_stats.downlinkJson();
  }
  return j;
}

// time_offset.csv: the estimated camera-IMU time offset after each keyframe, at the keyframe's time (as in the
// trajectory files).
Status writeTimeOffsets(const std::filesystem::path& path, const MappingStats& stats, const AgentRunSummary& summary) {
  std::ofstream out(path);
  out << "# t_s offset_ms   (keyframe time on the IMU's clock; t_imu = t_cam + offset)\n";
  char line[64];
  for (const auto& [t_ns, correction_ns] : stats.time_corrections) {
    std::snprintf(line, sizeof(line), "%.6f %.3f\n", static_cast<double>(t_ns) * 1e-9,
                  summary.time_offset_calibrated_ms + static_cast<double>(correction_ns) * 1e-6);
    out << line;
  }
  if (!out) return Error{ErrorCode::kIoError, "cannot write " + path.string()};
  return Status::Ok();
}
}  // namespace

Status writeRunOutputs(const AgentOptions& options, const TrajectoryRecorder& recorder,
                       const MappingStats& mapping_stats, const RunSetup& setup, AgentRunSummary& summary) {
  dataset::Trajectory refined;
  dataset::Trajectory online;
  dataset::Trajectory keyframes;
  recorder.build(refined, online, keyframes);
  summary.trajectory = options.output / "trajectory.txt";
  summary.keyframe_trajectory = options.output / "keyframes.txt";
  summary.latency_json = options.output / "latency.json";
  for (const auto& [path, trajectory] :
       {std::pair{summary.trajectory, &refined}, std::pair{options.output / "trajectory_online.txt", &online},
        std::pair{summary.keyframe_trajectory, &keyframes}}) {
    if (Status s = dataset::writeTrajectory(path, *trajectory, dataset::TrajectoryFormat::kTum); !s.ok()) return s;
  }
  std::ofstream latency(summary.latency_json);
  latency << latencyJson(summary.stages);
  if (!latency) return Error{ErrorCode::kIoError, "cannot write " + summary.latency_json.string()};
  if (summary.time_offset_estimated) {
    if (Status s = writeTimeOffsets(options.output / "time_offset.csv", mapping_stats, summary); !s.ok()) return s;
  }
  std::ofstream json(options.output / "summary.json");
  json << summaryJson(summary, options, setup, mapping_stats).dump(2) << "\n";
  if (!json) return Error{ErrorCode::kIoError, "cannot write " + (options.output / "summary.json").string()};
  return Status::Ok();
}

std::string formatSummary(const AgentRunSummary& s) {
  char text[1024];
  std::snprintf(
      text, sizeof(text),
      "frames %zu, tracked %zu (%.1f %%), keyframes %zu, maps %zu, mean tracked points %.0f\n"
      "IMU initialised at %s, tracking in a final frame from %s, unreadable frames %zu, IMU gaps %zu, frames lost %zu, "
      "keyframes dropped %zu\n"
      "mapping busy: keyframes deferred %zu, frames that needed mapping's answer %zu, most keyframes pending %d\n"
      "mapping asked to yield on %zu frames; local BAs skipped %zu, cut short %zu (for tracking's request %zu)\n"
      "camera-IMU time offset %.2f ms (calibrated %.2f ms)\n",
      s.frames, s.tracked_frames, s.frames > 0 ? 100.0 * s.tracked_frames / s.frames : 0.0, s.keyframes, s.new_maps,
      s.mean_tracked_points,
      s.imu_initialised_at_s < 0 ? "never" : (std::to_string(s.imu_initialised_at_s) + " s").c_str(),
      s.tracking_initialised_at_s < 0 ? "never" : (std::to_string(s.tracking_initialised_at_s) + " s").c_str(),
      s.unreadable_frames, s.imu_gaps, s.lost_frames, s.dropped_keyframes, s.deferred_keyframes,
      s.frames_needing_mapping, s.most_pending_keyframes, s.mapping_yield_requests, s.local_ba_skipped,
      s.local_ba_stopped_early, s.local_ba_yielded_to_tracking, s.time_offset_ms, s.time_offset_calibrated_ms);
  return std::string(text) + formatLatencyTable(s.stages);
}

}  // namespace cvislam::agent
