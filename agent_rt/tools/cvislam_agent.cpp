// cvislam_agent: the onboard visual-inertial odometry of one agent, on a recording or a driver's live topics.
//
//   cvislam_agent (--dataset SEQ_DIR | --mcap BAG.mcap | --live NAME) --output OUT_DIR [--config FILE]
//                 [--mode mono|stereo|auto]
//                 [--calibration KALIBR_CAMCHAIN --imu-calibration KALIBR_IMU]
//                 [--cam0-topic T --cam1-topic T --imu-topic T]
//                 [--pace realtime|fast|sync] [--rate R] [--roudi embedded|external] [--agent-id N]
//                 [--server HOST:PORT --mission NAME]
//
// Writes OUT_DIR/trajectory.txt (TUM, every tracked frame on its keyframe's refined pose),
// trajectory_online.txt (as tracked live), keyframes.txt, latency.json and summary.json, and prints the
// latency table; with --server also link.json and link_timeline.csv. SIGINT/SIGTERM stop it early; the outputs
// are still written.
// Exit status: 0 done, 1 the run could not start or its outputs could not be written, 2 bad command line.
#include <atomic>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <string>

#include <CLI/CLI.hpp>

#include "agent_rt/runtime/agent.hpp"
#include "common/core/text.hpp"

namespace {
std::atomic<bool> g_stop{false};
extern "C" void onSignal(int /*signal*/) {
  g_stop.store(true);
}

// The command line: its options, and what they change in the agent's options (after the config file).
struct CommandLine {
  std::string dataset;
  std::string output;
  std::string config;
  std::string mode;
  std::string pace;
  std::string roudi;
  double rate = 0.0;
  int agent_id = -1;
  std::string server;
  std::string mission;
  bool no_imu = false;
  std::string time_offset;
  bool quiet = false;
  bool trace_mapping = false;
  std::filesystem::path trace_file;
  std::size_t trace_events_per_thread = 0;
  bool no_priorities = false;
  std::size_t max_frames = 0;
  std::string mcap;
  cvislam::agent::McapTopics topics;
  std::string live;
  std::string calibration;
  std::string imu_calibration;
  std::string token;
  std::string tls_ca;

  void define(CLI::App& app);
  // False, with the reason on stderr, when a value is wrong.
  bool applyTo(cvislam::agent::AgentOptions& options);
};

void CommandLine::define(CLI::App& app) {
  auto* dataset_option = app.add_option("--dataset", dataset, "Sequence folder that holds mav0 (EuRoC/ASL layout)");
  auto* mcap_option =
      app.add_option("--mcap", mcap,
                     "ROS 2 bag in MCAP (sensor_msgs/msg/Image mono8, rgb8 or bgr8, and sensor_msgs/msg/Imu, CDR); "
                     "needs --calibration and --imu-calibration")
          ->check(CLI::ExistingFile);
  dataset_option->excludes(mcap_option);
  auto* live_option = app.add_option(
      "--live", live,
      "Track a driver's live topics NAME (cvislam_sensor_publisher --name NAME plays a recording onto them); attaches "
      "to an iox-roudi (implies --roudi external), needs --calibration and --imu-calibration, and runs until the "
      "driver ends the stream or SIGINT");
  live_option->excludes(dataset_option)->excludes(mcap_option);
  app.add_option("--cam0-topic", topics.cam0, "With --mcap: cam0's image topic [/cam0/image_raw]");
  app.add_option("--cam1-topic", topics.cam1, "With --mcap: cam1's image topic; empty: none [/cam1/image_raw]");
  app.add_option("--imu-topic", topics.imu, "With --mcap: the IMU topic [/imu0]");
  app.add_option("--calibration", calibration,
                 "Kalibr camera chain (camchain-imucam.yaml: cam0, cam1 with intrinsics, distortion, T_cam_imu, "
                 "timeshift_cam_imu) used instead of the recording's cam0/cam1 sensor.yaml")
      ->check(CLI::ExistingFile);
  app.add_option("--imu-calibration", imu_calibration,
                 "Kalibr IMU file (imu.yaml: noise densities, random walks, update_rate) used instead of the "
                 "recording's imu0/sensor.yaml")
      ->check(CLI::ExistingFile);
  app.add_option("--output", output, "Folder for trajectories, latency profile and summary (created)")->required();
  app.add_option("--config", config, "YAML config (see deploy/agent_config.yaml); command-line options win");
  app.add_option("--mode", mode, "mono, stereo, or auto = stereo when mav0/cam1 exists [auto]");
  app.add_option("--pace", pace,
                 "realtime: frames at the sensor rate; fast: as fast as tracking goes; sync: tracking waits for "
                 "mapping after each keyframe (reproducible) [realtime]");
  app.add_option("--rate", rate, "Playback speed for --pace realtime [1]");
  app.add_option("--roudi", roudi, "embedded: RouDi inside this process; external: attach to iox-roudi [embedded]");
  app.add_option("--agent-id", agent_id, "This agent's id, in every keyframe and map point id [0]");
  app.add_option("--server", server,
                 "Stream the map to the cvislam_server at HOST:PORT; without it the agent runs alone. The agent never "
                 "waits for the server: it reconnects by itself and resends what was not acknowledged");
  app.add_option("--mission", mission, "Mission name on the server (letters, digits, . _ -) [default]");
  app.add_option("--token", token,
                 "The mission's token, when the server has a tokens file [$CVISLAM_TOKEN; none]. The environment "
                 "variable keeps it out of the process list");
  app.add_option("--tls-ca", tls_ca, "Speak TLS, trusting the server certificate's CA in this PEM file [plaintext]");
  app.add_option("--max-frames", max_frames, "Stop after this many frames (0 = all)");
  app.add_flag("--no-imu", no_imu, "Vision only");
  app.add_option("--time-offset", time_offset,
                 "The camera-IMU time offset: estimate (a state of local BA, from the calibration's "
                 "timeshift_cam_imu on; for cameras not synchronised with the IMU) or fixed (the calibration's) "
                 "[config imu.estimate_time_offset; fixed]");
  app.add_flag("--quiet", quiet, "No progress output");
  app.add_flag("--no-priorities", no_priorities,
               "Leave every thread at the process's scheduling (default at --pace realtime: tracking SCHED_FIFO 10 "
               "where allowed and the others at the process's nice value; without that privilege tracking nice 0, "
               "mapping 10, the link 5, the frame loader 2; see the threads section of deploy/agent_config.yaml)");
  app.add_option("--trace", trace_file,
                 "Write a Chrome Trace Event JSON of every thread's stages here at the end (opens in "
                 "https://ui.perfetto.dev; cvislam_trace joins it with the server's)");
  app.add_option("--trace-events-per-thread", trace_events_per_thread,
                 "Events each thread keeps for --trace, the newest (about 104 bytes each, reserved at start) [65536]");
  app.add_flag("--trace-mapping", trace_mapping,
               "One line per keyframe on stderr: matches linked, points fused/made/culled, stereo matches, local BA "
               "size, cam1 factors and rejected stereo mismatches, cost");
}

bool CommandLine::applyTo(cvislam::agent::AgentOptions& options) {
  if (dataset.empty() && mcap.empty() && live.empty()) {
    std::cerr << "cvislam_agent: give the sensor input: --dataset DIR (EuRoC/ASL folder), --mcap FILE (ROS 2 bag) or "
                 "--live NAME (a driver's topics)\n";
    return false;
  }
  options.dataset = dataset;
  options.mcap = mcap;
  options.live = live;
  if (!live.empty()) options.roudi = cvislam::agent::RouDiMode::kExternal;
  options.topics = topics;
  options.calibration = calibration;
  options.imu_calibration = imu_calibration;
  options.output = output;
  // --mode, --pace, --roudi: parsed by the agent's own parsers, which name the accepted values.
  const auto parse = [](const std::string& text, const char* flag, auto parser, auto& target) {
    if (text.empty()) return true;
    auto value = parser(text);
    if (!value) {
      std::cerr << "cvislam_agent: --" << flag << ": " << value.error().message() << "\n";
      return false;
    }
    target = *value;
    return true;
  };
  if (!parse(mode, "mode", cvislam::agent::parseAgentMode, options.mode) ||
      !parse(pace, "pace", cvislam::agent::parsePace, options.pace) ||
      !parse(roudi, "roudi", cvislam::agent::parseRouDiMode, options.roudi)) {
    return false;
  }
  if (rate > 0.0) options.rate = rate;
  if (agent_id >= 0) {
    if (agent_id > 65535) {
      std::cerr << "cvislam_agent: --agent-id must be in [0, 65535]\n";
      return false;
    }
    options.agent = static_cast<cvislam::AgentId>(agent_id);
  }
  if (no_imu) options.use_imu = false;
  if (!time_offset.empty()) {
    if (time_offset != "estimate" && time_offset != "fixed") {
      std::cerr << "cvislam_agent: --time-offset is estimate or fixed, not '" << time_offset << "'\n";
      return false;
    }
    options.mapping.ba.estimate_time_offset = time_offset == "estimate";
  }
  if (!server.empty()) options.link.server = server;
  if (!mission.empty()) options.link.mission = mission;
  if (token.empty()) {
    if (const char* from_env = std::getenv("CVISLAM_TOKEN"); from_env != nullptr) token = from_env;
  }
  options.link.token = token;
  if (!tls_ca.empty()) {
    auto pem = cvislam::text::readPemFile(tls_ca, "CA file (--tls-ca)");
    if (!pem) {
      std::cerr << "cvislam_agent: " << pem.error().message() << "\n";
      return false;
    }
    options.link.tls_ca_pem = std::move(pem).value();
  }
  options.quiet = quiet;
  if (no_priorities) options.threads.enabled = false;
  options.trace_mapping = trace_mapping;
  options.trace_file = trace_file;
  if (trace_events_per_thread > 0) options.trace_events_per_thread = trace_events_per_thread;
  options.max_frames = max_frames;
  return true;
}

// Runs the agent and prints its summary; the exit status.
int run(const cvislam::agent::AgentOptions& options) {
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  auto summary = cvislam::agent::runAgent(options, g_stop);
  if (!summary) {
    std::cerr << "cvislam_agent: " << summary.error().toString() << "\n";
    return 1;
  }
  std::cout << cvislam::agent::formatSummary(*summary);
  std::cout << "trajectory: " << summary->trajectory.string()
            << "\nkeyframes: " << summary->keyframe_trajectory.string()
            << "\nlatency: " << summary->latency_json.string() << "\n";
  if (summary->interrupted) std::cout << "interrupted: the outputs hold what was tracked until then\n";
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "cvislam_agent: real-time visual-inertial odometry of one agent, on a recording (EuRoC folder, ROS 2 bag) or "
      "on a driver's live topics"};
  CommandLine command_line;
  command_line.define(app);
  CLI11_PARSE(app, argc, argv);

  cvislam::agent::AgentOptions options;
  if (!command_line.config.empty()) {
    if (auto s = cvislam::agent::loadAgentConfig(command_line.config, options); !s.ok()) {
      std::cerr << "cvislam_agent: " << s.error().toString() << "\n";
      return 2;
    }
  }
  if (!command_line.applyTo(options)) return 2;
  return run(options);
}
