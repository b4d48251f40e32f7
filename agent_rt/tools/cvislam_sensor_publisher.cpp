// cvislam_sensor_publisher: plays a recording onto the live sensor topics of NAME at sensor pace, as a camera/IMU
// driver would, for `cvislam_agent --live NAME`. Both attach to one iox-roudi (iox-roudi -c deploy/roudi_config.toml).
//
//   cvislam_sensor_publisher (--dataset SEQ_DIR | --mcap BAG.mcap [--calibration F --imu-calibration F])
//                            --name NAME [--rate R] [--mode mono|stereo|auto] [--wait-for-agent S] [--max-frames N]
//                            [--crash-after-frames N]
//   cvislam_sensor_publisher (--dataset SEQ_DIR | ...) --write-calibration DIR
//
// The second form writes the recording's rig as Kalibr files (DIR/camchain-imucam.yaml, DIR/imu.yaml), which is
// what `cvislam_agent --live` reads, and exits.
//
// Every image is decoded straight into a loaned shared-memory chunk, which the agent reads in place. Frames carry the
// camera's own timestamps (a calibration's timeshift_cam_imu is taken off again, as a driver would not know it); the
// IMU samples go out between them in time order. At the end it publishes end-of-stream, which ends the agent's run.
// Exit status: 0 done, 1 the recording or iceoryx failed, 2 bad command line.
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>

#include "agent_rt/ipc/embedded_roudi.hpp"
#include "agent_rt/live/sensor_publisher.hpp"
#include "agent_rt/sources/recording.hpp"
#include "common/dataset/kalibr.hpp"

namespace {

using cvislam::agent::Recording;
using cvislam::agent::live::SensorPublisher;
using Clock = std::chrono::steady_clock;

std::atomic<bool> g_stop{false};
extern "C" void onSignal(int /*signal*/) {
  g_stop.store(true);
}

struct PlayOptions {
  double rate = 1.0;
  bool stereo = false;
  std::size_t max_frames = 0;
  std::size_t crash_after_frames = 0;  // 0: never
  bool quiet = false;
};

struct PlayCounts {
  std::size_t frames = 0;
  std::size_t unreadable = 0;
  std::size_t imu = 0;
};

// The frames to play: pairs when stereo, every cam0 frame otherwise.
std::vector<cvislam::dataset::RigFrame> framesToPlay(const Recording& recording, const PlayOptions& options) {
  std::vector<cvislam::dataset::RigFrame> frames;
  for (const auto& f : recording.rigFrames()) {
    if (options.stereo && !f.cam1) continue;
    frames.push_back(f);
  }
  if (options.max_frames > 0 && frames.size() > options.max_frames) frames.resize(options.max_frames);
  return frames;
}

// Plays IMU and frames in time order, each when its sensor time comes (divided by the rate).
PlayCounts play(Recording& recording, SensorPublisher& publisher, const PlayOptions& options) {
  PlayCounts counts;
  const auto frames = framesToPlay(recording, options);
  if (frames.empty()) return counts;
  const auto imu = recording.imu();
  const std::int64_t shift_ns = recording.rig().timeshift_cam_imu_ns;
  // The IMU from a little before the first frame, so that the agent can cover its first interval.
  const std::int64_t t0_ns = frames.front().t_ns;
  std::size_t next_imu = 0;
  while (next_imu < imu.size() && imu[next_imu].t_ns < t0_ns - 100'000'000) ++next_imu;
  const auto start = Clock::now();
  const auto due = [&](std::int64_t t_ns) {
    return start +
           std::chrono::nanoseconds(static_cast<std::int64_t>(static_cast<double>(t_ns - t0_ns) / options.rate));
  };
  auto last_progress = start;
  for (std::size_t i = 0; i < frames.size() && !g_stop.load(); ++i) {
    const auto& frame = frames[i];
    for (; next_imu < imu.size() && imu[next_imu].t_ns <= frame.t_ns && !g_stop.load(); ++next_imu) {
      std::this_thread::sleep_until(due(imu[next_imu].t_ns));
      publisher.publishImu(imu[next_imu]);
      ++counts.imu;
    }
    std::span<std::uint8_t> pixels = publisher.loanFrame();
    if (pixels.empty()) continue;  // counted by the publisher
    const std::size_t one = pixels.size() / (options.stereo ? 2 : 1);
    cvislam::Status st = recording.loadImageInto(0, frame.cam0, pixels.subspan(0, one));
    if (st.ok() && options.stereo) st = recording.loadImageInto(1, *frame.cam1, pixels.subspan(one, one));
    if (!st.ok()) {
      // A driver whose camera gave a bad image sends nothing for it.
      ++counts.unreadable;
      if (!options.quiet)
        std::fprintf(stderr, "[publisher] frame %zu not sent: %s\n", i, st.error().toString().c_str());
      continue;
    }
    std::this_thread::sleep_until(due(frame.t_ns));
    publisher.publishFrame(frame.t_ns - shift_ns);
    ++counts.frames;
    // Between two publishes, where this process holds none of iceoryx's locks: a crash anywhere else can leave
    // one held (they are not robust in iceoryx 2.0), and a test of the agent's recovery would test iceoryx's.
    if (counts.frames == options.crash_after_frames) std::raise(SIGKILL);
    if (!options.quiet && Clock::now() - last_progress > std::chrono::seconds(2)) {
      last_progress = Clock::now();
      std::fprintf(stderr, "[publisher] frame %zu/%zu  t=%.1f s  IMU samples %zu\n", i + 1, frames.size(),
                   static_cast<double>(frame.t_ns - t0_ns) * 1e-9, counts.imu);
    }
  }
  // The IMU up to a little after the last frame, as a driver that keeps running would send it.
  const std::int64_t t_end_ns = frames.back().t_ns + 100'000'000;
  for (; next_imu < imu.size() && imu[next_imu].t_ns <= t_end_ns && !g_stop.load(); ++next_imu) {
    std::this_thread::sleep_until(due(imu[next_imu].t_ns));
    publisher.publishImu(imu[next_imu]);
    ++counts.imu;
  }
  return counts;
}

bool waitForAgent(const SensorPublisher& publisher, double seconds, const std::string& name) {
  if (seconds <= 0.0) return true;
  std::fprintf(stderr, "[publisher] waiting up to %.0f s for an agent on '%s' (cvislam_agent --live %s)\n", seconds,
               name.c_str(), name.c_str());
  const auto deadline =
      Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  // iceoryx gives no event for a new subscriber: this start-up wait alone polls.
  while (!publisher.hasSubscribers() && Clock::now() < deadline && !g_stop.load()) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return publisher.hasSubscribers();
}

// The rig as Kalibr's files; 0 when written.
int writeCalibration(const cvislam::agent::SensorRig& rig, bool stereo, const std::filesystem::path& folder) {
  std::error_code ec;
  std::filesystem::create_directories(folder, ec);
  const cvislam::geometry::SE3d T_b_i = rig.imu ? rig.imu->T_b_i : cvislam::geometry::SE3d();
  const std::optional<cvislam::dataset::CameraCalibration> cam1 = stereo ? rig.cam1 : std::nullopt;
  std::vector<std::pair<std::filesystem::path, std::string>> files = {
      {folder / "camchain-imucam.yaml",
       cvislam::dataset::kalibrCamchainYaml(rig.cam0, cam1, rig.timeshift_cam_imu_ns, T_b_i)}};
  if (rig.imu) files.emplace_back(folder / "imu.yaml", cvislam::dataset::kalibrImuYaml(*rig.imu));
  for (const auto& [path, text] : files) {
    std::ofstream out(path);
    out << text;
    if (!out) {
      std::cerr << "cvislam_sensor_publisher: cannot write " << path.string() << "\n";
      return 1;
    }
    std::fprintf(stderr, "[publisher] wrote %s\n", path.string().c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"cvislam_sensor_publisher: plays a recording onto the live sensor topics of NAME, as a driver would"};
  cvislam::agent::RecordingOptions recording_options;
  std::string dataset;
  std::string mcap;
  std::string calibration;
  std::string imu_calibration;
  std::string name;
  std::string mode = "auto";
  double wait_for_agent_s = 30.0;
  PlayOptions play_options;
  auto* dataset_option = app.add_option("--dataset", dataset, "Sequence folder that holds mav0 (EuRoC/ASL layout)");
  auto* mcap_option =
      app.add_option("--mcap", mcap, "ROS 2 bag in MCAP; needs --calibration")->check(CLI::ExistingFile);
  dataset_option->excludes(mcap_option);
  app.add_option("--cam0-topic", recording_options.topics.cam0, "With --mcap: cam0's image topic [/cam0/image_raw]");
  app.add_option("--cam1-topic", recording_options.topics.cam1, "With --mcap: cam1's image topic [/cam1/image_raw]");
  app.add_option("--imu-topic", recording_options.topics.imu, "With --mcap: the IMU topic [/imu0]");
  app.add_option("--calibration", calibration, "Kalibr camera chain (the frames' sizes and timeshift_cam_imu)")
      ->check(CLI::ExistingFile);
  app.add_option("--imu-calibration", imu_calibration, "Kalibr IMU file")->check(CLI::ExistingFile);
  app.add_option("--name", name, "The stream's NAME, as cvislam_agent --live NAME takes it");
  app.add_option("--rate", play_options.rate, "Playback speed: 2 plays twice as fast [1]")->check(CLI::PositiveNumber);
  app.add_option("--mode", mode, "stereo: publish pairs; mono: cam0 only; auto: pairs when there is a cam1 [auto]");
  app.add_option("--wait-for-agent", wait_for_agent_s,
                 "Seconds to wait for an agent to subscribe before playing; 0: play at once, as a driver would [30]");
  app.add_option("--max-frames", play_options.max_frames, "Stop after this many frames (0 = all)");
  app.add_flag("--quiet", play_options.quiet, "No progress output");
  app.add_option("--crash-after-frames", play_options.crash_after_frames,
                 "For tests of a driver crash: kill this process (SIGKILL, no end-of-stream) right after frame N")
      ->group("Testing");
  std::string write_calibration;
  app.add_option("--write-calibration", write_calibration,
                 "Write the recording's rig as Kalibr files (DIR/camchain-imucam.yaml, DIR/imu.yaml) for "
                 "cvislam_agent --live --calibration --imu-calibration, and exit");
  CLI11_PARSE(app, argc, argv);

  if (dataset.empty() == mcap.empty()) {
    std::cerr << "cvislam_sensor_publisher: give the recording: --dataset DIR or --mcap FILE\n";
    return 2;
  }
  if (name.empty() && write_calibration.empty()) {
    std::cerr << "cvislam_sensor_publisher: --name NAME is required (the stream cvislam_agent --live NAME reads)\n";
    return 2;
  }
  if (mode != "auto" && mode != "mono" && mode != "stereo") {
    std::cerr << "cvislam_sensor_publisher: --mode '" << mode << "': use mono, stereo or auto\n";
    return 2;
  }
  recording_options.dataset = dataset;
  recording_options.mcap = mcap;
  recording_options.calibration = calibration;
  recording_options.imu_calibration = imu_calibration;
  recording_options.require_imu = false;
  auto recording = cvislam::agent::openRecording(recording_options);
  if (!recording) {
    std::cerr << "cvislam_sensor_publisher: " << recording.error().toString() << "\n";
    return 1;
  }
  const auto& rig = (*recording)->rig();
  if (mode == "stereo" && !rig.cam1) {
    std::cerr << "cvislam_sensor_publisher: " << (*recording)->describe() << " has no cam1: use --mode mono\n";
    return 2;
  }
  play_options.stereo = mode == "stereo" || (mode == "auto" && rig.cam1.has_value());
  if (!write_calibration.empty()) return writeCalibration(rig, play_options.stereo, write_calibration);

  // The process id makes each start of a driver a new iceoryx process. Under its old name, RouDi would first clean
  // up the driver's last run, and a run killed inside a publish can leave iceoryx 2.0's (non-robust) port lock held:
  // that cleanup then blocks RouDi for every process on the machine.
  const std::string runtime_name = "cvislam_publisher_" + name + "_" + std::to_string(::getpid());
  if (auto s = cvislam::agent::attachToExternalRouDi(runtime_name); !s.ok()) {
    std::cerr << "cvislam_sensor_publisher: " << s.error().toString() << "\n";
    return 1;
  }
  cvislam::agent::live::SensorPublisherOptions publisher_options;
  publisher_options.stream = name;
  publisher_options.width = static_cast<std::uint32_t>(rig.cam0.width);
  publisher_options.height = static_cast<std::uint32_t>(rig.cam0.height);
  publisher_options.cameras = play_options.stereo ? 2 : 1;
  auto publisher = SensorPublisher::create(publisher_options);
  if (!publisher) {
    std::cerr << "cvislam_sensor_publisher: " << publisher.error().toString() << "\n";
    return 2;
  }
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  if (!waitForAgent(**publisher, wait_for_agent_s, name) && !g_stop.load()) {
    std::fprintf(stderr, "[publisher] no agent subscribed within %.0f s; playing anyway\n", wait_for_agent_s);
  }
  if (!play_options.quiet) {
    std::fprintf(stderr, "[publisher] '%s': %s, %s %dx%d, %zu IMU samples, at %.2fx\n", name.c_str(),
                 (*recording)->describe().c_str(), play_options.stereo ? "stereo" : "mono", rig.cam0.width,
                 rig.cam0.height, (*recording)->imu().size(), play_options.rate);
  }
  const PlayCounts counts = play(**recording, **publisher, play_options);
  (*publisher)->publishEndOfStream();
  const auto& stats = (*publisher)->stats();
  std::fprintf(stderr,
               "[publisher] %s: %zu frames and %zu IMU samples sent; %zu frames unreadable; no shared memory for %llu "
               "frames and %llu IMU samples\n",
               g_stop.load() ? "stopped" : "end of stream", counts.frames, counts.imu, counts.unreadable,
               static_cast<unsigned long long>(stats.frames_not_loaned),
               static_cast<unsigned long long>(stats.imu_not_loaned));
  // The end-of-stream chunk stays readable after this process goes; a moment lets the agent take it first.
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  return 0;
}
