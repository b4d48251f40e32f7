// cvislam_eval as a user runs it: exit codes, the table, JSON keys, the SVG, and messages for bad input.
#include <array>
#include <cstdio>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/dataset/trajectory_io.hpp"
#include "test/support/run_command.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace {

using ::testing::HasSubstr;

using cvislam::test::CommandResult;

CommandResult runEval(const std::string& args) {
  return cvislam::test::runCommand(CVISLAM_EVAL_BINARY, args);
}

// A helix as ground truth; the estimate is the same helix 5 % larger.
void writePair(const cvislam::test::TempDir& dir) {
  cvislam::dataset::Trajectory gt;
  cvislam::dataset::Trajectory est;
  for (int k = 0; k < 400; ++k) {
    const double a = 0.02 * k;
    const Eigen::Vector3d p(std::cos(a), std::sin(a), 0.05 * a);
    const cvislam::geometry::SO3d R = cvislam::geometry::SO3d::exp(Eigen::Vector3d(0, 0, a));
    gt.push_back({1'000'000'000LL + k * 10'000'000LL, {R, p}});
    if (k % 4 == 1) est.push_back({1'000'000'000LL + k * 10'000'000LL, {R, 1.05 * p}});
  }
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / "gt.csv", gt).ok());
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / "est.txt", est).ok());
}

TEST(CvislamEvalCli, PrintsATableAndWritesJsonAndSvg) {
  cvislam::test::TempDir dir;
  writePair(dir);
  const CommandResult run =
      runEval("--estimate " + (dir / "est.txt").string() + " --groundtruth " + (dir / "gt.csv").string() + " --json " +
              (dir / "out.json").string() + " --plot " + (dir / "out.svg").string() + " --rpe 0.5");
  ASSERT_EQ(run.exit_code, 0) << run.output;
  EXPECT_THAT(run.output, HasSubstr("100 of 100 associated"));
  EXPECT_THAT(run.output, HasSubstr("sim3"));
  EXPECT_THAT(run.output, HasSubstr("scale error +5.00 %"));
  const auto json = nlohmann::json::parse(cvislam::test::readTextFile(dir / "out.json"));
  for (const char* alignment : {"posyaw", "se3", "sim3"}) {
    for (const char* key : {"rmse", "mean", "median", "max"}) {
      EXPECT_TRUE(json[alignment].contains(key)) << alignment << "." << key;
    }
  }
  EXPECT_EQ(json["poses"], 100);
  EXPECT_NEAR(json["scale"].get<double>(), 1.0 / 1.05, 1e-12);
  EXPECT_LT(json["sim3"]["rmse"].get<double>(), 1e-12);
  EXPECT_EQ(json["rpe"].size(), 1u);
  const std::string svg = cvislam::test::readTextFile(dir / "out.svg");
  EXPECT_THAT(svg, HasSubstr("<svg"));
  EXPECT_EQ(std::count(svg.begin(), svg.end(), '\n') > 5, true);
  EXPECT_THAT(svg, HasSubstr("<polyline"));
}

// An estimate whose first poses were made before its initialisation (marked rows, here off by a metre): they are
// left out and counted unless asked for.
TEST(CvislamEvalCli, PosesFromBeforeTheInitialisationAreLeftOutAndCountedUnlessAskedFor) {
  cvislam::test::TempDir dir;
  cvislam::dataset::Trajectory gt;
  cvislam::dataset::Trajectory est;
  for (int k = 0; k < 100; ++k) {
    const double a = 0.05 * k;
    const Eigen::Vector3d p(std::cos(a), std::sin(a), 0.05 * a);
    const cvislam::geometry::SO3d R = cvislam::geometry::SO3d::exp(Eigen::Vector3d(0, 0, a));
    const std::int64_t t_ns = 1'000'000'000LL + k * 10'000'000LL;
    gt.push_back({t_ns, {R, p}});
    const bool before = k < 20;
    est.push_back({t_ns, {R, before ? p + Eigen::Vector3d(1.0, 0.0, 0.0) : p}, before});
  }
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / "gt.csv", gt).ok());
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / "est.txt", est).ok());
  const std::string args = "--estimate " + (dir / "est.txt").string() + " --groundtruth " + (dir / "gt.csv").string();

  const CommandResult metric = runEval(args + " --json " + (dir / "metric.json").string());
  ASSERT_EQ(metric.exit_code, 0) << metric.output;
  EXPECT_THAT(metric.output, HasSubstr("80 of 80 associated"));
  EXPECT_THAT(metric.output, HasSubstr("20 poses marked as estimated before the initialisation: left out"));
  const auto m = nlohmann::json::parse(cvislam::test::readTextFile(dir / "metric.json"));
  EXPECT_EQ(m["before_initialisation"], 20);
  EXPECT_FALSE(m["before_initialisation_scored"].get<bool>());
  EXPECT_LT(m["se3"]["rmse"].get<double>(), 1e-9);

  const CommandResult all = runEval(args + " --include-before-init --json " + (dir / "all.json").string());
  ASSERT_EQ(all.exit_code, 0) << all.output;
  EXPECT_THAT(all.output, HasSubstr("100 of 100 associated"));
  const auto a = nlohmann::json::parse(cvislam::test::readTextFile(dir / "all.json"));
  EXPECT_TRUE(a["before_initialisation_scored"].get<bool>());
  EXPECT_GT(a["se3"]["rmse"].get<double>(), 0.1);

  // Nothing but poses from before the initialisation: nothing to score, and the message says how to score them.
  for (auto& pose : est) pose.before_initialisation = true;
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / "est.txt", est).ok());
  const CommandResult none = runEval(args);
  EXPECT_EQ(none.exit_code, 1) << none.output;
  EXPECT_THAT(none.output, HasSubstr("--include-before-init"));
}

TEST(CvislamEvalCli, BadInputGivesAMessageAndExitCodeOne) {
  cvislam::test::TempDir dir;
  writePair(dir);
  const CommandResult missing =
      runEval("--estimate " + (dir / "nope.txt").string() + " --groundtruth " + (dir / "gt.csv").string());
  EXPECT_EQ(missing.exit_code, 1);
  EXPECT_THAT(missing.output, HasSubstr("cannot read the estimate"));
  EXPECT_THAT(missing.output, HasSubstr("nope.txt"));

  const CommandResult offset = runEval("--estimate " + (dir / "est.txt").string() + " --groundtruth " +
                                       (dir / "gt.csv").string() + " --offset 100");
  EXPECT_EQ(offset.exit_code, 1);
  EXPECT_THAT(offset.output, HasSubstr("could be associated"));
}

TEST(CvislamEvalCli, UsageErrorsExitWithTwoAndHelpDescribesTheInterface) {
  EXPECT_EQ(runEval("--estimate x.txt").exit_code, 2);  // --groundtruth is required
  EXPECT_EQ(runEval("--estimate x --groundtruth y --associate spline").exit_code, 2);
  const CommandResult help = runEval("--help");
  EXPECT_EQ(help.exit_code, 0);
  for (const char* flag : {"--estimate", "--groundtruth", "--associate", "--max-diff", "--json", "--plot"}) {
    EXPECT_THAT(help.output, HasSubstr(flag));
  }
}

TEST(CvislamEvalCli, EvaluatesAgainstAEurocSequenceFolder) {
  CVISLAM_REQUIRE_DATA(seq, "euroc-v101-excerpt");
  CVISLAM_REQUIRE_DATA(gt, "euroc-groundtruth/V1_01_easy.txt");
  cvislam::test::TempDir dir;
  // The ground truth itself, as a TUM estimate: zero error against the sequence folder.
  const CommandResult run =
      runEval("--estimate " + gt.string() + " --groundtruth " + seq.string() + " --json " + (dir / "o.json").string());
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const auto json = nlohmann::json::parse(cvislam::test::readTextFile(dir / "o.json"));
  // The TUM copy's timestamps are rounded to 10 us: its first pose falls 3 us before the sequence's first.
  EXPECT_EQ(json["poses"], 2894);
  EXPECT_EQ(json["outside_groundtruth_span"], 1);
  EXPECT_LT(json["se3"]["rmse"].get<double>(), 1e-5);  // the TUM copy is rounded to 10 us
}

// Several agents: each a helix as ground truth, all in one world frame; its estimate is every 4th pose mapped into
// the estimate's world by S_est_gt (with b's extra offset, when given, applied after it).
struct Agent {
  std::string folder;
  Eigen::Vector3d centre;
  int poses = 400;
};

cvislam::geometry::Sim3d yawAndShift(double yaw_rad, const Eigen::Vector3d& t) {
  return cvislam::geometry::Sim3d(1.0, cvislam::geometry::SO3d::exp(Eigen::Vector3d(0, 0, yaw_rad)), t);
}

void writeAgent(const cvislam::test::TempDir& dir, const Agent& agent, const cvislam::geometry::Sim3d& S_est_gt) {
  cvislam::dataset::Trajectory gt;
  cvislam::dataset::Trajectory est;
  for (int k = 0; k < agent.poses; ++k) {
    const double a = 0.02 * k;
    const Eigen::Vector3d p = agent.centre + Eigen::Vector3d(std::cos(a), std::sin(a), 0.05 * a);
    const cvislam::geometry::SO3d R = cvislam::geometry::SO3d::exp(Eigen::Vector3d(0, 0, a));
    const std::int64_t t = 1'000'000'000LL + k * 10'000'000LL;
    gt.push_back({t, {R, p}});
    if (k % 4 == 1) est.push_back({t, {S_est_gt.so3() * R, S_est_gt * p}});
  }
  std::filesystem::create_directories(dir / agent.folder);
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / (agent.folder + "/gt.csv"), gt).ok());
  ASSERT_TRUE(cvislam::dataset::writeTrajectory(dir / (agent.folder + "/est.txt"), est).ok());
}

std::string pairArgs(const cvislam::test::TempDir& dir, const std::string& folder) {
  return " --estimate " + (dir / (folder + "/est.txt")).string() + " --groundtruth " +
         (dir / (folder + "/gt.csv")).string();
}

TEST(CvislamEvalCli, UnequalCountsOfEstimatesAndGroundTruthsAreACommandLineError) {
  const CommandResult more_estimates = runEval("--estimate a.txt --groundtruth a.csv --estimate b.txt");
  EXPECT_EQ(more_estimates.exit_code, 2);
  EXPECT_THAT(more_estimates.output, HasSubstr("--estimate given 2 time(s) but --groundtruth 1 time(s)"));
  const CommandResult more_truths = runEval("--estimate a.txt --groundtruth a.csv --groundtruth b.csv");
  EXPECT_EQ(more_truths.exit_code, 2);
  EXPECT_THAT(more_truths.output, HasSubstr("--estimate given 1 time(s) but --groundtruth 2 time(s)"));
  const CommandResult labels =
      runEval("--estimate a.txt --groundtruth a.csv --estimate b.txt --groundtruth b.csv --label one");
  EXPECT_EQ(labels.exit_code, 2);
  EXPECT_THAT(labels.output, HasSubstr("--label given 1 time(s) for 2 estimate(s)"));
  EXPECT_EQ(runEval("--estimate a.txt --groundtruth a.csv --estimate b.txt --groundtruth b.csv --label x --label x")
                .exit_code,
            2);
  EXPECT_EQ(runEval("--estimate a.txt --groundtruth a.csv --align sideways").exit_code, 2);
}

TEST(CvislamEvalCli, ScoresSeveralEstimatesJointlyInATableJsonAndSvg) {
  cvislam::test::TempDir dir;
  // Two agents' estimates in one map, off the ground truth's world by one rigid transform: zero joint error.
  const auto S_est_gt = yawAndShift(0.5, Eigen::Vector3d(1.0, 2.0, 0.0));
  writeAgent(dir, {"a", Eigen::Vector3d(0, 0, 0), 400}, S_est_gt);
  writeAgent(dir, {"b", Eigen::Vector3d(5, 0, 1), 200}, S_est_gt);
  const CommandResult run = runEval(pairArgs(dir, "a") + pairArgs(dir, "b") + " --json " + (dir / "out.json").string() +
                                    " --plot " + (dir / "out.svg").string() + " --per-pose");
  ASSERT_EQ(run.exit_code, 0) << run.output;
  // Both estimates are called est.txt: their labels are the folder and the stem.
  EXPECT_THAT(run.output, HasSubstr("[a/est]"));
  EXPECT_THAT(run.output, HasSubstr("[b/est]"));
  EXPECT_THAT(run.output, HasSubstr("joint line: all 150 poses under one transform"));
  EXPECT_THAT(run.output, HasSubstr("se3      joint        150"));

  const auto json = nlohmann::json::parse(cvislam::test::readTextFile(dir / "out.json"));
  EXPECT_EQ(json["align"], "joint");
  ASSERT_EQ(json["estimates"].size(), 2u);
  const std::size_t poses[] = {100, 50};
  for (std::size_t i = 0; i < 2; ++i) {
    const auto& e = json["estimates"][i];
    EXPECT_EQ(e["label"], i == 0 ? "a/est" : "b/est");
    EXPECT_EQ(e["estimate"], "est.txt");
    EXPECT_EQ(e["poses"], poses[i]);
    EXPECT_GT(e["path_m"].get<double>(), 0.0);
    for (const char* alignment : {"posyaw", "se3", "sim3"}) {
      EXPECT_LT(e[alignment]["rmse"].get<double>(), 1e-6) << alignment;
      EXPECT_EQ(e[alignment]["translation_errors_m"].size(), poses[i]);
    }
    EXPECT_NEAR(e["scale_error_percent"].get<double>(), 0.0, 1e-6);
    // Per pose: timestamps, ground truth, and the estimate after the (joint) SE3 alignment, which lies on it.
    ASSERT_EQ(e["timestamps_s"].size(), poses[i]);
    ASSERT_EQ(e["groundtruth_xyz_m"].size(), poses[i]);
    ASSERT_EQ(e["estimate_se3_aligned_xyz_m"].size(), poses[i]);
    for (std::size_t k = 0; k < poses[i]; ++k) {
      for (std::size_t c = 0; c < 3; ++c) {
        EXPECT_NEAR(e["estimate_se3_aligned_xyz_m"][k][c].get<double>(), e["groundtruth_xyz_m"][k][c].get<double>(),
                    1e-6);
      }
    }
  }
  const auto& joint = json["joint"];
  EXPECT_EQ(joint["poses"], 150);
  for (const char* alignment : {"posyaw", "se3", "sim3"}) {
    EXPECT_LT(joint[alignment]["rmse"].get<double>(), 1e-6) << alignment;
    EXPECT_EQ(joint[alignment]["count"], 150);
    EXPECT_TRUE(joint[alignment].contains("transform_gt_est"));
  }
  EXPECT_NEAR(joint["scale_error_percent"].get<double>(), 0.0, 1e-6);

  const std::string svg = cvislam::test::readTextFile(dir / "out.svg");
  EXPECT_THAT(svg, HasSubstr("a/est (posyaw-aligned"));
  EXPECT_THAT(svg, HasSubstr("b/est (posyaw-aligned"));
  std::size_t polylines = 0;
  for (std::size_t at = svg.find("<polyline"); at != std::string::npos; at = svg.find("<polyline", at + 1)) ++polylines;
  EXPECT_EQ(polylines, 4u);  // two ground truths, two estimates
}

TEST(CvislamEvalCli, AlignEachPoolsTheEstimatesOwnErrorsAndSaysSo) {
  cvislam::test::TempDir dir;
  // Maps not merged: b's world is 1 m and 10 degrees off a's. Each on its own fits exactly; jointly they cannot.
  const auto S_a = yawAndShift(0.5, Eigen::Vector3d(1.0, 2.0, 0.0));
  writeAgent(dir, {"a", Eigen::Vector3d(0, 0, 0), 400}, S_a);
  writeAgent(dir, {"b", Eigen::Vector3d(0, 0, 0), 400}, S_a * yawAndShift(10.0 * M_PI / 180.0, {1.0, 0.0, 0.0}));
  const std::string args = pairArgs(dir, "a") + pairArgs(dir, "b") + " --label A --label B --json ";
  const CommandResult each = runEval(args + (dir / "each.json").string() + " --align each");
  ASSERT_EQ(each.exit_code, 0) << each.output;
  EXPECT_THAT(each.output, HasSubstr("alignment:    each"));
  EXPECT_THAT(each.output, HasSubstr("joint line: RMSE pooled over all 200 poses"));
  const auto each_json = nlohmann::json::parse(cvislam::test::readTextFile(dir / "each.json"));
  EXPECT_EQ(each_json["align"], "each");
  EXPECT_EQ(each_json["estimates"][1]["label"], "B");
  EXPECT_LT(each_json["joint"]["se3"]["rmse"].get<double>(), 1e-6);
  EXPECT_FALSE(each_json["joint"]["se3"].contains("transform_gt_est"));  // there is none
  EXPECT_TRUE(each_json["joint"]["scale"].is_null());

  const CommandResult joint = runEval(args + (dir / "joint.json").string() + " --align joint");
  ASSERT_EQ(joint.exit_code, 0) << joint.output;
  const auto joint_json = nlohmann::json::parse(cvislam::test::readTextFile(dir / "joint.json"));
  // Both fly the same helix, pose k of each at one place, their estimates d_k apart: any rigid transform leaves
  // residuals summing to at least d_k there, so the joint RMSE is at least rms(d) / 2; d_k >= 1 m - (the 10 deg
  // chord at the helix's 1 m radius) > 0.8 m, so > 0.4 m.
  EXPECT_GT(joint_json["joint"]["se3"]["rmse"].get<double>(), 0.4);
}

TEST(CvislamEvalCli, OneEstimateKeepsItsJsonAndAddsAlignedPositionsPerPose) {
  cvislam::test::TempDir dir;
  writePair(dir);
  const CommandResult run = runEval("--estimate " + (dir / "est.txt").string() + " --groundtruth " +
                                    (dir / "gt.csv").string() + " --per-pose --json " + (dir / "out.json").string());
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const auto json = nlohmann::json::parse(cvislam::test::readTextFile(dir / "out.json"));
  EXPECT_FALSE(json.contains("align"));
  EXPECT_FALSE(json.contains("estimates"));
  EXPECT_EQ(json["poses"], 100);
  EXPECT_EQ(json["timestamps_s"].size(), 100u);
  EXPECT_EQ(json["groundtruth_xyz_m"].size(), 100u);
  ASSERT_EQ(json["estimate_se3_aligned_xyz_m"].size(), 100u);
  EXPECT_EQ(json["estimate_se3_aligned_xyz_m"][0].size(), 3u);
}

}  // namespace
