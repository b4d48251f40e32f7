// bench_recordings: what reading a recording costs the agent's loading thread, a EuRoC folder (PNG per image)
// against the same recording as a ROS 2 bag in MCAP (zstd chunks, uncompressed chunks, no chunks). The bag is
// written from the folder at start (test/support/euroc_to_mcap). Per source, over --passes passes: the time to
// open it (the bag's first scan included), and per rig frame the time to load its images (both cameras when
// stereo), p50 / p99, and the CPU time of a whole pass (open and every frame).
//
//   bench_recordings [--dataset DIR] [--passes 5] [--json OUT]
#include <time.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "agent_rt/sources/recording.hpp"
#include "test/bench/percentiles.hpp"
#include "test/support/euroc_to_mcap.hpp"
#include "test/support/kalibr_files.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

double cpuSeconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

double msSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

struct Variant {
  std::string name;
  cvislam::agent::RecordingOptions options;
};

struct Figures {
  std::vector<double> open_ms;
  std::vector<double> frame_ms;
  std::vector<double> pass_cpu_s;
  std::size_t frames = 0;
  std::uintmax_t bytes = 0;
};

// One pass: open, then every rig frame's images in order, as the agent's loader does.
bool runPass(const Variant& v, Figures& f) {
  const double cpu0 = cpuSeconds();
  const auto t0 = Clock::now();
  auto recording = cvislam::agent::openRecording(v.options);
  if (!recording) {
    std::cerr << "bench_recordings: " << v.name << ": " << recording.error().toString() << "\n";
    return false;
  }
  f.open_ms.push_back(msSince(t0));
  cvislam::agent::Recording& r = **recording;
  const auto n0 = static_cast<std::size_t>(r.rig().cam0.width) * static_cast<std::size_t>(r.rig().cam0.height);
  std::vector<std::uint8_t> left(n0);
  std::vector<std::uint8_t> right(r.rig().cam1 ? static_cast<std::size_t>(r.rig().cam1->width) *
                                                     static_cast<std::size_t>(r.rig().cam1->height)
                                               : 0);
  for (const cvislam::dataset::RigFrame& frame : r.rigFrames()) {
    const auto t = Clock::now();
    cvislam::Status s = r.loadImageInto(0, frame.cam0, left);
    if (s.ok() && frame.cam1 && r.rig().cam1) s = r.loadImageInto(1, *frame.cam1, right);
    if (!s.ok()) {
      std::cerr << "bench_recordings: " << v.name << ": " << s.error().toString() << "\n";
      return false;
    }
    f.frame_ms.push_back(msSince(t));
  }
  f.frames = r.rigFrames().size();
  f.pass_cpu_s.push_back(cpuSeconds() - cpu0);
  return true;
}

std::uintmax_t sizeOf(const fs::path& path) {
  if (fs::is_regular_file(path)) return fs::file_size(path);
  std::uintmax_t total = 0;
  for (const auto& e : fs::recursive_directory_iterator(path)) {
    if (e.is_regular_file()) total += e.file_size();
  }
  return total;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"bench_recordings: the agent's recording sources, a EuRoC folder against the same as an MCAP bag"};
  std::string dataset;
  int passes = 5;
  std::string json_path;
  app.add_option("--dataset", dataset, "EuRoC/ASL folder [the shared data's euroc-v101-excerpt]");
  app.add_option("--passes", passes, "Passes per source [5]")->check(CLI::Range(1, 1000));
  app.add_option("--json", json_path, "Write the figures as JSON");
  CLI11_PARSE(app, argc, argv);
  const fs::path folder = dataset.empty() ? cvislam::test::findData("euroc-v101-excerpt") : fs::path(dataset);
  if (folder.empty() || !fs::exists(folder)) {
    std::cerr << "bench_recordings: no dataset: give --dataset DIR or provide ../shared/data/euroc-v101-excerpt\n";
    return 1;
  }
  const cvislam::test::TempDir dir;
  std::vector<Variant> variants;
  variants.push_back({"folder (PNG)", {}});
  variants.back().options.dataset = folder;
  const std::pair<const char*, cvislam::test::EurocToMcapOptions> bags[] = {
      {"MCAP zstd chunks", {}},
      {"MCAP uncompressed chunks", {cvislam::mcap::Compression::kNone, true, "mono8", false}},
      {"MCAP unchunked", {cvislam::mcap::Compression::kNone, false, "mono8", false}},
  };
  for (const auto& [name, options] : bags) {
    const fs::path bag = dir.path() / (std::string(name).substr(5) + ".mcap");
    if (cvislam::Status s = cvislam::test::writeEurocAsMcap(folder, bag, options); !s.ok()) {
      std::cerr << "bench_recordings: writing " << bag << ": " << s.error().toString() << "\n";
      return 1;
    }
    variants.push_back({name, {}});
    variants.back().options.mcap = bag;
    variants.back().options.calibration = bag.string() + ".camchain.yaml";
    variants.back().options.imu_calibration = bag.string() + ".imu.yaml";
  }
  // The bags need Kalibr files; they are made from the folder's sensor.yaml so that every source has one rig.
  {
    auto folder_recording = cvislam::agent::openRecording(variants.front().options);
    if (!folder_recording) {
      std::cerr << "bench_recordings: " << folder_recording.error().toString() << "\n";
      return 1;
    }
    const cvislam::agent::SensorRig& rig = (*folder_recording)->rig();
    for (std::size_t i = 1; i < variants.size(); ++i) {
      cvislam::test::writeTextFile(variants[i].options.calibration,
                                   cvislam::test::kalibrCamchainYaml(rig.cam0, rig.cam1));
      cvislam::test::writeTextFile(variants[i].options.imu_calibration, cvislam::test::kalibrImuYaml(*rig.imu));
    }
  }

  nlohmann::json out = nlohmann::json::array();
  std::printf("%-26s %8s %10s %9s %11s %11s %13s\n", "source", "frames", "size[MB]", "open[ms]", "frame p50",
              "frame p99", "CPU/pass [s]");
  for (const Variant& v : variants) {
    Figures f;
    f.bytes = sizeOf(v.options.dataset.empty() ? v.options.mcap : v.options.dataset);
    for (int p = 0; p < passes; ++p) {
      if (!runPass(v, f)) return 1;
    }
    const double open_p50 = cvislam::bench::percentile(f.open_ms, 0.5);
    const double p50 = cvislam::bench::percentile(f.frame_ms, 0.5);
    const double p99 = cvislam::bench::percentile(f.frame_ms, 0.99);
    const double cpu_p50 = cvislam::bench::percentile(f.pass_cpu_s, 0.5);
    std::printf("%-26s %8zu %10.1f %9.1f %8.2f ms %8.2f ms %13.3f\n", v.name.c_str(), f.frames,
                static_cast<double>(f.bytes) / 1e6, open_p50, p50, p99, cpu_p50);
    out.push_back({{"source", v.name},
                   {"frames", f.frames},
                   {"bytes", f.bytes},
                   {"passes", passes},
                   {"open_ms_p50", open_p50},
                   {"frame_ms_p50", p50},
                   {"frame_ms_p99", p99},
                   {"pass_cpu_s_p50", cpu_p50}});
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}
