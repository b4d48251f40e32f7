// cvislam_eval as a user runs it: exit codes, the table, JSON keys, the SVG, and messages for bad input.
#include <array>
#include <cstdio>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/dataset/trajectory_io.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace {

using ::testing::HasSubstr;

struct CommandResult {
  int exit_code = -1;
  std::string output;  // stdout and stderr
};

CommandResult runEval(const std::string& args) {
  const std::string command = std::string(CVISLAM_EVAL_BINARY) + " " + args + " 2>&1";
  CommandResult run;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return run;
  std::array<char, 4096> buffer{};
  while (fgets(buffer.data(), buffer.size(), pipe) != nullptr) run.output += buffer.data();
  const int status = pclose(pipe);
  run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return run;
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

}  // namespace
