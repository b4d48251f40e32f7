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

// Each position mapped by S_est_gt, plus seeded isotropic Gaussian noise of `sigma_m` per axis.
dataset::Trajectory noisy(const dataset::Trajectory& in, const geometry::Sim3d& S_est_gt, double sigma_m,
                          std::mt19937& rng) {
  std::normal_distribution<double> noise(0.0, sigma_m);
  dataset::Trajectory out = transformed(in, S_est_gt);
  for (auto& pose : out) {
    pose.T_w_b = geometry::SE3d(pose.T_w_b.so3(),
                                pose.T_w_b.translation() + Eigen::Vector3d(noise(rng), noise(rng), noise(rng)));
  }
  return out;
}

dataset::Trajectory shiftedInTime(dataset::Trajectory in, std::int64_t dt_ns) {
  for (auto& pose : in) pose.t_ns += dt_ns;
  return in;
}

geometry::Sim3d yawAndShift(double yaw_deg, const Eigen::Vector3d& t) {
  return geometry::Sim3d(1.0, geometry::rotationAboutZ(yaw_deg * 3.14159265358979323846 / 180.0), t);
}

// With noise of sigma per axis, the RMSE of the error norm is sigma * sqrt(3): the fit absorbs at most 7 of the
// 3N degrees of freedom and, for N >= 1000 poses, the RMSE's relative spread is 1 / sqrt(6N) < 1.3 %; 5 % is
// wide enough not to be luck and narrow enough to catch a wrong transform.
constexpr double kNoiseTolerance = 0.05;

TEST(EvaluateJoint, EstimatesMappedByOneTransformHaveTheNoiseAsTheirJointAndOwnError) {
  constexpr double kSigma = 0.01;
  std::mt19937 rng(20240601);
  // Two agents on different paths in one world frame, over different times.
  const auto gt_a = figureEight(kT0, 10'000'000, 2000);
  const auto gt_b = transformed(figureEight(kT0 + 30'000'000'000LL, 10'000'000, 1200),
                                yawAndShift(90.0, Eigen::Vector3d(10.0, -2.0, 0.5)));
  // Both estimates in one map whose world is off the ground truth's by one rigid transform (yaw and
  // translation, so that position+yaw alignment can absorb it too).
  const geometry::Sim3d S_est_gt = yawAndShift(-35.0, Eigen::Vector3d(4.0, 1.0, -0.3));
  const auto est_a = noisy(gt_a, S_est_gt, kSigma, rng);
  const auto est_b = noisy(gt_b, S_est_gt, kSigma, rng);
  const std::vector<TrajectoryPair> pairs = {{"a", &est_a, &gt_a}, {"b", &est_b, &gt_b}};

  auto joint = evaluateJoint(pairs, {}, JointAlignment::kJoint);
  ASSERT_TRUE(joint.ok()) << joint.error().toString();
  ASSERT_EQ(joint->estimates.size(), 2u);
  EXPECT_EQ(joint->poses, 3200u);
  EXPECT_EQ(joint->estimates[0].poses.size(), 2000u);
  EXPECT_EQ(joint->estimates[1].poses.size(), 1200u);
  EXPECT_TRUE(joint->notes.empty());
  const double expected = kSigma * std::sqrt(3.0);
  for (Alignment alignment : {Alignment::kPosYaw, Alignment::kSE3, Alignment::kSim3}) {
    SCOPED_TRACE(toString(alignment));
    const AbsoluteError* all = joint->find(alignment);
    ASSERT_NE(all, nullptr);
    EXPECT_EQ(all->translation_m.count, 3200u);
    EXPECT_NEAR(all->translation_m.rmse, expected, kNoiseTolerance * expected);
    // The transform found is the inverse of the one applied, up to what the noise leaves: the rotation to about
    // sigma / (sqrt(N) * spread of the points, ~3 m) = 6e-5 rad, the translation to about sigma / sqrt(N) plus
    // that rotation times the 4 m lever arm of S_est_gt.
    const geometry::Sim3d residual = all->S_gt_est * S_est_gt;
    constexpr double kRotationBoundRad = 1e-3;
    EXPECT_LT(residual.translation().norm(), 0.5 * kSigma);
    EXPECT_LT(residual.so3().log().norm(), kRotationBoundRad);
    for (const Evaluation& ev : joint->estimates) {
      const AbsoluteError* own = ev.find(alignment);
      ASSERT_NE(own, nullptr);
      EXPECT_NEAR(own->translation_m.rmse, expected, kNoiseTolerance * expected);
      // The noise is on positions only: what remains is the error of the fitted rotation.
      EXPECT_LT(own->rotation_deg.rmse, kRotationBoundRad * 180.0 / 3.14159265358979323846);
      // Measured under the joint transform, not under one of its own.
      EXPECT_EQ(own->S_gt_est.translation(), all->S_gt_est.translation());
      EXPECT_EQ(own->S_gt_est.scale(), all->S_gt_est.scale());
    }
    // One transform for all: the joint mean square is the pose-weighted mean of the estimates'.
    const double a = joint->estimates[0].find(alignment)->translation_m.rmse;
    const double b = joint->estimates[1].find(alignment)->translation_m.rmse;
    EXPECT_NEAR(all->translation_m.rmse, std::sqrt((2000 * a * a + 1200 * b * b) / 3200), 1e-12);
  }
  ASSERT_TRUE(joint->sim3_scale.has_value());
  EXPECT_NEAR(*joint->sim3_scale, 1.0, 1e-3);
  EXPECT_EQ(*joint->estimates[1].sim3_scale, *joint->sim3_scale);
}

TEST(EvaluateJoint, EstimatesInDifferentFramesNeedTheirOwnTransforms) {
  constexpr double kSigma = 0.01;
  std::mt19937 rng(7);
  // Two agents fly the same route one after the other, so that pose i of one and of the other are at one place.
  const auto gt_a = figureEight(kT0, 10'000'000, 2000);
  const auto gt_b = shiftedInTime(gt_a, 100'000'000'000LL);
  // Their maps are not merged: b's world is 1 m and 10 degrees of yaw off a's.
  const geometry::Sim3d S_a = yawAndShift(20.0, Eigen::Vector3d(-1.0, 3.0, 0.0));
  const geometry::Sim3d S_b = S_a * yawAndShift(10.0, Eigen::Vector3d(1.0, 0.0, 0.0));
  const auto est_a = noisy(gt_a, S_a, kSigma, rng);
  const auto est_b = noisy(gt_b, S_b, kSigma, rng);
  const std::vector<TrajectoryPair> pairs = {{"a", &est_a, &gt_a}, {"b", &est_b, &gt_b}};

  auto each = evaluateJoint(pairs, {}, JointAlignment::kEach);
  ASSERT_TRUE(each.ok()) << each.error().toString();
  const double noise = kSigma * std::sqrt(3.0);
  for (const Evaluation& ev : each->estimates) {
    EXPECT_NEAR(ev.find(Alignment::kSE3)->translation_m.rmse, noise, kNoiseTolerance * noise);
    EXPECT_NEAR(ev.find(Alignment::kPosYaw)->translation_m.rmse, noise, kNoiseTolerance * noise);
  }
  EXPECT_NEAR(each->find(Alignment::kSE3)->translation_m.rmse, noise, kNoiseTolerance * noise);
  EXPECT_FALSE(each->sim3_scale.has_value());  // no single Sim3 when each estimate has its own

  auto joint = evaluateJoint(pairs, {}, JointAlignment::kJoint);
  ASSERT_TRUE(joint.ok()) << joint.error().toString();
  // A lower bound for any rigid X. Pose i of both agents is at one place p_i; the estimates are q_a = S_a p_i +
  // n_a and q_b = S_b p_i + n_b. Since X keeps distances, |X q_a - X q_b| = |q_a - q_b| =: d_i, and by the
  // triangle inequality the two residuals |p_i - X q_a| + |p_i - X q_b| >= d_i, so their squares sum to at least
  // d_i^2 / 2. Over all 2N poses: rmse^2 >= mean(d_i^2) / 4.
  ASSERT_EQ(joint->estimates[0].poses.size(), joint->estimates[1].poses.size());
  double sum_d2 = 0.0;
  const std::size_t n = joint->estimates[0].poses.size();
  for (std::size_t i = 0; i < n; ++i) {
    ASSERT_EQ(joint->estimates[0].poses.ground_truth[i].translation(),
              joint->estimates[1].poses.ground_truth[i].translation());
    sum_d2 +=
        (joint->estimates[0].poses.estimate[i].translation() - joint->estimates[1].poses.estimate[i].translation())
            .squaredNorm();
  }
  const double bound = std::sqrt(sum_d2 / static_cast<double>(n) / 4.0);
  EXPECT_GT(bound, 10.0 * noise);  // the geometry makes the two frames clearly distinguishable
  for (Alignment alignment : {Alignment::kPosYaw, Alignment::kSE3}) {
    SCOPED_TRACE(toString(alignment));
    ASSERT_NE(joint->find(alignment), nullptr);
    EXPECT_GE(joint->find(alignment)->translation_m.rmse, bound);
    EXPECT_GT(joint->find(alignment)->translation_m.rmse, 10.0 * each->find(alignment)->translation_m.rmse);
    // The joint transform is the least-squares one over all poses: better than either estimate's own, applied
    // to both.
    for (const Evaluation& own : each->estimates) {
      const geometry::Sim3d& S = own.find(alignment)->S_gt_est;
      const double a = absoluteErrorUnder(joint->estimates[0].poses, alignment, S).translation_m.rmse;
      const double b = absoluteErrorUnder(joint->estimates[1].poses, alignment, S).translation_m.rmse;
      EXPECT_LT(joint->find(alignment)->translation_m.rmse, std::sqrt((a * a + b * b) / 2.0));
    }
  }
}

TEST(EvaluateJoint, ThePooledRmseIsThePoseWeightedRootMeanSquareOfTheEstimatesOwnErrors) {
  std::mt19937 rng(12345);
  const auto gt_a = figureEight(kT0, 10'000'000, 1500);
  const auto gt_b = transformed(figureEight(kT0, 10'000'000, 400), yawAndShift(0.0, Eigen::Vector3d(0, 8.0, 0)));
  // Different noise and different pose counts, so that weighting by poses matters.
  const auto est_a = noisy(gt_a, yawAndShift(30.0, Eigen::Vector3d(1, 2, 3)), 0.005, rng);
  const auto est_b = noisy(gt_b, yawAndShift(-60.0, Eigen::Vector3d(-4, 0, 1)), 0.05, rng);
  const std::vector<TrajectoryPair> pairs = {{"a", &est_a, &gt_a}, {"b", &est_b, &gt_b}};
  auto each = evaluateJoint(pairs, {}, JointAlignment::kEach);
  ASSERT_TRUE(each.ok()) << each.error().toString();
  for (Alignment alignment : {Alignment::kPosYaw, Alignment::kSE3, Alignment::kSim3}) {
    SCOPED_TRACE(toString(alignment));
    // By hand, from each estimate's own per-pose errors.
    double sum_sq = 0.0;
    double sum = 0.0;
    double max = 0.0;
    std::size_t count = 0;
    std::vector<double> rmse;
    for (const Evaluation& ev : each->estimates) {
      const AbsoluteError* own = ev.find(alignment);
      ASSERT_NE(own, nullptr);
      for (double e : own->translation_errors_m) {
        sum_sq += e * e;
        sum += e;
        max = std::max(max, e);
        ++count;
      }
      rmse.push_back(own->translation_m.rmse);
    }
    const AbsoluteError* pooled = each->find(alignment);
    ASSERT_NE(pooled, nullptr);
    EXPECT_EQ(pooled->translation_m.count, 1900u);
    EXPECT_EQ(count, 1900u);
    EXPECT_NEAR(pooled->translation_m.rmse, std::sqrt(sum_sq / 1900.0), 1e-12);
    EXPECT_NEAR(pooled->translation_m.mean, sum / 1900.0, 1e-12);
    EXPECT_EQ(pooled->translation_m.max, max);
    // The same from the per-estimate RMSEs, weighted by their pose counts; the unweighted mean is far off.
    EXPECT_NEAR(pooled->translation_m.rmse, std::sqrt((1500 * rmse[0] * rmse[0] + 400 * rmse[1] * rmse[1]) / 1900.0),
                1e-12);
    EXPECT_GT(std::abs(pooled->translation_m.rmse - std::sqrt((rmse[0] * rmse[0] + rmse[1] * rmse[1]) / 2.0)), 0.01);
  }
}

TEST(EvaluateJoint, APairThatCannotBeAssociatedIsNamed) {
  const auto gt = figureEight(kT0, 10'000'000, 500);
  const auto late = shiftedInTime(gt, 1'000'000'000'000LL);
  const std::vector<TrajectoryPair> pairs = {{"first", &gt, &gt}, {"'second' (late.txt)", &late, &gt}};
  auto joint = evaluateJoint(pairs, {}, JointAlignment::kJoint);
  ASSERT_FALSE(joint.ok());
  EXPECT_THAT(joint.error().message(), HasSubstr("estimate 'second' (late.txt): only 0 of 500"));
  EXPECT_FALSE(evaluateJoint({}, {}, JointAlignment::kJoint).ok());
}

TEST(EvaluateJoint, ADegenerateEstimateStillCountsInTheJointAlignmentButHasNoPooledFigure) {
  // One agent on a straight line: SE3 cannot be fitted to it alone, but it can jointly with a second agent.
  const auto curve = figureEight(kT0, 10'000'000, 500);
  dataset::Trajectory line;
  for (int k = 0; k < 100; ++k) {
    line.push_back({kT0 + k * 10'000'000LL, geometry::SE3d(geometry::SO3d(), Eigen::Vector3d(0.01 * k, 5.0, 0))});
  }
  const std::vector<TrajectoryPair> pairs = {{"curve", &curve, &curve}, {"line", &line, &line}};
  auto joint = evaluateJoint(pairs, {}, JointAlignment::kJoint);
  ASSERT_TRUE(joint.ok());
  ASSERT_NE(joint->find(Alignment::kSE3), nullptr);
  EXPECT_LT(joint->estimates[1].find(Alignment::kSE3)->translation_m.rmse, 1e-9);
  EXPECT_TRUE(joint->notes.empty());
  auto each = evaluateJoint(pairs, {}, JointAlignment::kEach);
  ASSERT_TRUE(each.ok());
  EXPECT_EQ(each->find(Alignment::kSE3), nullptr);
  ASSERT_FALSE(each->notes.empty());
  EXPECT_THAT(each->notes.front(), HasSubstr("the se3 alignment of line failed"));
}

TEST(Evaluate, RejectsNonPositiveRpeDistances) {
  const auto gt = figureEight(kT0, 10'000'000, 100);
  EvaluationOptions options;
  options.rpe.distances_m = {0.0};
  EXPECT_EQ(evaluate(gt, gt, options).error().code(), ErrorCode::kInvalidArgument);
}

}  // namespace
}  // namespace cvislam::eval
