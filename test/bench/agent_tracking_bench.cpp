// Tracking latency per frame: Tracker::track() (IMU prediction, ORB, projection searches, pose optimisation,
// motion-only VI BA, keyframe decision and message write) on every frame of a EuRoC-format sequence, with
// mapping answering each keyframe in the same thread between frames (not timed). Frames are read before they
// are timed. Writes p50/p90/p99/max per stage and p99/p50 (the measure of determinism) as JSON.
//
//   taskset -c 1 build/default/bin/bench_agent_tracking [--dataset SEQ_DIR] [--mode stereo|mono]
//                                                        [--passes N] [--json OUT]
//
// Default dataset: the real V1_01 excerpt ($CVISLAM_DATA_DIR/euroc-v101-excerpt), stereo. Each pass runs
// the sequence from scratch (a new tracker and map), so every pass includes the start-up frames.
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "agent_rt/runtime/latency_profile.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/test_data.hpp"

namespace {
std::int64_t nowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Per-frame tracking latency of the cvislam agent on a EuRoC-format sequence"};
  std::string dataset = (cvislam::test::dataRoot() / "euroc-v101-excerpt").string();
  std::string mode = "stereo";
  std::string json;
  int passes = 5;
  app.add_option("--dataset", dataset, "Sequence folder that holds mav0");
  app.add_option("--mode", mode, "stereo or mono")->check(CLI::IsMember({"stereo", "mono"}));
  app.add_option("--passes", passes, "Runs over the whole sequence")->check(CLI::PositiveNumber);
  app.add_option("--json", json, "Write the summary here as JSON");
  CLI11_PARSE(app, argc, argv);

  auto sequence = cvislam::dataset::EurocSequence::open(dataset);
  if (!sequence) {
    std::cerr << "bench_agent_tracking: " << sequence.error().toString() << "\n";
    return 1;
  }
  const std::size_t capacity = static_cast<std::size_t>(passes) * sequence->cam0().frames.size();
  cvislam::agent::LatencyRecorder total("tracking_total", capacity);
  cvislam::agent::LatencyRecorder orb("orb_extraction", capacity);
  cvislam::agent::LatencyRecorder matching("matching", capacity);
  cvislam::agent::LatencyRecorder pose("pose_optimisation", capacity);
  cvislam::agent::LatencyRecorder motion("motion_ba", capacity);
  std::size_t tracked = 0;
  std::size_t frames = 0;
  std::size_t keyframes = 0;
  for (int pass = 0; pass < passes; ++pass) {
    auto agent = cvislam::test::InlineAgent::create(*sequence, mode == "stereo");
    if (!agent) {
      std::cerr << "bench_agent_tracking: " << agent.error().toString() << "\n";
      return 1;
    }
    for (std::size_t i = 0; i < (*agent)->frameCount(); ++i) {
      if (!(*agent)->load(i).ok()) continue;
      std::int64_t t0 = 0;
      std::int64_t t1 = 0;
      const cvislam::agent::FrameResult r = (*agent)->track([&] { t0 = nowNs(); }, [&] { t1 = nowNs(); });
      ++frames;
      total.add(t1 - t0);
      orb.add(r.times.orb_ns);
      if (r.tracked) {
        ++tracked;
        matching.add(r.times.matching_ns);
        pose.add(r.times.pose_ns);
        if (r.times.motion_ba_ns > 0) motion.add(r.times.motion_ba_ns);
      }
      keyframes += r.keyframe ? 1 : 0;
    }
  }
  std::vector<cvislam::agent::StageSummary> stages;
  for (const auto* r : {&total, &orb, &matching, &pose, &motion}) stages.push_back(cvislam::agent::summarise(*r));
  std::printf("%s: %zu frames (%d passes), %zu tracked, %zu keyframes\n%s", dataset.c_str(), frames, passes, tracked,
              keyframes, cvislam::agent::formatLatencyTable(stages).c_str());
  const double determinism = stages[0].p50_ms > 0 ? stages[0].p99_ms / stages[0].p50_ms : 0.0;
  std::printf("tracking p99/p50 = %.2f\n", determinism);
  if (!json.empty()) std::ofstream(json) << cvislam::agent::latencyJson(stages);
  return 0;
}
