// The whole agent on REAL EuRoC recordings from ../shared/data, at --pace sync (reproducible): the accuracy it
// reaches over its metric poses, the poses before the IMU initialisation marked in both trajectory files, and the
// live trajectory (what a robot flies on) scored beside the refined one. The bounds are today's figures rounded
// up, so that a change that costs accuracy on real motion fails here.
#include <atomic>
#include <cstdio>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/runtime/agent.hpp"
#include "common/core/diagnostics.hpp"
#include "common/dataset/trajectory_io.hpp"
#include "common/eval/trajectory_eval.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::agent {
namespace {

namespace fs = std::filesystem;

struct Scored {
  double ate_m = 1e9;  // SE3 alignment, RMSE, over the poses not marked
  std::size_t scored = 0;
  std::size_t marked = 0;
};

// Scores `file` against `truth` as cvislam_eval does: poses marked as before the initialisation are left out.
// Also checks that exactly the poses before `initialised_s` (from the file's first pose) are marked.
Scored scoreMetricPoses(const fs::path& file, const fs::path& truth, double initialised_s) {
  Scored out;
  Diagnostics diagnostics;
  auto written = dataset::readTrajectory(file, {}, diagnostics);
  auto reference = dataset::readTrajectory(truth, {}, diagnostics);
  EXPECT_TRUE(written.ok() && reference.ok()) << file;
  if (!written.ok() || !reference.ok() || written->empty()) return out;
  const std::int64_t first_t_ns = written->front().t_ns;
  std::vector<dataset::StampedPose> metric;
  for (const dataset::StampedPose& pose : *written) {
    const double t_s = static_cast<double>(pose.t_ns - first_t_ns) * 1e-9;
    EXPECT_EQ(pose.before_initialisation, t_s < initialised_s - 1e-6) << file << " at " << t_s << " s";
    if (pose.before_initialisation) {
      ++out.marked;
    } else {
      metric.push_back(pose);
    }
  }
  auto evaluation = eval::evaluate(metric, *reference, {});
  EXPECT_TRUE(evaluation.ok()) << file;
  if (!evaluation.ok()) return out;
  const eval::AbsoluteError* se3 = evaluation->find(eval::Alignment::kSE3);
  if (se3 != nullptr) out.ate_m = se3->translation_m.rmse;
  out.scored = metric.size();
  return out;
}

AgentRunSummary runOn(const fs::path& dataset, const fs::path& output, AgentMode mode) {
  AgentOptions o;
  o.dataset = dataset;
  o.output = output;
  o.pace = Pace::kSync;
  o.quiet = true;
  o.mode = mode;
  const std::atomic<bool> stop{false};
  auto summary = runAgent(o, stop);
  EXPECT_TRUE(summary.ok()) << (summary.ok() ? "" : summary.error().toString());
  return summary.ok() ? *summary : AgentRunSummary{};
}

// 30 s of MH_01 (frames 100-699), left camera and IMU: a hand-held start over 5.5 m, then the sensor at rest.
// Today the mono agent has its two-view map at 0.3 s and is metric from 2.15 s on (its IMU initialisation made at
// 12 keyframes, once three attempts agreed on the scale; 2.75 s when it waited for 15), and scores 0.38 cm refined
// and 0.43 cm live over its metric poses.
TEST(RealDataAccuracy, MonoInertialOnAHandHeldMachineHallStart) {
  CVISLAM_REQUIRE_DATA(mh01, "euroc-mh01-30s-mono");
  CVISLAM_REQUIRE_DATA(truth, "euroc-groundtruth/MH_01_easy.txt");
  const test::TempDir dir;
  const AgentRunSummary summary = runOn(mh01, dir.path() / "mono", AgentMode::kMono);
  EXPECT_EQ(summary.new_maps, 1u);
  EXPECT_GT(summary.tracking_initialised_at_s, 0.0);
  EXPECT_LE(summary.tracking_initialised_at_s, 2.5);
  const Scored refined =
      scoreMetricPoses(dir.path() / "mono" / "trajectory.txt", truth, summary.tracking_initialised_at_s);
  const Scored live =
      scoreMetricPoses(dir.path() / "mono" / "trajectory_online.txt", truth, summary.tracking_initialised_at_s);
  std::printf(
      "MH_01 30 s mono-inertial: metric from %.2f s; ATE refined %.2f mm over %zu poses (%zu marked), live "
      "%.2f mm over %zu\n",
      summary.tracking_initialised_at_s, refined.ate_m * 1e3, refined.scored, refined.marked, live.ate_m * 1e3,
      live.scored);
  EXPECT_GT(refined.marked, 0u);
  EXPECT_GT(refined.scored, 400u);
  EXPECT_LE(refined.ate_m, 0.0045);
  EXPECT_LE(live.ate_m, 0.0050);
}

// The first 4.7 s of V1_01, stereo-inertial: today 0.77 mm over the 58 frames after the IMU initialisation.
TEST(RealDataAccuracy, StereoInertialOnTheVicon101Excerpt) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  const test::TempDir dir;
  const AgentRunSummary summary = runOn(excerpt, dir.path() / "stereo", AgentMode::kStereo);
  EXPECT_EQ(summary.new_maps, 1u);
  const Scored refined =
      scoreMetricPoses(dir.path() / "stereo" / "trajectory.txt", excerpt, summary.tracking_initialised_at_s);
  const Scored live =
      scoreMetricPoses(dir.path() / "stereo" / "trajectory_online.txt", excerpt, summary.tracking_initialised_at_s);
  std::printf("V1_01 excerpt stereo-inertial: metric from %.2f s; ATE refined %.3f mm over %zu poses, live %.3f mm\n",
              summary.tracking_initialised_at_s, refined.ate_m * 1e3, refined.scored, live.ate_m * 1e3);
  EXPECT_GT(refined.scored, 50u);
  EXPECT_LE(refined.ate_m, 0.0008);
  EXPECT_LE(live.ate_m, 0.0008);
}

}  // namespace
}  // namespace cvislam::agent
