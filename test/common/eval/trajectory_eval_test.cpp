// Unit tests of the evaluator on synthetic trajectories with known answers.
#include "common/eval/trajectory_eval.hpp"

#include <cmath>
#include <random>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "common/geometry/alignment.hpp"

namespace cvislam::eval {
namespace {

using ::testing::HasSubstr;

// A smooth 3D figure-of-eight with a varying heading, sampled every dt_ns from t0.
dataset::Trajectory figureEight(std::int64_t t0_ns, std::int64_t dt_ns, int count) {
  dataset::Trajectory out;
  for (int k = 0; k < count; ++k) {
    const std::int64_t t = t0_ns + k * dt_ns;
    const double s = 1e-9 * static_cast<double>(t - 1'000'000'000'000LL);
    const Eigen::Vector3d p(3.0 * std::sin(0.3 * s), 2.0 * std::sin(0.6 * s), 1.0 + 0.3 * std::cos(0.2 * s));
    const Eigen::Vector3d rotvec(0.1 * std::sin(0.5 * s), 0.05 * std::cos(0.7 * s), 0.4 * s);
    out.push_back({t, geometry::SE3d(geometry::SO3d::exp(rotvec), p)});
  }
  return out;
}

dataset::Trajectory transformed(const dataset::Trajectory& in, const geometry::Sim3d& S_est_gt) {
  dataset::Trajectory out = in;
  for (auto& pose : out) {
    pose.T_w_b = geometry::SE3d(S_est_gt.so3() * pose.T_w_b.so3(), S_est_gt * pose.T_w_b.translation());
  }
  return out;
}

const std::int64_t kT0 = 1'000'000'000'000LL;

TEST(ComputeStats, MatchesNumpyConventions) {
  const ErrorStats odd = computeStats({3.0, 1.0, 2.0});
  EXPECT_DOUBLE_EQ(odd.median, 2.0);
  EXPECT_DOUBLE_EQ(odd.mean, 2.0);
  EXPECT_DOUBLE_EQ(odd.rmse, std::sqrt(14.0 / 3.0));
  EXPECT_DOUBLE_EQ(odd.std, std::sqrt(2.0 / 3.0));  // population std
  const ErrorStats even = computeStats({4.0, 1.0, 3.0, 2.0});
  EXPECT_DOUBLE_EQ(even.median, 2.5);
  EXPECT_DOUBLE_EQ(even.min, 1.0);
  EXPECT_DOUBLE_EQ(even.max, 4.0);
  EXPECT_EQ(computeStats({}).count, 0u);
}

TEST(Evaluate, AnEstimateOffByASimilarityHasZeroSim3ErrorAndItsScaleIsRecovered) {
  const auto gt = figureEight(kT0, 5'000'000, 4000);
  const geometry::Sim3d S_est_gt(1.25, geometry::SO3d::exp(Eigen::Vector3d(0.3, -0.2, 2.0)),
                                 Eigen::Vector3d(5.0, -3.0, 1.0));
  // Estimate at 20 Hz, offset from the ground-truth samples by 1 ms: exercises interpolation.
  dataset::Trajectory est;
  for (const auto& pose : figureEight(kT0 + 1'000'000, 50'000'000, 390)) est.push_back(pose);
  est = transformed(est, S_est_gt);
  auto ev = evaluate(est, gt, {});
  ASSERT_TRUE(ev.ok()) << ev.error().toString();
  EXPECT_EQ(ev->poses.size(), 390u);
  const AbsoluteError* sim3 = ev->find(Alignment::kSim3);
  ASSERT_NE(sim3, nullptr);
  EXPECT_LT(sim3->translation_m.rmse, 1e-4);  // only the interpolation error of a 200 Hz curve remains
  EXPECT_LT(sim3->rotation_deg.rmse, 1e-3);
  EXPECT_NEAR(*ev->sim3_scale, 1.0 / 1.25, 1e-6);
  EXPECT_NEAR(*ev->scale_error_percent, 25.0, 1e-4);
  EXPECT_GT(ev->find(Alignment::kSE3)->translation_m.rmse, 0.1);  // SE3 cannot absorb the scale
}

TEST(Evaluate, PositionYawAlignmentAbsorbsYawButNotTilt) {
  const auto gt = figureEight(kT0, 10'000'000, 2000);
  const geometry::SE3d yawed(geometry::alignPositionYaw(std::vector<Eigen::Vector3d>{{0, 0, 0}, {1, 0, 0}},
                                                        std::vector<Eigen::Vector3d>{{0, 0, 0}, {0, 1, 0}})
                                 ->so3(),
                             Eigen::Vector3d(1.0, 2.0, 3.0));
  auto ev = evaluate(transformed(gt, geometry::Sim3d(yawed)), gt, {});
  ASSERT_TRUE(ev.ok());
  EXPECT_LT(ev->find(Alignment::kPosYaw)->translation_m.rmse, 1e-12);
  EXPECT_LT(ev->find(Alignment::kPosYaw)->rotation_deg.rmse, 1e-9);

  const geometry::SE3d tilted(geometry::SO3d::exp(Eigen::Vector3d(0.05, 0.0, 0.0)), Eigen::Vector3d::Zero());
  auto tilted_ev = evaluate(transformed(gt, geometry::Sim3d(tilted)), gt, {});
  ASSERT_TRUE(tilted_ev.ok());
  EXPECT_GT(tilted_ev->find(Alignment::kPosYaw)->translation_m.rmse, 0.01);
  EXPECT_LT(tilted_ev->find(Alignment::kSE3)->translation_m.rmse, 1e-12);
}

TEST(Associate, InterpolationUsesLinearPositionAndSlerp) {
  dataset::Trajectory gt;
  gt.push_back({kT0, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(0, 0, 0))});
  gt.push_back({kT0 + 100, geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0, 0, 1.0)), Eigen::Vector3d(2, 4, 0))});
  gt.push_back({kT0 + 200, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(0, 0, 0))});
  dataset::Trajectory est = {{kT0 + 25, {}}, {kT0 + 100, {}}, {kT0 + 150, {}}};
  auto a = associate(est, gt, {});
  ASSERT_TRUE(a.ok());
  ASSERT_EQ(a->size(), 3u);
  EXPECT_LT((a->ground_truth[0].translation() - Eigen::Vector3d(0.5, 1.0, 0.0)).norm(), 1e-15);
  EXPECT_NEAR(a->ground_truth[0].so3().log().z(), 0.25, 1e-12);
  EXPECT_NEAR(a->ground_truth[1].so3().log().z(), 1.0, 1e-12);
  EXPECT_NEAR(a->ground_truth[2].so3().log().z(), 0.5, 1e-12);
}

TEST(Associate, CountsPosesOutsideTheSpanAndInGaps) {
  dataset::Trajectory gt;
  for (int k = 0; k <= 10; ++k) gt.push_back({kT0 + k * 10'000'000LL, {}});
  for (int k = 0; k <= 10; ++k) gt.push_back({kT0 + 2'000'000'000LL + k * 10'000'000LL, {}});  // 1.9 s gap
  dataset::Trajectory est;
  for (int k = -5; k < 250; ++k) est.push_back({kT0 + k * 10'000'000LL + 3'000'000LL, {}});
  auto a = associate(est, gt, {});
  ASSERT_TRUE(a.ok());
  EXPECT_EQ(a->estimate_poses, 255u);
  EXPECT_EQ(a->outside_span, 5u + 40u);  // before 0 s, and after 2.1 s
  // Matched: the 10 poses inside each span, and the 10 on either side of the gap that lie within 0.1 s of
  // a ground-truth sample; the other 170 poses in the gap are unmatched.
  EXPECT_EQ(a->size(), 10u + 10u + 10u + 10u);
  EXPECT_EQ(a->unmatched, 170u);

  AssociationOptions nearest;
  nearest.mode = AssociationMode::kNearest;
  nearest.max_diff_ns = 2'000'000;  // the estimate is 3 ms off every sample
  EXPECT_FALSE(associate(est, gt, nearest).ok());
  nearest.max_diff_ns = 3'000'000;  // boundary is inclusive, as evo
  auto n = associate(est, gt, nearest);
  ASSERT_TRUE(n.ok());
  EXPECT_EQ(n->size(), 22u);
}

TEST(Associate, NearestKeepsRepeatedEstimateTimestampsAndBreaksTiesTowardsTheEarlierPose) {
  dataset::Trajectory gt = {{kT0, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(0, 0, 0))},
                            {kT0 + 10, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(1, 0, 0))},
                            {kT0 + 20, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(2, 0, 0))}};
  dataset::Trajectory est = {{kT0 + 5, {}}, {kT0 + 5, {}}, {kT0 + 16, {}}};
  AssociationOptions nearest;
  nearest.mode = AssociationMode::kNearest;
  auto a = associate(est, gt, nearest);
  ASSERT_TRUE(a.ok());
  ASSERT_EQ(a->size(), 3u);
  EXPECT_EQ(a->ground_truth[0].translation().x(), 0.0);
  EXPECT_EQ(a->ground_truth[1].translation().x(), 0.0);
  EXPECT_EQ(a->ground_truth[2].translation().x(), 2.0);
}

TEST(Associate, DisjointClocksGiveAMessageThatSaysWhatToCheck) {
  const auto gt = figureEight(kT0, 5'000'000, 100);
  auto est = figureEight(kT0, 5'000'000, 100);
  for (auto& pose : est) pose.t_ns /= 1000;  // microseconds written where nanoseconds were expected
  auto a = associate(est, gt, {});
  ASSERT_FALSE(a.ok());
  EXPECT_THAT(a.error().message(), HasSubstr("only 0 of 100 estimate poses could be associated"));
  EXPECT_THAT(a.error().message(), HasSubstr("same clock"));
  AssociationOptions shifted;
  shifted.estimate_offset_ns = kT0 - kT0 / 1000;  // a known clock offset brings them together
  EXPECT_TRUE(associate(est, gt, shifted).ok());
}

TEST(RelativeError, IsZeroForAPerfectEstimateAndScalesWithAScaleError) {
  const auto gt = figureEight(kT0, 10'000'000, 3000);
  RpeOptions options;
  options.distances_m = {1.0, 5.0};
  auto perfect = associate(gt, gt, {});
  ASSERT_TRUE(perfect.ok());
  for (const RelativeError& r : relativeError(*perfect, options)) {
    EXPECT_GT(r.translation_m.count, 100u);
    EXPECT_LT(r.translation_m.max, 1e-12);
    EXPECT_LT(r.rotation_deg.max, 1e-9);
  }
  // 3 % too large everywhere: a segment's translation error is 3 % of its chord, so at most 3 % of its path...
  auto scaled = associate(transformed(gt, geometry::Sim3d(1.03, {}, Eigen::Vector3d::Zero())), gt, {});
  ASSERT_TRUE(scaled.ok());
  for (const RelativeError& r : relativeError(*scaled, options)) {
    EXPECT_GT(r.translation_percent.mean, 0.5);
    EXPECT_LE(r.translation_percent.max, 3.0 + 1e-9);
  }
  // ... and exactly 3 % on a straight line, where chord and path are equal.
  dataset::Trajectory line;
  for (int k = 0; k < 1000; ++k) {
    line.push_back({kT0 + k * 10'000'000LL, geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0, 0, 0.01 * k)),
                                                           Eigen::Vector3d(0.01 * k, 0.005 * k, 0.0))});
  }
  auto scaled_line = associate(transformed(line, geometry::Sim3d(1.03, {}, Eigen::Vector3d::Zero())), line, {});
  ASSERT_TRUE(scaled_line.ok());
  for (const RelativeError& r : relativeError(*scaled_line, options)) {
    EXPECT_NEAR(r.translation_percent.min, 3.0, 1e-9);
    EXPECT_NEAR(r.translation_percent.max, 3.0, 1e-9);
  }
  options.pairing = RpePairing::kConsecutive;
  const auto consecutive = relativeError(*scaled, options);
  ASSERT_EQ(consecutive.size(), 2u);
  EXPECT_GT(consecutive[0].translation_m.count, consecutive[1].translation_m.count);
  options.distances_m = {1e6};
  EXPECT_EQ(relativeError(*scaled, options)[0].translation_m.count, 0u);
}

TEST(Evaluate, DegenerateMotionIsANoteNotACrash) {
  dataset::Trajectory line;
  for (int k = 0; k < 100; ++k)
    line.push_back({kT0 + k * 10'000'000LL, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(0.01 * k, 0, 0))});
  auto ev = evaluate(line, line, {});
  ASSERT_TRUE(ev.ok());
  EXPECT_EQ(ev->find(Alignment::kSE3), nullptr);
  EXPECT_NE(ev->find(Alignment::kPosYaw), nullptr);
  ASSERT_FALSE(ev->notes.empty());
  EXPECT_THAT(ev->notes.front(), HasSubstr("collinear"));
}

TEST(Evaluate, RejectsNonPositiveRpeDistances) {
  const auto gt = figureEight(kT0, 10'000'000, 100);
  EvaluationOptions options;
  options.rpe.distances_m = {0.0};
  EXPECT_EQ(evaluate(gt, gt, options).error().code(), ErrorCode::kInvalidArgument);
}

}  // namespace
}  // namespace cvislam::eval
