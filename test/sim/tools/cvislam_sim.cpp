// cvislam_sim: synthetic multi-agent missions in the EuRoC/ASL layout, with exact ground truth.
//
//   cvislam_sim --preset loop --out DIR [--seed S] [--duration SECONDS] [--stereo] [--no-imu-noise]
//               [--pixel-noise SIGMA] [--exposure AMPLITUDE] [--overwrite]
//   cvislam_sim --replay GT_FILE[,GT_FILE...] --out DIR ...
//   cvislam_sim --preset NAME [--seed S] [--duration SECONDS] --fingerprint   (prints the plan's hash; no files)
//
// Exit status: 0 written, 1 the mission could not be planned or written (the message says why), 2 bad command line.
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/camera/camera_model.hpp"
#include "common/core/hash.hpp"
#include "common/dataset/calibration.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"

namespace {

std::string joined(const std::vector<std::string>& names) {
  std::string out;
  for (const std::string& n : names) out += (out.empty() ? "" : ", ") + n;
  return out;
}

// FNV-1a over the mission plan: the hall, every obstacle, and every agent's pose at 10 Hz (micrometres). A
// cache of rendered missions keys on it, so that a changed preset is rendered again rather than reused.
std::string planFingerprint(const cvislam::sim::MissionPlan& plan) {
  cvislam::Fnv1a64 hash;
  const auto mix = [&hash](double value) {  // micrometres, as 8 little-endian bytes
    const auto v = static_cast<std::int64_t>(std::llround(value * 1e6));
    char bytes[8];
    for (int b = 0; b < 8; ++b) bytes[b] = static_cast<char>((v >> (8 * b)) & 0xFF);
    hash.add(std::string_view(bytes, sizeof(bytes)));
  };
  const auto box = [&mix](const cvislam::sim::Box& b) {
    for (int i = 0; i < 3; ++i) {
      mix(b.min_w[i]);
      mix(b.max_w[i]);
    }
  };
  box(plan.layout.hall);
  for (const cvislam::sim::Box& b : plan.layout.obstacles) box(b);
  for (const cvislam::sim::AgentPlan& agent : plan.agents) {
    for (double t = 0.0; t <= plan.duration_s; t += 0.1) {
      const auto T_w_b = agent.trajectory.state(t).T_w_b;
      for (int i = 0; i < 3; ++i) mix(T_w_b.translation()[i]);
      const Eigen::Vector3d r = T_w_b.so3().log();
      for (int i = 0; i < 3; ++i) mix(r[i]);
    }
  }
  char text[17];
  std::snprintf(text, sizeof(text), "%016llx", static_cast<unsigned long long>(hash.value()));
  return text;
}

}  // namespace

static int run(int argc, char** argv) {
  CLI::App app{
      "Simulate a multi-agent mission in a textured hall and write one EuRoC/ASL dataset per agent "
      "(OUT/agent0, OUT/agent1, ...): cam0 (and cam1) PNG at 20 Hz, imu0 at 200 Hz, and "
      "state_groundtruth_estimate0 with the true biases. Same preset and seed give byte-identical files.\n"
      "Presets: loop (1 agent, a loop back to its start), overlap2 (2 agents whose paths share about a third), "
      "hall4 / hall8 (4 / 8 agents flying laps of the hall, half each way, each turning round once), aggressive (1 "
      "agent, fast motion), euroc-mh (5 agents "
      "replaying EuRoC MH_01..MH_05 from $CVISLAM_DATA_DIR/euroc-groundtruth).",
      "cvislam_sim"};
  std::string preset;
  std::string out_dir;
  std::uint64_t seed = 0;
  double duration_s = 60.0;
  std::vector<std::string> replay;
  bool stereo = false;
  bool no_imu_noise = false;
  double pixel_noise = 0.0;
  double exposure = 0.0;
  bool overwrite = false;
  bool quiet = false;
  std::string calibration_dir;

  auto* preset_opt = app.add_option("--preset", preset, "Mission preset: " + joined(cvislam::sim::presetNames()))
                         ->check(CLI::IsMember(cvislam::sim::presetNames()));
  auto* replay_opt = app.add_option("--replay", replay,
                                    "Replay real flights instead: ground-truth files in TUM format "
                                    "(t x y z qx qy qz qw), comma-separated, one agent each")
                         ->delimiter(',');
  preset_opt->excludes(replay_opt);
  app.add_option("--out", out_dir, "Output folder; agents are written to OUT/agentN (required unless --fingerprint)");
  bool fingerprint = false;
  app.add_flag("--fingerprint", fingerprint,
               "Print a hash of the mission's plan (hall, obstacles, paths) and write nothing; caches of rendered "
               "missions key on it");
  app.add_option("--seed", seed, "Seed of the world textures, obstacle layout, paths and noise (default 0)");
  app.add_option("--duration", duration_s, "Seconds per agent (default 60)")->check(CLI::Range(0.1, 3600.0));
  app.add_flag("--stereo", stereo, "Also render cam1 at the EuRoC stereo baseline");
  app.add_flag("--no-imu-noise", no_imu_noise, "Exact IMU readings: no white noise, zero biases");
  app.add_option("--pixel-noise", pixel_noise, "Gaussian pixel noise, sigma in grey levels (default 0: none)")
      ->check(CLI::Range(0.0, 50.0));
  app.add_option("--exposure", exposure,
                 "Smooth exposure change, relative amplitude (e.g. 0.2 for +-20 %; default 0: none)")
      ->check(CLI::Range(0.0, 0.95));
  double camera_clock_shift_ms = 0.0;
  app.add_option("--camera-clock-shift", camera_clock_shift_ms,
                 "Stamp the images on a camera clock this many ms behind the IMU's (t_imu = t_cam + shift, Kalibr's "
                 "timeshift_cam_imu), as on a robot without hardware sync; ground truth stays on the IMU's clock "
                 "(default 0)")
      ->check(CLI::Range(-1000.0, 1000.0));
  app.add_option("--calibration", calibration_dir,
                 "ASL calibration folder with cam0/sensor.yaml, cam1/sensor.yaml and imu0/sensor.yaml "
                 "(default: the built-in EuRoC calibration)")
      ->check(CLI::ExistingDirectory);
  app.add_flag("--overwrite", overwrite, "Replace existing OUT/agentN/mav0 folders (they are deleted first)");
  int threads = static_cast<int>(std::max(1U, std::thread::hardware_concurrency()));
  app.add_option("--threads", threads,
                 "Agents rendered at once, one per thread; the files do not depend on it "
                 "[the number of cores]")
      ->check(CLI::Range(1, 64));
  app.add_flag("-q,--quiet", quiet, "No progress output");

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (preset.empty() && replay.empty()) {
    std::cerr << "cvislam_sim: give --preset NAME or --replay GT_FILE[,...] (see --help)\n";
    return 2;
  }
  if (out_dir.empty() && !fingerprint) {
    std::cerr << "cvislam_sim: give --out DIR (the folder the agents' datasets are written to; see --help)\n";
    return 2;
  }

  cvislam::sim::MissionPlanOptions plan_options;
  plan_options.preset = preset.empty() ? "replay" : preset;
  plan_options.seed = seed;
  plan_options.duration_s = duration_s;
  for (const std::string& f : replay) plan_options.replay.emplace_back(f);

  cvislam::sim::MissionWriterOptions options = cvislam::sim::defaultWriterOptions();
  if (!calibration_dir.empty()) {
    const std::filesystem::path dir(calibration_dir);
    auto cam0 = cvislam::dataset::readCameraCalibration(dir / "cam0" / "sensor.yaml", "cam0");
    if (!cam0) {
      std::cerr << "cvislam_sim: " << cam0.error().toString() << '\n';
      return 1;
    }
    options.cam0 = *cam0;
    if (stereo) {
      auto cam1 = cvislam::dataset::readCameraCalibration(dir / "cam1" / "sensor.yaml", "cam1");
      if (!cam1) {
        std::cerr << "cvislam_sim: " << cam1.error().toString() << '\n';
        return 1;
      }
      options.cam1 = *cam1;
    }
    auto imu = cvislam::dataset::readImuCalibration(dir / "imu0" / "sensor.yaml");
    if (!imu) {
      std::cerr << "cvislam_sim: " << imu.error().toString() << '\n';
      return 1;
    }
    options.imu = *imu;
  }
  options.out_dir = out_dir;
  options.seed = seed;
  options.stereo = stereo;
  options.imu_options.noise = !no_imu_noise;
  options.pixel_noise_sigma = pixel_noise;
  options.exposure_amplitude = exposure;
  options.camera_time_shift_ns = static_cast<std::int64_t>(std::llround(camera_clock_shift_ms * 1e6));
  options.overwrite = overwrite;
  options.threads = threads;

  const auto start = std::chrono::steady_clock::now();
  auto plan = cvislam::sim::planMission(plan_options);
  if (!plan) {
    std::cerr << "cvislam_sim: " << plan.error().toString() << '\n';
    return 1;
  }
  if (fingerprint) {
    std::cout << planFingerprint(*plan) << '\n';
    return 0;
  }
  if (!quiet) {
    std::cout << "cvislam_sim: " << plan->preset << ", seed " << seed << ", " << plan->agents.size() << " agent(s), "
              << duration_s << " s each, " << plan->layout.obstacles.size() << " obstacles -> " << out_dir << '\n';
    options.progress = [&](std::size_t agent, std::size_t done, std::size_t total) {
      if (done == total || done % std::max<std::size_t>(1, total / 10) == 0) {
        const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
        std::cout << "  " << plan->agents[agent].name << " (" << plan->agents[agent].source << "): " << done << "/"
                  << total << " frames, " << static_cast<int>(elapsed) << " s elapsed\n"
                  << std::flush;
      }
    };
  }
  // Existing output: refuse, or with --overwrite replace each agent's mav0 (so no stale images stay behind).
  for (const cvislam::sim::AgentPlan& agent : plan->agents) {
    const std::filesystem::path mav0 = std::filesystem::path(out_dir) / agent.name / "mav0";
    std::error_code ec;
    if (!std::filesystem::exists(mav0, ec)) continue;
    if (!overwrite) {
      std::cerr << "cvislam_sim: " << mav0.string() << " already exists; pass --overwrite to replace it, or choose "
                << "another --out\n";
      return 1;
    }
    std::filesystem::remove_all(mav0, ec);
    if (ec) {
      std::cerr << "cvislam_sim: cannot remove " << mav0.string() << ": " << ec.message() << '\n';
      return 1;
    }
  }
  if (cvislam::Status st = cvislam::sim::writeMission(*plan, options); !st) {
    std::cerr << "cvislam_sim: " << st.error().toString() << '\n';
    return 1;
  }
  if (!quiet) std::cout << "cvislam_sim: done\n";
  return 0;
}

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    std::cerr << "cvislam_sim: unexpected error: " << e.what() << '\n';
    return 1;
  }
}
