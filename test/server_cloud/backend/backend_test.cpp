// The server's back-end on synthetic visual-inertial maps with exact ground truth (test/support/vi_scenario): a
// smooth trajectory with IMU samples from its analytic derivatives, points on a box, pixel observations. Agents'
// maps are built from it as the server would hold them (keypoints, descriptors, observations, raw IMU and its
// preintegration between consecutive keyframes), then moved, drifted or perturbed; the back-end must recover
// the truth (backend_test_maps.hpp). Real Ceres solves and the real worker threads; no mocks. What happens when
// changes arrive while a GBA runs is in backend_concurrency_test.cpp, map merges in backend_merge_test.cpp.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <map>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/backend/map_fusion.hpp"
#include "server_cloud/backend/redundancy.hpp"
#include "test/server_cloud/backend/backend_test_maps.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::server::backend {
namespace {

using namespace test_maps;  // NOLINT(google-build-using-namespace): the tests' shared maps and fixture

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

// ---------------------------------------------------------------------------------------------- global BA
TEST(GlobalBa, ConvergesToTheTruthFromAPerturbedStartWithImuFactorsOnlyInsideEachAgent) {
  const test::ViScenario s = scenario(16, 0.5, 0.5);
  MapContent map(0);
  buildTwoAgentsFusedMap(map, s);
  if (HasFatalFailure()) return;
  // The best the data allows: the solve started at the truth (0.5 px noise on 5-9 m points). The server's
  // default stops once an iteration gains less than 1e-4 of the cost; here the solves run to the optimum.
  GlobalBaOptions options;
  options.full_iterations = 30;
  options.function_tolerance = 1e-8;
  Result<GbaSnapshot> from_truth = makeGbaSnapshot(map, {{1, sensorsOf(s)}, {2, sensorsOf(s)}});
  ASSERT_TRUE(from_truth.ok());
  ASSERT_TRUE(runGlobalBa(*from_truth, options).ok());
  perturbAllButTheGauge(map, 5);
  const double before = std::max(maxPositionError(map, s, 1), maxPositionError(map, s, 2));
  ASSERT_GT(before, 0.05);

  Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, {{1, sensorsOf(s)}, {2, sensorsOf(s)}});
  ASSERT_TRUE(snapshot.ok()) << snapshot.error().toString();
  // The server's default options end within 1 % of the optimum's cost and within 1 cm of the truth.
  GbaSnapshot by_default = *snapshot;
  Result<GlobalBaSummary> default_summary = runGlobalBa(by_default, GlobalBaOptions{});
  ASSERT_TRUE(default_summary.ok()) << default_summary.error().toString();
  Result<GlobalBaSummary> summary = runGlobalBa(*snapshot, options);
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_LT(default_summary->full_iterations, summary->full_iterations);
  EXPECT_LT(default_summary->final_cost, 1.01 * summary->final_cost);
  for (std::size_t k = 0; k < by_default.keyframes.size(); ++k) {
    const KeyframeId& id = by_default.keyframes[k].id;
    const Vector3d truth = s.keyframe_states[id.counter].T_w_s.translation();
    EXPECT_LT((by_default.keyframes[k].T_w_s.translation() - truth).norm(), 0.01) << id.toString();
  }
  // IMU only between consecutive keyframes of one agent: 7 + 7, never across agents.
  EXPECT_EQ(summary->imu_factors, 14);
  EXPECT_LT(summary->final_cost, 0.2 * summary->initial_cost);
  for (const auto& [id, kf] : map.keyframes()) EXPECT_FALSE(kf.refined) << id.toString() << " before any GBA";
  const AppliedCorrections applied = applyCorrections(map, keyframeCorrections(*snapshot), pointCorrections(*snapshot));
  EXPECT_EQ(applied.keyframes_optimised, 16);
  for (const auto& [id, kf] : map.keyframes()) EXPECT_TRUE(kf.refined) << id.toString() << " is the GBA's state now";
  const double after = std::max(maxPositionError(map, s, 1), maxPositionError(map, s, 2));
  EXPECT_LT(after, 0.01) << "before " << before;
  // From the perturbed start it reaches the same optimum as from the truth.
  ASSERT_EQ(snapshot->points.size(), from_truth->points.size());
  double worst_point = 0.0;
  for (std::size_t p = 0; p < snapshot->points.size(); ++p) {
    worst_point = std::max(worst_point, (snapshot->points[p].p_w - from_truth->points[p].p_w).norm());
  }
  EXPECT_LT(worst_point, 0.005);
  double worst_pose = 0.0;
  for (std::size_t k = 0; k < snapshot->keyframes.size(); ++k) {
    worst_pose = std::max(
        worst_pose, (snapshot->keyframes[k].T_w_s.translation() - from_truth->keyframes[k].T_w_s.translation()).norm());
  }
  EXPECT_LT(worst_pose, 0.001);
}

// A time budget stops the solve before the first iteration that would end past it, but each of the two steps takes
// its first: a budget already spent leaves one structure and one full iteration, applied as any result. Each
// accepted step is recorded with its time and cost, the last being the final cost.
TEST(GlobalBa, ATimeBudgetStopsEachStepAfterItsFirstIterationAndTheSummarySaysSo) {
  const test::ViScenario s = scenario(16, 0.5, 0.5);
  MapContent map(0);
  buildTwoAgentsFusedMap(map, s);
  if (HasFatalFailure()) return;
  perturbAllButTheGauge(map, 5);
  Result<GbaSnapshot> start = makeGbaSnapshot(map, {{1, sensorsOf(s)}, {2, sensorsOf(s)}});
  ASSERT_TRUE(start.ok());
  for (const GlobalBaOptions::Solver solver : {GlobalBaOptions::Solver::kSchur, GlobalBaOptions::Solver::kCeres}) {
    SCOPED_TRACE(toString(solver));
    GlobalBaOptions options;
    options.solver = solver;
    GbaSnapshot unbudgeted = *start;
    const Result<GlobalBaSummary> whole = runGlobalBa(unbudgeted, options);
    ASSERT_TRUE(whole.ok());
    EXPECT_FALSE(whole->budget_reached);
    ASSERT_GT(whole->full_iterations, 2) << "a perturbed start needs several: the budget below must cut them";

    options.time_budget_s = 1e-9;
    GbaSnapshot budgeted = *start;
    const Result<GlobalBaSummary> cut = runGlobalBa(budgeted, options);
    ASSERT_TRUE(cut.ok());
    EXPECT_TRUE(cut->budget_reached);
    EXPECT_FALSE(cut->cancelled);
    if (solver == GlobalBaOptions::Solver::kSchur) {
      EXPECT_EQ(cut->structure_iterations, 1);
      EXPECT_EQ(cut->full_iterations, 1);
    }
    EXPECT_LT(cut->full_iterations, whole->full_iterations);
    EXPECT_LT(cut->final_cost, cut->initial_cost);
    EXPECT_GT(cut->final_cost, whole->final_cost);

    ASSERT_FALSE(whole->accepted.empty());
    EXPECT_EQ(whole->accepted.back().cost, whole->final_cost);
    for (std::size_t i = 1; i < whole->accepted.size(); ++i) {
      EXPECT_GE(whole->accepted[i].t_s, whole->accepted[i - 1].t_s);
      EXPECT_LE(whole->accepted[i].cost, whole->accepted[i - 1].cost);
    }
  }
  GlobalBaOptions bad;
  bad.time_budget_s = -1.0;
  EXPECT_NE(bad.validate().error().toString().find("time_budget_s"), std::string::npos);
}

// A windowed solve (the merge's correction) moves the window's keyframes and the points they see, holds the
// keyframes around them, and leaves the left-out ones out of the problem; applied, the held keyframes stay and
// a left-out newer one is carried along like a keyframe that arrived during the solve.
TEST(GlobalBa, AWindowedSolveMovesTheWindowAndHoldsTheKeyframesAroundIt) {
  const test::ViScenario s = scenario(16, 0.5, 0.3);
  MapContent map(0);
  buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 15}, nullptr);
  // Keyframes 6-9 are 4 cm off; keyframe 15 too, but it is left out.
  GbaWindow window;
  for (std::uint32_t k = 6; k <= 9; ++k) window.free.insert(KeyframeId{1, k});
  window.left_out.insert(KeyframeId{1, 15});
  for (std::uint32_t k : {6U, 7U, 8U, 9U, 15U}) {
    ServerKeyframe* kf = map.keyframe(KeyframeId{1, k});
    kf->T_w_s = SE3d(kf->T_w_s.so3(), kf->T_w_s.translation() + Vector3d(0.03, -0.02, 0.02));
  }
  Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, {{1, sensorsOf(s)}}, &window);
  ASSERT_TRUE(snapshot.ok()) << snapshot.error().toString();
  int held = 0;
  for (const GbaKeyframe& kf : snapshot->keyframes) {
    EXPECT_NE(kf.id, (KeyframeId{1, 15})) << "left out";
    held += kf.held ? 1 : 0;
  }
  EXPECT_EQ(snapshot->keyframes.size(), 15U);
  EXPECT_EQ(held, 11);
  Result<GlobalBaSummary> summary = runGlobalBa(*snapshot, GlobalBaOptions{});
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  const std::vector<KeyframeCorrection> corrections = keyframeCorrections(*snapshot);
  ASSERT_EQ(corrections.size(), 4U) << "held keyframes are not corrected";
  const std::unordered_set<KeyframeId> held_ids = heldKeyframes(*snapshot);
  EXPECT_EQ(held_ids.size(), 11U);
  const AppliedCorrections applied = applyCorrections(map, corrections, pointCorrections(*snapshot),
                                                      ApplyOptions{.marks_refined = true, .held = &held_ids});
  EXPECT_EQ(applied.keyframes_optimised, 4);
  EXPECT_EQ(applied.keyframes_propagated, 1) << "keyframe 15 alone";
  for (std::uint32_t k = 0; k < 16; ++k) {
    const Vector3d truth = s.keyframe_states[k].T_w_s.translation();
    EXPECT_LT((map.keyframe(KeyframeId{1, k})->T_w_s.translation() - truth).norm(), 0.005) << k;
  }
}

// A loop's pose graph moves keyframes without their points' evidence: what it applies is not the refined state
// the downlink waits for (another agent's keyframes go down only while refined), so it clears the flag that a GBA
// set, and the GBA after it sets it again.
TEST(GlobalBa, APoseGraphsCorrectionClearsTheRefinedStateThatAGbaSets) {
  const test::ViScenario s = scenario(8, 0.5, 0.5);
  MapContent map(0);
  buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 7}, nullptr);
  std::vector<KeyframeCorrection> moves;
  for (const auto& [id, kf] : map.keyframes()) {
    moves.push_back({id, kf.T_w_s, SE3d(SO3d(), Vector3d(0.01, 0.0, 0.0)) * kf.T_w_s, std::nullopt});
  }
  ASSERT_FALSE(moves.empty());
  (void)applyCorrections(map, moves, {}, ApplyOptions{.marks_refined = true});
  for (const auto& [id, kf] : map.keyframes()) {
    EXPECT_TRUE(kf.refined) << id.toString() << " after a GBA";
    EXPECT_FALSE(kf.provisional) << id.toString() << " after a GBA";
  }
  for (KeyframeCorrection& m : moves) {
    m.T_w_s_before = map.keyframe(m.id)->T_w_s;
    m.T_w_s_after = SE3d(SO3d(), Vector3d(0.0, 0.02, 0.0)) * m.T_w_s_before;
  }
  const AppliedCorrections pose_graph = applyCorrections(map, moves, {}, ApplyOptions{.marks_refined = false});
  EXPECT_EQ(pose_graph.keyframes_optimised, static_cast<int>(moves.size()));
  for (const auto& [id, kf] : map.keyframes()) {
    EXPECT_FALSE(kf.refined) << id.toString() << " after a pose graph";
    EXPECT_TRUE(kf.provisional) << id.toString() << " after a pose graph";
  }
  (void)applyCorrections(map, moves, {}, ApplyOptions{.marks_refined = true});
  for (const auto& [id, kf] : map.keyframes()) EXPECT_FALSE(kf.provisional) << id.toString() << " after the GBA";
}

// A map whose gravity is off by 1 deg of roll (every estimate turned about the oldest keyframe): vision cannot
// see it, the IMU can. A gauge on the whole oldest pose keeps the tilt; the position-and-yaw gauge lets GBA
// take it out and leaves the oldest keyframe's position and heading where they were.
TEST(GlobalBa, ThePositionAndYawGaugeLetsGravityLevelATiltedMap) {
  const test::ViScenario s = scenario(16, 0.5, 0.5);
  const Vector3d p0 = s.keyframe_states[0].T_w_s.translation();
  const SO3d tilt = SO3d::exp(Vector3d(1.0 * M_PI / 180.0, 0.0, 0.0));
  const SE3d E(tilt, p0 - (tilt * p0));
  const auto tiltErrorDeg = [&](const GbaSnapshot& snapshot) {  // the oldest keyframe's gravity direction
    const Vector3d up_est = snapshot.keyframes[0].T_w_s.so3().inverse() * Vector3d::UnitZ();
    const Vector3d up_true = s.keyframe_states[0].T_w_s.so3().inverse() * Vector3d::UnitZ();
    return std::acos(std::clamp(up_est.dot(up_true), -1.0, 1.0)) * 180.0 / M_PI;
  };
  for (const bool yaw_only : {false, true}) {
    MapContent map(0);
    buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 15, .E = [&](int) { return E; }}, nullptr);
    Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, {{1, sensorsOf(s)}});
    ASSERT_TRUE(snapshot.ok());
    ASSERT_EQ(snapshot->keyframes[0].id, (KeyframeId{1, 0}));
    const SE3d oldest_before = snapshot->keyframes[0].T_w_s;
    ASSERT_NEAR(tiltErrorDeg(*snapshot), 1.0, 1e-6);
    GlobalBaOptions options;
    options.full_iterations = 30;
    options.gauge_position_yaw_only = yaw_only;
    ASSERT_TRUE(runGlobalBa(*snapshot, options).ok());
    const SE3d& oldest_after = snapshot->keyframes[0].T_w_s;
    EXPECT_LT((oldest_after.translation() - oldest_before.translation()).norm(), 1e-3) << "yaw only " << yaw_only;
    // The change of orientation in the world frame; its z component is the change of heading.
    const double yaw_change = (oldest_after.so3() * oldest_before.so3().inverse()).log().z();
    EXPECT_LT(std::abs(yaw_change), 1e-3) << "yaw only " << yaw_only;
    if (yaw_only) {
      EXPECT_LT(tiltErrorDeg(*snapshot), 0.1);
    } else {
      EXPECT_GT(tiltErrorDeg(*snapshot), 0.9) << "the whole pose is held";
    }
  }
}

TEST(GlobalBa, TheSnapshotTakesTheKeypointsIngestUndistorted) {
  const test::ViScenario s = scenario(6, 0.5, 0.3);
  MapContent map(0);
  buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 5}, nullptr);
  // Keyframe 3 carries undistorted pixels that differ from its keypoints (as a distorting camera's would); the
  // camera here has no distortion, so only the stored ones can give these values.
  const Eigen::Vector2f offset(7.0F, -3.0F);
  ServerKeyframe* kf3 = map.keyframe(KeyframeId{1, 3});
  for (const features::Keypoint& key : kf3->keypoints) kf3->keypoints_undistorted.push_back(key.px + offset);
  Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, {{1, sensorsOf(s)}});
  ASSERT_TRUE(snapshot.ok());
  int checked = 0;
  for (const GbaKeyframe& kf : snapshot->keyframes) {
    const ServerKeyframe& held = *map.keyframe(kf.id);
    Eigen::Vector2d shift = Eigen::Vector2d::Zero();
    if (kf.id.counter == 3) shift = offset.cast<double>();
    for (const GbaObservation& o : kf.observations) {
      const bool from_a_keypoint = std::any_of(held.keypoints.begin(), held.keypoints.end(), [&](const auto& key) {
        return (key.px.template cast<double>() + shift - o.px_undistorted).norm() < 1e-4;
      });
      EXPECT_TRUE(from_a_keypoint) << kf.id.toString();
      ++checked;
    }
  }
  EXPECT_GT(checked, 100);
}

TEST(GlobalBa, ACancelledSolveSaysSoAndChangesNothing) {
  const test::ViScenario s = scenario(8, 0.5, 0.5);
  MapContent map(0);
  buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 7}, nullptr);
  Result<GbaSnapshot> snapshot = makeGbaSnapshot(map, {{1, sensorsOf(s)}});
  ASSERT_TRUE(snapshot.ok());
  const std::atomic<bool> cancel{true};
  Result<GlobalBaSummary> summary = runGlobalBa(*snapshot, GlobalBaOptions{}, &cancel);
  ASSERT_TRUE(summary.ok());
  EXPECT_TRUE(summary->cancelled);
  EXPECT_FALSE(makeGbaSnapshot(map, {}).ok());  // no sensors: the error names the agent
}

// An agent map's frame change after a GBA or a loop (T_m_w follows it): 10 keyframes 0.3 m apart along x, and a
// change given per keyframe.
std::map<std::int64_t, TimedChange> seriesOf(const std::vector<SE3d>& deltas) {
  std::map<std::int64_t, TimedChange> series;
  for (std::size_t i = 0; i < deltas.size(); ++i) {
    series.emplace(static_cast<std::int64_t>(i) * 500'000'000, TimedChange{deltas[i], Vector3d(0.3 * i, 1.0, 1.5)});
  }
  return series;
}

double angleDeg(const SO3d& a, const SO3d& b) {
  return (a.inverse() * b).log().norm() * 180.0 / M_PI;
}

TEST(FrameChange, ARigidChangeOfTheWholeWindowIsThatChangeWhateverTheWindow) {
  const SE3d rigid(SO3d::exp(Vector3d(0.01, -0.02, 0.3)), Vector3d(0.4, -0.2, 0.05));
  const auto series = seriesOf(std::vector<SE3d>(10, rigid));
  for (int window : {1, 3, 10, 50}) {
    const SE3d change = windowChange(series, window);
    EXPECT_LT(angleDeg(change.so3(), rigid.so3()), 1e-9) << window;
    EXPECT_LT((change.translation() - rigid.translation()).norm(), 1e-9) << window;
  }
}

TEST(FrameChange, TheNewestKeyframesOwnTurnDoesNotTurnTheFrameWhenTheWindowFollowsTen) {
  // Nine keyframes move by one rigid change; the newest, least constrained, also turns 1 deg about its own position.
  const SE3d rigid(SO3d::exp(Vector3d(0.0, 0.0, 0.02)), Vector3d(0.05, 0.0, 0.0));
  std::vector<SE3d> deltas(10, rigid);
  const Vector3d p_newest(0.3 * 9, 1.0, 1.5);
  const SE3d about_newest = SE3d(SO3d(), rigid * p_newest) *
                            SE3d(SO3d::exp(Vector3d(0.0, 0.0, M_PI / 180.0)), Vector3d::Zero()) *
                            SE3d(SO3d(), -(rigid * p_newest));
  deltas.back() = about_newest * rigid;
  const auto series = seriesOf(deltas);
  const Vector3d anchor(p_newest + Vector3d(8.0, 0.0, 0.0));  // what is sent next, 8 m from the agent
  const SE3d newest_only = windowChange(series, 1);
  const SE3d ten = windowChange(series, 10);
  EXPECT_NEAR(angleDeg(newest_only.so3(), rigid.so3()), 1.0, 1e-6);
  EXPECT_NEAR(angleDeg(ten.so3(), rigid.so3()), 0.1, 1e-3);
  // The newest alone swings the anchor by 8 m x 1 deg = 14 cm; following ten keyframes, by a tenth of that.
  EXPECT_GT((newest_only * anchor - rigid * anchor).norm(), 0.13);
  EXPECT_LT((ten * anchor - rigid * anchor).norm(), 0.02);
  // And the agent's newest keyframe itself still lands within millimetres of its own corrected position.
  EXPECT_LT((ten * p_newest - deltas.back() * p_newest).norm(), 0.01);
}

TEST(FrameChange, TranslationsAlongTheWindowAverage) {
  std::vector<SE3d> deltas;
  for (int i = 0; i < 10; ++i) deltas.emplace_back(SO3d(), Vector3d(0.01 * i, 0.0, -0.02));
  const SE3d change = windowChange(seriesOf(deltas), 4);  // the newest four: 0.06 .. 0.09
  EXPECT_LT(change.so3().log().norm(), 1e-12);
  EXPECT_NEAR(change.translation().x(), 0.075, 1e-12);
  EXPECT_NEAR(change.translation().z(), -0.02, 1e-12);
}

// -------------------------------------------------------------------------------- the worker: a mission
// Agent 1's drift in the loop tests below: from keyframe 12 on the estimate drifts, as VIO does, a little more at
// every keyframe up to 3 deg of yaw and 0.4 m at keyframe 23, with points made anew (nobody re-associated them).
SE3d loopDrift(int k) {
  const double f = k < 12 ? 0.0 : static_cast<double>(k - 11) / 12.0;
  return SE3d(SO3d::exp(Vector3d(0.0, 0.0, 0.05 * f)), f * Vector3d(0.3, -0.25, 0.05));
}
int loopGeneration(int k) {
  return k >= 12 ? 1 : 0;
}

// The loop of those tests, measured exactly: keyframe 22 against keyframe 3's points; then the worker is drained.
void closeTheLoop22To3(BackendWorker& worker, MapId map, const test::ViScenario& s) {
  ASSERT_TRUE(worker.onMatch("m", exactLoop(map, s, 22, 3)));
  worker.drain(false);
}

TEST_F(BackendWorkerTest, ALoopClosureRemovesAnInjectedDrift) {
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  // A loop from keyframe 22 to keyframe 3 sees the truth.
  const SE3d drift = loopDrift(22);
  const auto map =
      addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 23, .E = loopDrift, .generation = loopGeneration});
  const double before = maxPositionError(*map->read(), s, 1);
  ASSERT_GT(before, 0.25);

  BackendOptions options;
  options.redundancy.enabled = false;
  BackendWorker worker(options, registry_, nullptr);
  closeTheLoop22To3(worker, map->id(), s);

  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.loops.size(), 1U);
  const auto events = mission_->events().read(1, 100).events;
  ASSERT_GE(events.size(), 2U);
  EXPECT_EQ(events[0].kind, MissionEvent::Kind::kMapCorrected);
  EXPECT_EQ(events[0].cause, "loop closure");
  EXPECT_GT(events[0].keyframes, 10U);
  EXPECT_EQ(events[1].cause, "global BA");
  // The pose graph alone took out most of the query keyframe's drift (GBA the rest, below).
  const Vector3d p22 = s.keyframe_states[22].T_w_s.translation();
  const double drift_m = (drift * p22 - p22).norm();
  EXPECT_GT(stats.loops[0].correction_m, 0.8 * drift_m);
  EXPECT_LT(stats.loops[0].correction_m, 1.1 * drift_m);
  EXPECT_GT(stats.loops[0].fusion.projection_fused, 50) << "the new points are the old ones";
  ASSERT_FALSE(stats.gba.empty());
  const auto content = map->read();
  EXPECT_TRUE(content->checkConsistency().ok());
  const double after = maxPositionError(*content, s, 1);
  EXPECT_LT(after, 0.02) << "before " << before;
}

// With a budget that every GBA overruns, the loop's GBA stops after its first iterations and is applied: the loop's
// time to refined is set by it, and every keyframe holds its state. The final GBA has no budget and runs to
// convergence.
TEST_F(BackendWorkerTest, ABudgetedGbaIsAppliedAfterItsFirstIterationsAndTheFinalOneRunsToConvergence) {
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  const auto map =
      addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 23, .E = loopDrift, .generation = loopGeneration});
  const double before = maxPositionError(*map->read(), s, 1);
  ASSERT_GT(before, 0.25);

  BackendOptions options;
  options.redundancy.enabled = false;
  options.gba_time_budget_s = 1e-9;
  BackendWorker worker(options, registry_, nullptr);
  closeTheLoop22To3(worker, map->id(), s);

  BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.loops.size(), 1U);
  EXPECT_GT(stats.loops[0].match_to_optimised_s, 0.0) << "the budgeted GBA counts as the loop's refinement";
  ASSERT_EQ(stats.gba.size(), 1U) << "no continuation";
  EXPECT_TRUE(stats.gba[0].summary.budget_reached);
  EXPECT_FALSE(stats.gba[0].final);
  EXPECT_EQ(stats.gba[0].summary.full_iterations, 1);
  EXPECT_LT(stats.gba[0].summary.final_cost, stats.gba[0].summary.initial_cost);
  {
    const auto content = map->read();
    EXPECT_TRUE(content->checkConsistency().ok());
    for (const auto& [id, kf] : content->keyframes()) EXPECT_TRUE(kf.refined) << id.toString() << ": applied";
    EXPECT_LT(maxPositionError(*content, s, 1), 0.25 * before);
  }

  // Away from the optimum again: the final GBA needs more than one iteration, and takes them.
  perturbAllButTheGauge(*map->write(), 7);
  worker.drain(true);
  stats = worker.stats("m");
  ASSERT_EQ(stats.gba.size(), 2U);
  EXPECT_TRUE(stats.gba[1].final);
  EXPECT_FALSE(stats.gba[1].summary.budget_reached);
  EXPECT_GT(stats.gba[1].summary.full_iterations, 1);
  EXPECT_LT(maxPositionError(*map->read(), s, 1), 0.02);

  BackendOptions bad;
  bad.gba_time_budget_s = -1.0;
  ASSERT_FALSE(bad.validate().ok());
  EXPECT_NE(bad.validate().error().toString().find("gba_time_budget_s"), std::string::npos);
}

TEST(LoopWindow, FreesTheLoopsSidesThenTheMostMovedAgentMapsUpToTheFractionAndNeverTheBarelyMoved) {
  const test::ViScenario s = scenario(12, 0.5, 0.3);
  MapContent map(0);
  for (AgentId agent = 1; agent <= 4; ++agent) {
    buildAgentMap(map, s, AgentPlan{.agent = agent, .first = 0, .last = 9}, nullptr);
  }
  // Every keyframe of agent a moved by move_m[a]: 1 by 5 cm, 2 by 2 cm, 3 by 3 cm, 4 by half a millimetre.
  const std::map<AgentId, double> move_m{{1, 0.05}, {2, 0.02}, {3, 0.03}, {4, 0.0005}};
  std::vector<KeyframeCorrection> corrections;
  for (const auto& [id, kf] : map.keyframes()) {
    corrections.push_back(
        {id, kf.T_w_s, SE3d(SO3d(), Vector3d(move_m.at(id.agent), 0.0, 0.0)) * kf.T_w_s, std::nullopt});
  }
  EXPECT_EQ(loopWindowAgentMaps(map, corrections, {}, 0.01, 0.1, 1.0).map_agent_maps, 4);
  const auto agents = [](const std::set<AgentMapKey>& keys) {
    std::set<AgentId> out;
    for (const auto& [agent, agent_map] : keys) out.insert(agent);
    return out;
  };
  const KeyframeId side1{1, 9};
  const KeyframeId side4{4, 2};
  // 40 keyframes, 10 per agent map. The sides come first even when barely moved (agent 4).
  EXPECT_EQ(agents(loopWindowAgentMaps(map, corrections, {side1, side4}, 0.01, 0.1, 0.6).free),
            (std::set<AgentId>{1, 4}));
  EXPECT_EQ(agents(loopWindowAgentMaps(map, corrections, {side1, side4}, 0.01, 0.1, 0.8).free),
            (std::set<AgentId>{1, 3, 4}))
      << "agent 3 (3 cm) before agent 2 (2 cm)";
  EXPECT_EQ(agents(loopWindowAgentMaps(map, corrections, {side1}, 0.01, 0.1, 1.0).free), (std::set<AgentId>{1, 2, 3}))
      << "agent 4 moved less than the bound";
  EXPECT_EQ(agents(loopWindowAgentMaps(map, corrections, {side1}, 0.025, 0.1, 1.0).free), (std::set<AgentId>{1, 3}));
}

TEST_F(BackendWorkerTest, ALoopInALargeMapHasAGbaOfTheAgentMapsItsPoseGraphMovedTheRestHeld) {
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  // Agent 1 drifts from keyframe 12 on as in ALoopClosureRemovesAnInjectedDrift. Agent 2 flew the same keyframes
  // without drift, in the same map, its points fused with those of agent 1's first half (as a merge leaves them):
  // the loop's pose graph moves agent 1's second half and barely agent 2.
  const auto map =
      addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 23, .E = loopDrift, .generation = loopGeneration});
  {
    auto record = mission_->agent(2)->write();
    record->sensors = sensorsOf(s);
    record->agent_maps[0] = AgentRecord::AgentMap{map->id(), SE3d()};
    auto content = map->write();
    buildAgentMap(*content, s, AgentPlan{.agent = 2, .first = 0, .last = 23}, &*record);
    for (std::size_t p = 0; p < s.points.size(); ++p) {
      const MapPointId a{1, static_cast<std::uint32_t>(p)};
      const MapPointId b{2, static_cast<std::uint32_t>(p)};
      if (content->point(a) != nullptr && content->point(b) != nullptr) {
        ASSERT_TRUE(content->mergePoints(b, a).ok());
      }
    }
    ASSERT_TRUE(content->checkConsistency().ok());
  }

  BackendOptions options;
  options.redundancy.enabled = false;
  options.gba_window_above_keyframes = 40;  // the map holds 48
  BackendWorker worker(options, registry_, nullptr);
  closeTheLoop22To3(worker, map->id(), s);

  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.loops.size(), 1U);
  ASSERT_FALSE(stats.gba.empty());
  const GbaRecord& gba = stats.gba.front();
  EXPECT_TRUE(gba.windowed) << "a loop in a map above gba_window_above_keyframes";
  EXPECT_EQ(gba.held_keyframes, 24) << "agent 2's keyframes, which the pose graph barely moved";
  EXPECT_EQ(stats.loops[0].window_agent_maps, 1);
  EXPECT_EQ(stats.loops[0].map_agent_maps, 2);
  const auto content = map->read();
  EXPECT_TRUE(content->checkConsistency().ok());
  EXPECT_LT(maxPositionError(*content, s, 1), 0.02) << "agent 1's drift is gone";
  EXPECT_LT(maxPositionError(*content, s, 2), 0.02);
}

// ------------------------------------------------------------------------------------ new keyframe fusion
// Two agents in one map frame (as after a merge), over the same points but with points of their own: agent 1
// flies keyframes 0-11, agent 2 keyframes 8-19. Nothing links agent 2's keyframes to agent 1's.
struct TwoAgentsOnePlace {
  test::ViScenario s = scenario(20, 0.5, 0.3);
  MapContent map{0};
  AgentSensorsMap sensors;
  std::map<AgentId, recognition::AgentCamera> cameras;
  TwoAgentsOnePlace() {
    buildAgentMap(map, s, AgentPlan{.agent = 1, .first = 0, .last = 11}, nullptr);
    buildAgentMap(map, s, AgentPlan{.agent = 2, .first = 8, .last = 19}, nullptr);
    for (AgentId a : {1U, 2U}) cameras.emplace(a, recognition::AgentCamera{pinholeCamera(s), s.T_s_c});
  }
  [[nodiscard]] recognition::CameraLookup lookup() const {
    return [this](AgentId a) -> const recognition::AgentCamera* {
      const auto it = cameras.find(a);
      return it == cameras.end() ? nullptr : &it->second;
    };
  }
  [[nodiscard]] int covisibilityWithAgent1(const KeyframeId& id) const {
    int shared = 0;
    for (const auto& [other, count] : map.covisible(id)) shared += other.agent == 1 ? count : 0;
    return shared;
  }
};

TEST(NewKeyframeFusion, FindsTheSamePointsInANearbyKeyframeOfAnotherAgentAndMakesThemOne) {
  TwoAgentsOnePlace place;
  const KeyframeId newest{2, 8};
  ASSERT_EQ(place.covisibilityWithAgent1(newest), 0);
  const std::size_t points_before = place.map.points().size();

  FusionOptions options;
  const std::vector<KeyframeId> nearby = nearbyKeyframes(place.map, newest, place.lookup(), options);
  EXPECT_EQ(nearby.size(), 10U);
  EXPECT_TRUE(std::any_of(nearby.begin(), nearby.end(), [](const KeyframeId& id) { return id.agent == 1; }));
  const std::vector<ProjectionMatch> matches = searchNewKeyframe(place.map, newest, place.lookup(), options);
  FusionReport report;
  applyProjectionMatches(place.map, matches, report);

  EXPECT_GT(report.projection_fused, 50);
  EXPECT_LT(place.map.points().size(), points_before - 50);
  EXPECT_GT(place.covisibilityWithAgent1(newest), 50) << "the agents' keyframes are joined";
  EXPECT_TRUE(place.map.checkConsistency().ok());
  // Every fused point is one physical point: its observations are all of one scenario point (same descriptor).
  for (const auto& [id, p] : place.map.points()) {
    for (const auto& o : p.observations) {
      const ServerKeyframe* kf = place.map.keyframe(o.keyframe);
      ASSERT_EQ(kf->descriptors[o.keypoint], p.descriptor) << id.toString() << " joined two physical points";
    }
  }
}

TEST(NewKeyframeFusion, WithoutNearbyKeyframesOnlyItsOwnCovisibleOnesAreSearched) {
  TwoAgentsOnePlace place;
  FusionOptions options;
  const auto touchesAgent1 = [](const std::vector<ProjectionMatch>& matches) {
    return std::any_of(matches.begin(), matches.end(),
                       [](const ProjectionMatch& m) { return m.point.agent == 1U || m.keyframe.agent == 1U; });
  };
  EXPECT_TRUE(touchesAgent1(searchNewKeyframe(place.map, KeyframeId{2, 8}, place.lookup(), options)));
  options.nearby_keyframes = 0;
  EXPECT_FALSE(touchesAgent1(searchNewKeyframe(place.map, KeyframeId{2, 8}, place.lookup(), options)));
}

TEST(NewKeyframeFusion, KeyframesThatLookTheOtherWayAreNotNearby) {
  TwoAgentsOnePlace place;
  FusionOptions options;
  // Turn agent 1's keyframes round (their points stay): none looks the way agent 2's keyframe 8 does.
  for (std::uint32_t k = 0; k <= 11; ++k) {
    ServerKeyframe* kf = place.map.keyframe(KeyframeId{1, k});
    kf->T_w_s = SE3d(kf->T_w_s.so3() * SO3d::exp(Vector3d(0.0, M_PI, 0.0)), kf->T_w_s.translation());
  }
  for (const KeyframeId& id : nearbyKeyframes(place.map, KeyframeId{2, 8}, place.lookup(), options)) {
    EXPECT_EQ(id.agent, 2U) << id.toString();
  }
  options.nearby_radius_m = 0.0;
  EXPECT_TRUE(nearbyKeyframes(place.map, KeyframeId{2, 8}, place.lookup(), options).empty());
}

TEST_F(BackendWorkerTest, EveryNewKeyframeIsFusedWithTheMapOnTheControlThread) {
  const test::ViScenario s = scenario(20, 0.5, 0.3);
  const auto map = twoAgentsInOneMap(s);
  const std::size_t points_before = map->read()->points().size();
  BackendOptions options;
  options.redundancy.enabled = false;
  BackendWorker worker(options, registry_, nullptr);
  std::vector<std::pair<MapId, KeyframeId>> added;
  for (std::uint32_t k = 8; k <= 19; ++k) added.emplace_back(map->id(), KeyframeId{2, k});
  ASSERT_TRUE(worker.onKeyframesAdded("m", added));
  worker.drain(false);
  const BackendStats stats = worker.stats("m");
  EXPECT_EQ(stats.new_keyframes_fused, 12U);
  EXPECT_GT(stats.new_keyframe_point_merges, 100U);
  EXPECT_GT(stats.new_keyframe_fuse_ms_max, 0.0);
  const auto content = map->read();
  EXPECT_LT(content->points().size(), points_before - 100);
  EXPECT_TRUE(content->checkConsistency().ok());
}

// Agent 2 flies into agent 1's part of a shared map with a drift of its own (2 cm growing to 8 cm and 1 deg of
// yaw): no merge or loop happens, so only the periodic GBA can use the points new-keyframe fusion shared.
class PeriodicGba : public BackendWorkerTest {
 protected:
  double agent2ErrorAfter(int gba_every_keyframes, std::size_t* gba_runs) {
    const test::ViScenario s = scenario(20, 0.5, 0.3);
    const auto map = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 11});
    {
      auto record = mission_->agent(2)->write();
      record->sensors = sensorsOf(s);
      record->agent_maps[0] = AgentRecord::AgentMap{map->id(), SE3d()};
      const auto drift_at = [](int k) {
        const double f = static_cast<double>(k - 7) / 12.0;
        return SE3d(SO3d::exp(Vector3d(0.0, 0.0, 0.0175 * f)), Vector3d(0.08, -0.05, 0.02) * f);
      };
      buildAgentMap(*map->write(), s, AgentPlan{.agent = 2, .first = 8, .last = 19, .E = drift_at}, &*record);
    }
    before_ = maxPositionError(*map->read(), s, 2);
    BackendOptions options;
    options.redundancy.enabled = false;
    options.gba_every_keyframes = gba_every_keyframes;
    BackendWorker worker(options, registry_, nullptr);
    for (std::uint32_t k = 8; k <= 19; ++k) {
      EXPECT_TRUE(worker.onKeyframesAdded("m", {{map->id(), KeyframeId{2, k}}}));
    }
    worker.drain(false);
    *gba_runs = worker.stats("m").gba.size();
    const auto content = map->read();
    EXPECT_TRUE(content->checkConsistency().ok());
    return maxPositionError(*content, s, 2);
  }
  double before_ = 0.0;
};

TEST_F(PeriodicGba, AGbaEveryFewKeyframesTakesOutTheDriftOfAnAgentInASharedMap) {
  std::size_t runs = 0;
  const double after = agent2ErrorAfter(6, &runs);
  ASSERT_GT(before_, 0.05);
  EXPECT_GE(runs, 1U);
  EXPECT_LE(runs, 2U) << "12 keyframes at one per 6: at most two requests";
  EXPECT_LT(after, 0.2 * before_) << "before " << before_;
}

TEST_F(PeriodicGba, OffByDefaultNothingButAMergeOrLoopStartsAGba) {
  EXPECT_EQ(BackendOptions{}.gba_every_keyframes, 0);
  std::size_t runs = 0;
  const double after = agent2ErrorAfter(0, &runs);
  EXPECT_EQ(runs, 0U);
  EXPECT_NEAR(after, before_, 1e-9);
  BackendOptions bad;
  bad.gba_every_keyframes = -1;
  EXPECT_FALSE(bad.validate().ok());
}

TEST_F(BackendWorkerTest, NewKeyframeFusionCanBeTurnedOff) {
  const test::ViScenario s = scenario(20, 0.5, 0.3);
  const auto map = twoAgentsInOneMap(s);
  const std::size_t points_before = map->read()->points().size();
  BackendOptions options;
  options.redundancy.enabled = false;
  options.fuse_new_keyframes = false;
  BackendWorker worker(options, registry_, nullptr);
  ASSERT_TRUE(worker.onKeyframesAdded("m", {{map->id(), KeyframeId{2, 8}}}));
  worker.drain(false);
  EXPECT_EQ(worker.stats("m").new_keyframes_fused, 0U);
  EXPECT_EQ(map->read()->points().size(), points_before);
}

TEST_F(BackendWorkerTest, RedundancyRemovalNeverLeavesAnImuGapOver2sAndKeepsTheMapAccurate) {
  // 0.1 s between keyframes that all see the same box: most are redundant.
  const test::ViScenario s = scenario(60, 0.1, 0.3);
  const auto map = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 59});
  RedundancyOptions options;
  options.checks_per_round = 1000;
  std::mt19937_64 rng(3);
  RedundancyReport report;
  {
    auto content = map->write();
    report = removeRedundantKeyframes(*content, {{1, sensorsOf(s)}}, options, rng);
    EXPECT_TRUE(content->checkConsistency().ok());
  }
  EXPECT_GT(report.removed_keyframes.size(), 20U);
  const auto content = map->read();
  EXPECT_EQ(content->keyframes().size(), 60U - report.removed_keyframes.size());
  // Every IMU link spans at most 2 s and its preintegration covers exactly its keyframes' interval.
  int links = 0;
  for (const auto& [id, kf] : content->keyframes()) {
    if (!kf.imu_from) continue;
    const ServerKeyframe* before = content->keyframe(*kf.imu_from);
    ASSERT_NE(before, nullptr) << id.toString() << " links to a removed keyframe";
    const double gap_s = static_cast<double>(kf.t_ns - before->t_ns) * 1e-9;
    EXPECT_LE(gap_s, 2.0 + 1e-9);
    ASSERT_TRUE(kf.preintegration.has_value());
    EXPECT_NEAR(kf.preintegration->dt(), gap_s, 1e-6);
    ++links;
  }
  EXPECT_EQ(links, static_cast<int>(content->keyframes().size()) - 1) << "one unbroken IMU chain";
  // The newest keep_newest keyframes stay.
  for (int k = 50; k < 60; ++k) EXPECT_NE(content->keyframe(KeyframeId{1, static_cast<std::uint32_t>(k)}), nullptr);
  // GBA on the lean map (joined preintegrations) stays on the truth.
  Result<GbaSnapshot> snapshot = makeGbaSnapshot(*content, {{1, sensorsOf(s)}});
  ASSERT_TRUE(snapshot.ok());
  ASSERT_TRUE(runGlobalBa(*snapshot, GlobalBaOptions{}).ok());
  double worst = 0.0;
  for (const GbaKeyframe& kf : snapshot->keyframes) {
    worst = std::max(worst, (kf.T_w_s.translation() - s.keyframe_states[kf.id.counter].T_w_s.translation()).norm());
  }
  EXPECT_LT(worst, 0.01);
}

TEST_F(BackendWorkerTest, TheMissionsEndChecksEveryKeyframeOnceMoreBeforeTheLastGba) {
  // 0.1 s between keyframes that all see the same box, and no keyframe event during the "mission": only the
  // final pass can find the redundant ones.
  const test::ViScenario s = scenario(60, 0.1, 0.3);
  const auto map = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 59});
  for (const bool final_pass : {false, true}) {
    BackendOptions options;
    options.final_redundancy_pass = final_pass;
    BackendWorker worker(options, registry_, nullptr);
    worker.drain(true);
    const BackendStats stats = worker.stats("m");
    if (!final_pass) {
      EXPECT_EQ(stats.redundant_removed, 0U);
      EXPECT_EQ(map->read()->keyframes().size(), 60U);
      continue;
    }
    EXPECT_GT(stats.final_pass_removed, 20U);
    EXPECT_EQ(stats.redundant_removed, stats.final_pass_removed);
    const auto content = map->read();
    EXPECT_EQ(content->keyframes().size(), 60U - stats.final_pass_removed);
    EXPECT_TRUE(content->checkConsistency().ok());
    ASSERT_FALSE(stats.gba.empty());
    EXPECT_EQ(stats.gba.back().summary.keyframes, static_cast<int>(content->keyframes().size()))
        << "the last GBA ran on the lean map";
    EXPECT_LT(maxPositionError(*content, s, 1), 0.01);
  }
}

}  // namespace
}  // namespace cvislam::server::backend
