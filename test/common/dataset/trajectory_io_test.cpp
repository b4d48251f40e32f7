#include "common/dataset/trajectory_io.hpp"

#include <algorithm>
#include <sstream>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "test/common/dataset/sequence_fixture.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::dataset {
namespace {

using ::testing::HasSubstr;

Trajectory sampleTrajectory() {
  Trajectory t;
  for (int i = 0; i < 5; ++i) {
    t.push_back({1403715273262142976LL + i * 50'000'000LL,
                 geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0.1 * i, -0.2, 0.3)),
                                Eigen::Vector3d(0.1 * i, 1.0 / 3.0, -2.5e-7))});
  }
  return t;
}

class TrajectoryRoundTrip : public ::testing::TestWithParam<TrajectoryFormat> {};

TEST_P(TrajectoryRoundTrip, IsExactInTimeAndValue) {
  test::TempDir dir;
  const auto path = dir / (GetParam() == TrajectoryFormat::kTum ? "traj.txt" : "traj.csv");
  const Trajectory original = sampleTrajectory();
  ASSERT_TRUE(writeTrajectory(path, original).ok());  // format picked from the extension
  Diagnostics diag;
  auto read = readTrajectory(path, {}, diag);  // format sniffed from the content
  ASSERT_TRUE(read.ok()) << read.error().toString();
  EXPECT_TRUE(diag.empty());
  ASSERT_EQ(read->size(), original.size());
  for (std::size_t i = 0; i < original.size(); ++i) {
    EXPECT_EQ((*read)[i].t_ns, original[i].t_ns);
    EXPECT_EQ((*read)[i].T_w_b.translation(), original[i].T_w_b.translation());
    EXPECT_LT((*read)[i].T_w_b.quaternion().angularDistance(original[i].T_w_b.quaternion()), 1e-15);
  }
}

INSTANTIATE_TEST_SUITE_P(Formats, TrajectoryRoundTrip,
                         ::testing::Values(TrajectoryFormat::kTum, TrajectoryFormat::kEurocCsv),
                         [](const ::testing::TestParamInfo<TrajectoryFormat>& format) {
                           return std::string(toString(format.param));
                         });

// Poses from before an estimator's initialisation go out as comment rows, so that TUM tools that want 8 fields
// (evo) skip them, and come back marked when read here; a file of nothing else is still read.
TEST(TrajectoryIo, PosesFromBeforeTheInitialisationAreCommentRowsReadBackMarked) {
  test::TempDir dir;
  Trajectory original = sampleTrajectory();
  original[0].before_initialisation = true;
  original[1].before_initialisation = true;
  ASSERT_TRUE(writeTrajectory(dir / "traj.txt", original).ok());
  const std::string text = test::readTextFile(dir / "traj.txt");
  std::size_t marked_rows = 0;
  std::size_t plain_rows = 0;
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    if (line.rfind(kBeforeInitialisationMark, 0) == 0) {
      ++marked_rows;
    } else if (!line.empty() && line.front() != '#') {
      ++plain_rows;
      EXPECT_EQ(std::count(line.begin(), line.end(), ' '), 7) << "8 fields, as TUM readers want: " << line;
    }
  }
  EXPECT_EQ(marked_rows, 2u);
  EXPECT_EQ(plain_rows, 3u);

  Diagnostics diag;
  auto read = readTrajectory(dir / "traj.txt", {}, diag);
  ASSERT_TRUE(read.ok()) << read.error().toString();
  EXPECT_TRUE(diag.empty());
  ASSERT_EQ(read->size(), original.size());
  for (std::size_t i = 0; i < original.size(); ++i) {
    EXPECT_EQ((*read)[i].before_initialisation, i < 2) << i;
    EXPECT_EQ((*read)[i].t_ns, original[i].t_ns);
    EXPECT_EQ((*read)[i].T_w_b.translation(), original[i].T_w_b.translation());
  }

  Trajectory never = sampleTrajectory();
  for (StampedPose& p : never) p.before_initialisation = true;
  ASSERT_TRUE(writeTrajectory(dir / "never.txt", never).ok());
  auto read_never = readTrajectory(dir / "never.txt", {}, diag);
  ASSERT_TRUE(read_never.ok()) << read_never.error().toString();
  EXPECT_EQ(read_never->size(), never.size());
}

TEST(TrajectoryIo, ReadsTheGroundTruthOfASequenceFolder) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  Diagnostics diag;
  auto gt = readTrajectory(dir / "seq", {}, diag);
  ASSERT_TRUE(gt.ok()) << gt.error().toString();
  EXPECT_EQ(gt->size(), 6u);
  std::filesystem::remove_all(dir / "seq/mav0/state_groundtruth_estimate0");
  auto none = readTrajectory(dir / "seq", {}, diag);
  ASSERT_FALSE(none.ok());
  EXPECT_THAT(none.error().message(), HasSubstr("has no ground truth"));
}

TEST(TrajectoryIo, BadRowsAreSkippedWithTheirLineOrRefusedInStrictMode) {
  test::TempDir dir;
  test::writeTextFile(dir / "t.txt",
                      "# t x y z qx qy qz qw\n"
                      "1.0 0 0 0 0 0 0 1\n"
                      "2.0 0 0 0 0 0 0\n"    // truncated
                      "3.0 0 0 0 0 0 0 0\n"  // zero quaternion
                      "2.5 0 0 x 0 0 0 1\n"  // non-numeric
                      "0.5 0 0 0 0 0 0 1\n"  // time going backwards
                      "4.0 1 2 3 0 0 0 1\n"
                      "4.0 1 2 3 0 0 0 1\n");  // a repeated timestamp: kept, with a warning
  Diagnostics diag;
  auto t = readTrajectory(dir / "t.txt", {}, diag);
  ASSERT_TRUE(t.ok());
  EXPECT_EQ(t->size(), 3u);
  ASSERT_EQ(diag.warningCount(), 5u);
  EXPECT_EQ(diag.findings()[0].line, 3);
  EXPECT_THAT(diag.findings()[1].message, HasSubstr("quaternion norm 0"));
  EXPECT_THAT(diag.findings()[2].message, HasSubstr("field 4 ('x')"));
  EXPECT_THAT(diag.findings()[3].message, HasSubstr("not after the previous row"));
  EXPECT_THAT(diag.findings()[4].message, HasSubstr("repeats the previous row's; row kept"));
  Diagnostics unused;
  auto strict = readTrajectory(dir / "t.txt", {TrajectoryFormat::kAuto, true}, unused);
  ASSERT_FALSE(strict.ok());
  EXPECT_THAT(strict.error().message(), HasSubstr("t.txt:3: expected 8 fields"));
}

TEST(TrajectoryIo, EmptyAndMissingFilesAreErrors) {
  test::TempDir dir;
  test::writeTextFile(dir / "empty.txt", "# nothing here\n");
  Diagnostics diag;
  EXPECT_THAT(readTrajectory(dir / "empty.txt", {}, diag).error().message(), HasSubstr("no trajectory rows"));
  EXPECT_EQ(readTrajectory(dir / "missing.txt", {}, diag).error().code(), ErrorCode::kNotFound);
  EXPECT_FALSE(parseTrajectoryFormat("kitti").ok());
}

TEST(TrajectoryIo, ReadsThePeerEstimatesAndGroundTruths) {
  CVISLAM_REQUIRE_DATA(evo, "peer-evo");
  CVISLAM_REQUIRE_DATA(gt_dir, "euroc-groundtruth");
  Diagnostics diag;
  auto v102 = readTrajectory(evo / "V102.txt", {}, diag);
  ASSERT_TRUE(v102.ok());
  EXPECT_EQ(v102->size(), 807u);                         // four rows repeat a timestamp; evo keeps them, and so do we
  EXPECT_EQ(v102->front().t_ns, 1403715529112143517LL);  // exact, although written as 1.40e+09 s
  EXPECT_EQ(diag.warningCount(), 4u);
  diag = Diagnostics();
  auto v102_gt = readTrajectory(evo / "V102_groundtruth.csv", {}, diag);
  ASSERT_TRUE(v102_gt.ok());
  EXPECT_EQ(v102_gt->size(), 16702u);
  auto mh01 = readTrajectory(gt_dir / "MH_01_easy.txt", {}, diag);
  ASSERT_TRUE(mh01.ok());
  EXPECT_EQ(mh01->size(), 36382u);
  EXPECT_TRUE(diag.empty());
}

}  // namespace
}  // namespace cvislam::dataset
