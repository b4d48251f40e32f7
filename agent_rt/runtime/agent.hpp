// The agent process: takes frames from a recording (EuRoC folder, ROS 2 bag) or a driver's live topics, runs
// tracking (the calling thread) and mapping (its own thread) joined by iceoryx, and writes the trajectory, the
// keyframe trajectory and the latency profile. With a server, a link thread streams the map to it.
//
//   loader thread --(bounded ring of preallocated frames)--> tracking --KeyframeMessage (iceoryx)--> mapping
//   or a driver --(live topics, iceoryx, read in place)-->   tracking <--MapSnapshotMessage (iceoryx)-- mapping
//                                    server <--gRPC-- link <--MapDeltaMessage (iceoryx)-- mapping
//
// iceoryx headers stay in agent.cpp.
#pragma once

#include <atomic>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "agent_rt/link/link.hpp"
#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/runtime/frame_feed.hpp"
#include "agent_rt/runtime/latency_profile.hpp"
#include "agent_rt/runtime/live_state.hpp"
#include "agent_rt/runtime/thread_schedule.hpp"
#include "agent_rt/sources/recording.hpp"
#include "agent_rt/tracking/tracker.hpp"
#include "common/core/result.hpp"

namespace cvislam::agent {

enum class AgentMode { kAuto, kMono, kStereo };  // auto: stereo when the sequence has cam1
enum class RouDiMode { kEmbedded, kExternal };
enum class Pace {
  kRealtime,  // frames at the sensor's rate (times `rate`); tracking never waits on mapping
  kFast,      // as fast as tracking goes; waits for mapping only when it cannot go on without its answer
  kSync,      // after each keyframe, tracking waits for mapping's answer: reproducible runs for tests
};

Result<AgentMode> parseAgentMode(const std::string& name);
Result<RouDiMode> parseRouDiMode(const std::string& name);
Result<Pace> parsePace(const std::string& name);
const char* toString(AgentMode mode);
const char* toString(Pace pace);

struct AgentOptions {
  std::filesystem::path dataset;  // the folder that holds mav0, or
  std::filesystem::path mcap;     // a ROS 2 bag in MCAP, or
  std::string live;               // the NAME of a driver's live topics (agent_rt/live/sensor_topics.hpp), or
  bool embedded_input = false;    // frames pushed by the program embedding the agent (AgentHooks::feed)
  McapTopics topics;              // the bag's topics
  // Kalibr calibration files that replace the recording's own (empty: the recording's sensor.yaml files).
  std::filesystem::path calibration;      // camchain-imucam.yaml
  std::filesystem::path imu_calibration;  // imu.yaml
  std::filesystem::path output;
  AgentMode mode = AgentMode::kAuto;
  AgentId agent = 0;
  bool use_imu = true;
  // The sensor.yaml noise densities and random walks are multiplied by this. 0 = automatic: 1 on the project's
  // simulated sequences (their noise is exactly the stated model), 10 on real ones (EuRoC's densities are too small by
  // a factor of 6-12 for preintegration over keyframe intervals: with them as stated, the IMU terms outweigh the
  // reprojections and bend the trajectory).
  double imu_noise_inflation = 0.0;
  TrackerOptions tracking;
  MapperOptions mapping;
  LinkOptions link;  // link.server empty: no server, the agent is the VIO alone
  RouDiMode roudi = RouDiMode::kEmbedded;
  std::string runtime_name;  // default cvislam_agent_<agent>
  Pace pace = Pace::kRealtime;
  double rate = 1.0;  // realtime pace: 2 plays the sequence twice as fast
  double progress_interval_s = 2.0;
  bool quiet = false;
  bool trace_mapping = false;  // one line per keyframe on stderr: links, new points, stereo matches, local BA
  // Chrome Trace Event JSON of every thread's stages, written at the end (common/trace/trace.hpp); empty: none.
  // Each thread keeps its newest trace_events_per_thread events (about 104 bytes each, reserved at start).
  std::filesystem::path trace_file;
  std::size_t trace_events_per_thread = std::size_t{1} << 16;
  std::size_t max_frames = 0;  // 0 = all
  // Live: how long a frame waits for the IMU sample that closes its interval, and how many frames are kept for the
  // trajectory files and the latency profile (their memory is reserved at start; later frames are tracked and
  // published but not written). 72000 is an hour at 20 Hz.
  double live_imu_wait_s = 0.02;
  std::size_t live_record_frames = 72000;
  int frame_ring_size = 4;        // frames the loader reads ahead
  ThreadScheduleOptions threads;  // nice values, real-time priority and CPUs per thread (thread_schedule.hpp)

  [[nodiscard]] Status validate() const;
};

// Reads a YAML config (see deploy/agent_config.yaml) over `options`; names unknown keys and bad values.
Status loadAgentConfig(const std::filesystem::path& file, AgentOptions& options);

struct AgentRunSummary {
  std::size_t frames = 0;
  std::size_t tracked_frames = 0;
  std::size_t keyframes = 0;
  std::size_t new_maps = 0;
  std::size_t lost_frames = 0;
  std::size_t unreadable_frames = 0;
  std::size_t imu_gaps = 0;
  std::size_t dropped_keyframes = 0;
  std::size_t deferred_keyframes = 0;      // asked for by the rules, held back while mapping was busy
  std::size_t frames_needing_mapping = 0;  // lost, or needing a keyframe, while mapping was behind
  int most_pending_keyframes = 0;
  std::size_t mapping_yield_requests = 0;  // frames whose keyframe was overdue: mapping was asked to yield
  // The next keyframe was waiting, or tracking asked (MapperOptions::yield_to_waiting_keyframes, YieldRequests).
  std::size_t local_ba_skipped = 0;
  std::size_t local_ba_stopped_early = 0;        // cut short for the same reasons
  std::size_t local_ba_yielded_to_tracking = 0;  // of those skipped or cut short, because tracking asked
  std::size_t lost_keyframe_messages = 0;
  bool link_enabled = false;
  LinkStatus link;
  double imu_initialised_at_s = -1.0;  // sequence time of the IMU initialisation; -1 never
  // Sequence time of the first frame tracked in a final world frame (with the IMU: after its initialisation, so
  // metric and gravity-aligned); earlier poses are marked in the trajectory files. -1 never.
  double tracking_initialised_at_s = -1.0;
  // The camera-IMU time offset (t_imu = t_cam + offset): the calibration's, and the estimate at the end (the same
  // unless imu.estimate_time_offset).
  bool time_offset_estimated = false;
  double time_offset_calibrated_ms = 0.0;
  double time_offset_ms = 0.0;
  double mean_tracked_points = 0.0;
  double wall_s = 0.0;
  bool interrupted = false;
  bool live = false;
  FeedFaults live_faults;
  std::size_t frames_not_recorded = 0;        // live frames past live_record_frames
  std::uint64_t state_messages_not_sent = 0;  // states that found no free chunk on the state topics
  std::vector<StageSummary> stages;
  std::filesystem::path trajectory;
  std::filesystem::path keyframe_trajectory;
  std::filesystem::path latency_json;
};

// What a program embedding the agent (agent_rt/api) plugs in.
struct AgentHooks {
  // Told every state (each frame's, and with --live the IMU-rate ones) on the thread that made it, besides the
  // agent's state topics (agent_rt/live/state_topics.hpp).
  StateListener* listener = nullptr;
  FrameFeed* feed = nullptr;         // the frames when AgentOptions::embedded_input (the rig from options.calibration)
  std::function<void()> on_running;  // once every thread runs, before the first frame is asked for
};

// Runs the agent to the end of the sequence or until `stop` becomes true; the outputs are written on every
// path that gets past start-up.
Result<AgentRunSummary> runAgent(const AgentOptions& options, const std::atomic<bool>& stop,
                                 const AgentHooks& hooks = {});

std::string formatSummary(const AgentRunSummary& summary);

}  // namespace cvislam::agent
