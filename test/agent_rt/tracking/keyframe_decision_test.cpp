#include "agent_rt/tracking/keyframe_decision.hpp"

#include <vector>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

TEST(KeyframeDecision, EachOfThePapersThreeCriteriaTriggersAKeyframe) {
  const KeyframeDecisionOptions options;
  TrackingState healthy{5, 120, 0.7, 0.8};
  EXPECT_EQ(decideKeyframe(healthy, options), KeyframeReason::kNone);

  TrackingState old = healthy;
  old.frames_since_keyframe = 21;  // more than 20
  EXPECT_EQ(decideKeyframe(old, options), KeyframeReason::kFrameCount);
  old.frames_since_keyframe = 20;  // exactly 20 is not more
  EXPECT_EQ(decideKeyframe(old, options), KeyframeReason::kNone);

  TrackingState uncovered = healthy;
  uncovered.coverage = 0.31;  // under 40 % of the keyframe's 0.8
  EXPECT_EQ(decideKeyframe(uncovered, options), KeyframeReason::kCoverage);

  TrackingState starving = healthy;
  starving.tracked_points = 29;  // under the default 30
  EXPECT_EQ(decideKeyframe(starving, options), KeyframeReason::kFewTrackedPoints);
  starving.tracked_points = 30;
  EXPECT_EQ(decideKeyframe(starving, options), KeyframeReason::kNone);

  KeyframeDecisionOptions paper = options;  // the paper's 15
  paper.min_tracked_points = 15;
  starving.tracked_points = 14;
  EXPECT_EQ(decideKeyframe(starving, paper), KeyframeReason::kFewTrackedPoints);
  starving.tracked_points = 15;
  EXPECT_EQ(decideKeyframe(starving, paper), KeyframeReason::kNone);
}

TEST(KeyframeDecision, InitialisationKeepsAtMostThreeFramesBetweenKeyframes) {
  KeyframeDecisionOptions options;
  options.max_frames_between = 3;
  EXPECT_EQ(decideKeyframe({3, 200, 0.9, 0.9}, options), KeyframeReason::kNone);
  EXPECT_EQ(decideKeyframe({4, 200, 0.9, 0.9}, options), KeyframeReason::kFrameCount);
}

TEST(KeyframeDecision, WithTheImuKeyframesAreAtMostHalfASecondApart) {
  KeyframeDecisionOptions options;  // 0.5 s by default
  TrackingState slow{8, 200, 0.9, 0.9};
  slow.interval_s = 0.45;
  EXPECT_EQ(decideKeyframe(slow, options), KeyframeReason::kNone);
  slow.interval_s = 0.5;
  EXPECT_EQ(decideKeyframe(slow, options), KeyframeReason::kInterval);
  options.max_interval_s = 0.0;  // no cap: the frame count alone
  slow.interval_s = 5.0;
  EXPECT_EQ(decideKeyframe(slow, options), KeyframeReason::kNone);
  options.max_interval_s = -1.0;
  const Status status = options.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message().find("max_interval_s"), std::string::npos);
}

TEST(GridCoverage, CountsTheCellsThatHoldAPointAndIgnoresPointsOutsideTheImage) {
  // Two points in one cell, one in another, one outside: 2 of 48 cells.
  const std::vector<Eigen::Vector2f> points = {{10.0F, 10.0F}, {20.0F, 15.0F}, {700.0F, 400.0F}, {-5.0F, 10.0F}};
  EXPECT_DOUBLE_EQ(gridCoverage(points, 752, 480, 8, 6), 2.0 / 48.0);
  std::vector<Eigen::Vector2f> everywhere;
  for (int y = 0; y < 6; ++y) {
    for (int x = 0; x < 8; ++x)
      everywhere.emplace_back(94.0F * static_cast<float>(x) + 40.0F, 80.0F * static_cast<float>(y) + 40.0F);
  }
  EXPECT_DOUBLE_EQ(gridCoverage(everywhere, 752, 480, 8, 6), 1.0);
}

TEST(KeyframeDecisionOptions, ValidateNamesTheBadField) {
  KeyframeDecisionOptions options;
  EXPECT_TRUE(options.validate().ok());
  options.min_coverage_ratio = 1.5;
  const Status status = options.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message().find("min_coverage_ratio"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::agent
