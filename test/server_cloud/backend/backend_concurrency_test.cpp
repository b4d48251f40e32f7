// The back-end's worker while changes arrive during a global BA: keyframes streaming in, a loop, a merge, a
// removal; nothing accepted may be lost, and each change must end up optimised with the map it went into. Same
// synthetic maps as backend_test.cpp (backend_test_maps.hpp); real Ceres solves and worker threads, with a gate
// that holds a GBA after its snapshot so that the order of events is deterministic.
#include <algorithm>
#include <functional>
#include <random>
#include <thread>

#include <gtest/gtest.h>

#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/backend/map_fusion.hpp"
#include "test/server_cloud/backend/backend_test_maps.hpp"

namespace cvislam::server::backend {
namespace {

using namespace test_maps;  // NOLINT(google-build-using-namespace): the tests' shared maps and fixture
using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

TEST_F(BackendWorkerTest, GbaWhileKeyframesStreamInLosesNoneAndCarriesTheNewOnesAlong) {
  const test::ViScenario s = scenario(40, 0.25, 0.5);
  // The map holds keyframes 0-29 with a perturbation; 30-39 arrive while GBA runs.
  const auto map = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 29});
  {
    auto content = map->write();
    std::mt19937_64 rng(9);
    std::normal_distribution<double> noise(0.0, 0.03);
    for (std::uint32_t k = 1; k < 30; ++k) {
      ServerKeyframe* kf = content->keyframe(KeyframeId{1, k});
      kf->T_w_s = SE3d(kf->T_w_s.so3(), kf->T_w_s.translation() + Vector3d(noise(rng), noise(rng), noise(rng)));
    }
  }
  BackendOptions options;
  options.redundancy.enabled = false;
  BackendWorker worker(options, registry_, nullptr);
  std::thread gba([&] { worker.drain(true); });
  ASSERT_TRUE(addArrivingKeyframes(*map, s, AgentPlan{.agent = 1, .first = 30, .last = 39}));
  gba.join();
  const BackendStats stats = worker.stats("m");
  ASSERT_FALSE(stats.gba.empty());
  EXPECT_FALSE(stats.gba.back().summary.cancelled);
  const auto content = map->read();
  EXPECT_EQ(content->keyframes().size(), 40U);
  const int optimised = stats.gba.back().summary.keyframes;
  EXPECT_EQ(optimised + stats.gba.back().keyframes_propagated, 40);
  // The keyframes GBA saw are on the truth; those that came later kept their pose relative to the newest
  // optimised one (the same change applied).
  EXPECT_LT(maxPositionError(*content, s, 1), 0.05 + (optimised < 40 ? 0.1 : 0.0));
  EXPECT_TRUE(content->checkConsistency().ok());
}

// While a merge's correction solves (held by the test after its copy): the merged agent's next keyframes arrive
// in the map, and another map's match is queued. The new keyframes are kept and carried along by the
// correction; the second merge follows with its own correction; nothing is lost.
TEST_F(BackendWorkerTest, KeyframesAndAMergeArrivingDuringAMergesCorrectionAreKeptAndCarriedAlong) {
  const test::ViScenario s = scenario(32, 0.5, 0.3);
  const SE3d T_2_truth(SO3d::exp(Vector3d(0.0, 0.0, 0.7)), Vector3d(3.0, -2.0, 0.5));
  const SE3d T_3_truth(SO3d::exp(Vector3d(0.0, 0.0, -1.1)), Vector3d(-1.0, 4.0, 0.0));
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 15});
  const auto map2 = addAgent(s, AgentPlan{.agent = 2, .first = 8, .last = 27, .E = [&](int) { return T_2_truth; }});
  const auto map3 = addAgent(s, AgentPlan{.agent = 3, .first = 16, .last = 31, .E = [&](int) { return T_3_truth; }});

  GbaGate gate(map1->id());
  BackendOptions options;
  options.redundancy.enabled = false;
  options.fuse_new_keyframes = false;
  options.gba_after_change = false;  // the corrections alone
  options.merge_correction_keyframes = 10;
  options.on_merge_correction_solve_start = gate.hook();
  BackendWorker worker(options, registry_, nullptr);
  // Both matches' transforms are a few cm off.
  const SE3d error(SO3d::exp(Vector3d(0.0, 0.0, 0.01)), Vector3d(0.04, -0.03, 0.03));
  recognition::MatchRecord first =
      matchRecord(recognition::QueryKind::kMapMatch, KeyframeId{2, 10}, map2->id(), KeyframeId{1, 10}, map1->id());
  first.match.T_qmap_cmap = error * T_2_truth;
  recognition::MatchRecord second =
      matchRecord(recognition::QueryKind::kMapMatch, KeyframeId{3, 18}, map3->id(), KeyframeId{2, 18}, map1->id());
  second.match.T_qmap_cmap = error.inverse() * T_3_truth;
  ASSERT_TRUE(worker.onMatch("m", first));
  gate.waitUntilHeld();

  // Agent 2's keyframes 28-31 arrive as ingest stores them: in the merged map, where the match's transform puts them.
  const SE3d T_into_from =
      fourDofTransform(first.match.T_qmap_cmap.inverse(), (T_2_truth * s.keyframe_states[10].T_w_s).translation());
  ASSERT_TRUE(addArrivingKeyframes(
      *map1, s, AgentPlan{.agent = 2, .first = 28, .last = 31, .E = [&](int) { return T_into_from * T_2_truth; }}));
  ASSERT_GT(maxPositionError(*map1->read(), s, 2), 0.05);
  ASSERT_TRUE(worker.onMatch("m", second));
  gate.release();
  worker.drain(false);

  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.merges.size(), 2U);
  for (const MergeRecord& merge : stats.merges) EXPECT_GE(merge.match_to_corrected_s, merge.match_to_merged_s);
  EXPECT_EQ(mission_->stack().find(map2->id()), nullptr);
  EXPECT_EQ(mission_->stack().find(map3->id()), nullptr);
  const auto content = map1->read();
  EXPECT_TRUE(content->checkConsistency().ok());
  EXPECT_EQ(content->keyframes().size(), 16U + 24U + 16U);
  EXPECT_LT(maxPositionError(*content, s, 1), 0.005);
  EXPECT_LT(maxPositionError(*content, s, 2), 0.01) << "keyframes 28-31 carried along too";
  EXPECT_LT(maxPositionError(*content, s, 3), 0.01);
}

// What closeALoopWhileGbaRuns returns: the worker's stats and the largest keyframe position error before and after.
struct LoopDuringGba {
  BackendStats stats;
  double before = 0.0;
  double after = 0.0;
};

// Agent 1's map of the 24 keyframes of `s` with a drift of `drift_m` (position, with a yaw of `drift_rad`) from
// keyframe 12 on, the later keyframes making points of their own (as after drift).
std::shared_ptr<ServerMap> driftedMap(Mission& mission, const test::ViScenario& s, double drift_m, double drift_rad) {
  const Vector3d drift_xi = drift_m * Vector3d(0.3, -0.25, 0.05).normalized();
  const auto drift_at = [&](int k) {
    const double f = k < 12 ? 0.0 : static_cast<double>(k - 11) / 12.0;
    return SE3d(SO3d::exp(Vector3d(0.0, 0.0, drift_rad * f)), f * drift_xi);
  };
  std::shared_ptr<ServerMap> map = mission.stack().createMap();
  {
    auto record = mission.agent(1)->write();
    record->sensors = sensorsOf(s);
    record->agent_maps[0] = AgentRecord::AgentMap{map->id(), SE3d()};
    buildAgentMap(
        *map->write(), s,
        AgentPlan{
            .agent = 1, .first = 0, .last = 23, .E = drift_at, .generation = [](int k) { return k >= 12 ? 1 : 0; }},
        &*record);
  }
  return map;
}

// The mission's end, with its GBA of `map` held at its start while `during` runs; then the GBA is let go and the
// worker drained. The worker's stats.
BackendStats whileTheFinalGbaIsHeld(MissionRegistry& registry, MapId map, BackendOptions options,
                                    const std::function<void(BackendWorker&)>& during) {
  GbaGate gate(map);
  options.redundancy.enabled = false;
  options.on_gba_solve_start = gate.hook();
  BackendWorker worker(options, registry, nullptr);
  std::thread mission_end([&] { worker.drain(true); });
  gate.waitUntilHeld();
  during(worker);
  gate.release();
  mission_end.join();
  worker.drain(false);
  return worker.stats("m");
}

// A loop closed while the map's GBA runs, on driftedMap (as in ALoopClosureRemovesAnInjectedDrift).
LoopDuringGba closeALoopWhileGbaRuns(MissionRegistry& registry, double drift_m, double drift_rad) {
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  const std::shared_ptr<Mission> mission = registry.getOrCreate("m");
  std::shared_ptr<ServerMap> map = driftedMap(*mission, s, drift_m, drift_rad);
  LoopDuringGba out;
  out.before = maxPositionError(*map->read(), s, 1);
  out.stats = whileTheFinalGbaIsHeld(registry, map->id(), BackendOptions{}, [&](BackendWorker& worker) {
    EXPECT_TRUE(worker.onMatch("m", exactLoop(map->id(), s, 22, 3)));
    EXPECT_TRUE(eventually([&] { return !worker.stats("m").loops.empty(); }));
  });
  const auto content = map->read();
  EXPECT_TRUE(content->checkConsistency().ok());
  out.after = maxPositionError(*content, s, 1);
  return out;
}

TEST(BackendLoopDuringGba, ASmallLoopLetsTheRunningGbaFinishAndTheGbaAfterItTakesTheLoopIn) {
  MissionRegistry registry;
  // About 3 cm and 0.2 deg at the query keyframe: below the 5 cm / 0.5 deg bound.
  const LoopDuringGba r = closeALoopWhileGbaRuns(registry, 0.035, 0.004);
  ASSERT_EQ(r.stats.loops.size(), 1U);
  EXPECT_LT(r.stats.loops[0].correction_m, BackendOptions{}.loop_cancels_gba_m);
  EXPECT_GT(r.stats.loops[0].correction_m, 0.01);
  EXPECT_FALSE(r.stats.loops[0].cancelled_gba);
  EXPECT_EQ(r.stats.gba_cancelled, 0U);
  ASSERT_GE(r.stats.gba.size(), 2U) << "the running GBA, then the loop's";
  EXPECT_FALSE(r.stats.gba[0].summary.cancelled) << "the running GBA was applied";
  EXPECT_FALSE(r.stats.gba.back().summary.cancelled);
  EXPECT_GE(r.stats.loops[0].match_to_optimised_s, 0.0);
  ASSERT_GT(r.before, 0.025);
  EXPECT_LT(r.after, 0.01) << "before " << r.before;
}

// Two small loops arrive 0.3 s apart while the map's GBA runs: their requests join into one GBA, and each loop's
// time to refined counts from its own match, so the second's is the shorter by about the 0.3 s.
TEST(BackendLoopDuringGba, TwoLoopsWhoseGbaRequestsJoinAreEachTimedFromTheirOwnMatch) {
  MissionRegistry registry;
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  const std::shared_ptr<Mission> mission = registry.getOrCreate("m");
  std::shared_ptr<ServerMap> map = driftedMap(*mission, s, 0.035, 0.004);
  BackendOptions options;
  options.loop_cooldown_keyframes = 0;  // both loops are the same agent's, one keyframe apart
  const BackendStats stats = whileTheFinalGbaIsHeld(registry, map->id(), options, [&](BackendWorker& worker) {
    EXPECT_TRUE(worker.onMatch("m", exactLoop(map->id(), s, 22, 3)));
    EXPECT_TRUE(eventually([&] { return worker.stats("m").loops.size() == 1; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    EXPECT_TRUE(worker.onMatch("m", exactLoop(map->id(), s, 23, 2)));
    EXPECT_TRUE(eventually([&] { return worker.stats("m").loops.size() == 2; }));
  });

  ASSERT_EQ(stats.loops.size(), 2U);
  EXPECT_FALSE(stats.loops[0].cancelled_gba);
  EXPECT_FALSE(stats.loops[1].cancelled_gba);
  ASSERT_EQ(stats.gba.size(), 2U) << "the running GBA, then one for both loops";
  const double first = stats.loops[0].match_to_optimised_s;
  const double second = stats.loops[1].match_to_optimised_s;
  ASSERT_GT(second, 0.0);
  EXPECT_GT(first - second, 0.25) << "first " << first << " s, second " << second << " s";
}

TEST(BackendLoopDuringGba, ABigLoopCutsTheRunningGbaShortAndTheNextOneRemovesTheDrift) {
  MissionRegistry registry;
  const LoopDuringGba r = closeALoopWhileGbaRuns(registry, 0.4, 0.05);
  ASSERT_EQ(r.stats.loops.size(), 1U);
  EXPECT_GT(r.stats.loops[0].correction_m, BackendOptions{}.loop_cancels_gba_m);
  EXPECT_TRUE(r.stats.loops[0].cancelled_gba);
  EXPECT_EQ(r.stats.gba_cancelled, 1U);
  ASSERT_GE(r.stats.gba.size(), 2U);
  EXPECT_TRUE(r.stats.gba[0].summary.cancelled) << "cut short, not applied";
  EXPECT_FALSE(r.stats.gba.back().summary.cancelled);
  ASSERT_GT(r.before, 0.25);
  EXPECT_LT(r.after, 0.02) << "before " << r.before;
}

// A loop closed with a measurement 3 cm off and its GBA applied (the map is then at the truth), then a second loop
// measured exactly: its pose graph holds the first loop's edge at the relative pose the GBA left, so the map stays
// at the truth until the GBA after it. Held at the old measurement, ten times the weight of the path's own edges,
// the edge would bend the path by about the 3 cm.
TEST(BackendLoops, AfterAGbaALoopEdgeHoldsTheMapsRelativePoseNotTheOldMeasurement) {
  MissionRegistry registry;
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  const std::shared_ptr<Mission> mission = registry.getOrCreate("m");
  std::shared_ptr<ServerMap> map = driftedMap(*mission, s, 0.2, 0.02);
  // Holds the GBA after the second loop, so that the map is seen as that loop's pose graph left it.
  GbaGate gate(map->id());
  std::atomic<bool> armed{false};
  BackendOptions options;
  options.redundancy.enabled = false;
  options.loop_cooldown_keyframes = 0;  // both loops are the same agent's, one keyframe apart
  options.on_gba_solve_start = [&, hold = gate.hook()](MapId m) {
    if (armed) hold(m);
  };
  BackendWorker worker(options, registry, nullptr);
  recognition::MatchRecord loop1 =
      matchRecord(recognition::QueryKind::kLoop, KeyframeId{1, 22}, map->id(), KeyframeId{1, 3}, map->id());
  loop1.match.T_cmap_cq = SE3d(SO3d(), Vector3d(0.0, 0.03, 0.0)) * s.keyframe_states[22].T_w_s * s.T_s_c;
  EXPECT_TRUE(worker.onMatch("m", loop1));
  worker.drain(false);
  ASSERT_EQ(worker.stats("m").loops.size(), 1U);
  ASSERT_FALSE(worker.stats("m").gba.empty());
  const double after_first_gba = maxPositionError(*map->read(), s, 1);
  armed = true;
  EXPECT_TRUE(worker.onMatch("m", exactLoop(map->id(), s, 23, 2)));
  gate.waitUntilHeld();
  const double after_second_graph = maxPositionError(*map->read(), s, 1);
  gate.release();
  worker.drain(false);
  ASSERT_EQ(worker.stats("m").loops.size(), 2U);
  EXPECT_LT(after_first_gba, 0.005);
  EXPECT_LT(after_second_graph, 0.008) << "the first loop's 3 cm measurement bent the map again";
}

TEST_F(BackendWorkerTest, ARemovalAndAMergeArrivingWhileGbaRunsBothApply) {
  // 0.1 s between keyframes: many of agent 1's are redundant. Agent 2 flies the second half, in its own frame.
  const test::ViScenario s = scenario(40, 0.1, 0.3);
  const SE3d T_2_truth(SO3d::exp(Vector3d(0.0, 0.0, -0.5)), Vector3d(-1.0, 2.0, 0.3));
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 29});
  const auto map2 = addAgent(s, AgentPlan{.agent = 2, .first = 20, .last = 39, .E = [&](int) { return T_2_truth; }});

  GbaGate gate(map1->id());
  BackendOptions options;
  options.redundancy_every_keyframes = 1;
  options.redundancy.checks_per_round = 1000;
  options.final_redundancy_pass = false;   // the removal must arrive while the GBA runs, not before it
  options.merge_correction_keyframes = 0;  // without a correction a merge lets the running GBA finish
  options.on_gba_solve_start = gate.hook();
  BackendWorker worker(options, registry_, nullptr);
  std::thread mission_end([&] { worker.drain(true); });
  gate.waitUntilHeld();  // (a failure here leaves the gate open: the GBA runs on)
  // While map 1's GBA runs: a keyframe arrives (a redundancy round), then agent 2's map matches.
  EXPECT_TRUE(worker.onKeyframesAdded("m", {{map1->id(), KeyframeId{1, 29}}}));
  EXPECT_TRUE(eventually([&] { return worker.stats("m").redundancy_checked > 0; }));
  recognition::MatchRecord record =
      matchRecord(recognition::QueryKind::kMapMatch, KeyframeId{2, 25}, map2->id(), KeyframeId{1, 24}, map1->id());
  record.match.T_qmap_cmap = T_2_truth;
  EXPECT_TRUE(worker.onMatch("m", record));
  EXPECT_TRUE(eventually([&] { return !worker.stats("m").merges.empty(); }));
  gate.release();
  mission_end.join();
  worker.drain(false);

  const BackendStats stats = worker.stats("m");
  const std::uint64_t removed = stats.redundant_removed;
  EXPECT_GT(removed, 5U);
  {
    // Every removal is queued for agent 1's downlink, once.
    const auto agent1 = mission_->findAgent(1)->read();
    EXPECT_EQ(agent1->removals_to_send.size(), removed);
    EXPECT_EQ(agent1->server_removed_keyframes.size(), removed);
  }
  // Map 1's GBA ran on through the merge into map 1 and applied; the merged map's own GBA came after it.
  EXPECT_EQ(stats.gba_cancelled, 0U);
  ASSERT_GE(stats.gba.size(), 2U);
  EXPECT_FALSE(stats.gba.front().summary.cancelled);
  EXPECT_EQ(stats.gba.front().summary.keyframes, 30) << "map 1 when its GBA took its snapshot";
  EXPECT_FALSE(stats.gba.back().summary.cancelled);
  EXPECT_GE(stats.merges[0].match_to_optimised_s, 0.0);
  EXPECT_EQ(mission_->stack().find(map2->id()), nullptr);
  const auto merged = map1->read();
  EXPECT_TRUE(merged->checkConsistency().ok());
  EXPECT_EQ(merged->keyframes().size(), 30U - removed + 20U) << "the removal held through the merge and the GBAs";
  EXPECT_EQ(stats.gba.back().summary.keyframes, static_cast<int>(merged->keyframes().size()));
  EXPECT_LT(maxPositionError(*merged, s, 1), 0.02);
  EXPECT_LT(maxPositionError(*merged, s, 2), 0.02);
  EXPECT_EQ(mission_->findAgent(2)->read()->agent_maps.at(0).map, map1->id());
}

// A loop in map 2 waits for map 2's GBA, and map 2 is merged into map 1 before that GBA can run: the loop's time to
// optimised must come from map 1's GBA. `hold` says whose GBA is held while the loop and the merge arrive. With
// `hold_the_correction`, the merge's correction is held too, and the held GBA let go meanwhile: map 2's GBA then
// runs while the merge is still being corrected. With `release_when_joined`, the held GBA is let go the moment the
// merge has joined the maps (before its fusion and before the map leaves the stack), and the GBA thread finishes
// what it may before the merge goes on: the cut-short GBA of map 2 goes back in the queue and finds map 2 empty.
void loopWaitingForAMapThatIsMergedAway(MissionRegistry& registry, bool hold_the_merged_away_map,
                                        bool hold_the_correction = false, bool release_when_joined = false) {
  const std::shared_ptr<Mission> mission = registry.getOrCreate("m");
  const auto addAgent = [&](const test::ViScenario& s, const AgentPlan& plan) {
    std::shared_ptr<ServerMap> map = mission->stack().createMap();
    auto record = mission->agent(plan.agent)->write();
    record->sensors = sensorsOf(s);
    record->agent_maps[0] = AgentRecord::AgentMap{map->id(), SE3d()};
    buildAgentMap(*map->write(), s, plan, &*record);
    return map;
  };
  const test::ViScenario s = scenario(24, 0.5, 0.3);
  // Agent 2 drifts from keyframe 12 on (as in ALoopClosureRemovesAnInjectedDrift), in a frame of its own.
  const SE3d T_2_truth(SO3d::exp(Vector3d(0.0, 0.0, 0.6)), Vector3d(2.0, 1.0, -0.2));
  const auto drift_at = [](int k) {
    const double f = k < 12 ? 0.0 : static_cast<double>(k - 11) / 12.0;
    return SE3d(SO3d::exp(Vector3d(0.0, 0.0, 0.05 * f)), f * Vector3d(0.3, -0.25, 0.05));
  };
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 11});
  const auto map2 = addAgent(s, AgentPlan{.agent = 2,
                                          .first = 0,
                                          .last = 23,
                                          .E = [&](int k) { return T_2_truth * drift_at(k); },
                                          .generation = [](int k) { return k >= 12 ? 1 : 0; }});
  GbaGate gate(hold_the_merged_away_map ? map2->id() : map1->id());
  GbaGate correction_gate(map1->id());
  BackendOptions options;
  options.redundancy.enabled = false;
  options.on_gba_solve_start = gate.hook();
  if (hold_the_correction) {
    options.merge_correction_keyframes = 10;
    options.on_merge_correction_solve_start = correction_gate.hook();
  }
  BackendWorker* running_worker = nullptr;
  if (release_when_joined) {
    options.on_merge_joined = [&](MapId) {
      gate.release();
      EXPECT_TRUE(eventually([&] {
        const BackendWorker::GbaWork work = running_worker->gbaWork("m");
        return !work.running && std::count(work.queued.begin(), work.queued.end(), map2->id()) == 0;
      })) << "the GBA thread did not finish with map 2";
    };
  }
  BackendWorker worker(options, registry, nullptr);
  running_worker = &worker;
  std::thread mission_end([&] { worker.drain(true); });
  gate.waitUntilHeld();
  // While map 1's GBA runs: a loop in map 2 (its GBA is queued behind), then map 2 merges into map 1.
  recognition::MatchRecord loop =
      matchRecord(recognition::QueryKind::kLoop, KeyframeId{2, 22}, map2->id(), KeyframeId{2, 3}, map2->id());
  loop.match.T_cmap_cq = T_2_truth * s.keyframe_states[22].T_w_s * s.T_s_c;
  EXPECT_TRUE(worker.onMatch("m", loop));
  EXPECT_TRUE(eventually([&] { return !worker.stats("m").loops.empty(); }));
  recognition::MatchRecord merge =
      matchRecord(recognition::QueryKind::kMapMatch, KeyframeId{2, 5}, map2->id(), KeyframeId{1, 5}, map1->id());
  merge.match.T_qmap_cmap = T_2_truth;
  EXPECT_TRUE(worker.onMatch("m", merge));
  if (hold_the_correction) {
    correction_gate.waitUntilHeld();
    gate.release();
    // The GBA thread has done all it may while map 1 is being corrected: map 2's GBA went to map 1, which waits.
    EXPECT_TRUE(eventually([&] {
      const BackendWorker::GbaWork work = worker.gbaWork("m");
      return !work.running && work.queued == std::vector<MapId>{map1->id()};
    }));
    EXPECT_TRUE(worker.stats("m").merges.empty()) << "recorded once corrected";
    correction_gate.release();
  } else {
    EXPECT_TRUE(eventually([&] { return !worker.stats("m").merges.empty(); }));
    gate.release();
  }
  mission_end.join();
  worker.drain(false);

  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.loops.size(), 1U);
  ASSERT_EQ(stats.merges.size(), 1U);
  if (hold_the_correction) {
    // Map 1's GBA, running when the merge came, was cut short: the correction placed map 2 against map 1's
    // keyframes as they were, and that GBA would have moved them apart; the merge's GBA of both follows.
    ASSERT_FALSE(stats.gba.empty());
    EXPECT_EQ(stats.gba[0].map, map1->id());
    EXPECT_TRUE(stats.gba[0].summary.cancelled);
    EXPECT_FALSE(stats.gba.back().summary.cancelled);
  }
  EXPECT_GE(stats.loops[0].match_to_optimised_s, 0.0) << "the loop's waiter went with its map";
  EXPECT_GE(stats.merges[0].match_to_optimised_s, 0.0);
  EXPECT_EQ(mission->stack().find(map2->id()), nullptr);
  const auto merged = map1->read();
  EXPECT_TRUE(merged->checkConsistency().ok());
  EXPECT_LT(maxPositionError(*merged, s, 2), 0.03);
}

TEST(BackendMergeDuringGba, ALoopWhoseMapsGbaRunsWhileTheMergeIsCorrectedIsOptimisedWithTheMergedMap) {
  MissionRegistry registry;
  loopWaitingForAMapThatIsMergedAway(registry, false, true);
}

TEST(BackendMergeDuringGba, ALoopWaitingBehindAnotherMapsGbaIsOptimisedWithTheMapItsMapWentInto) {
  MissionRegistry registry;
  loopWaitingForAMapThatIsMergedAway(registry, false);
}

TEST(BackendMergeDuringGba, ALoopWaitingWhileItsOwnMapsGbaRunsIsOptimisedWithTheMapItsMapWentInto) {
  MissionRegistry registry;
  loopWaitingForAMapThatIsMergedAway(registry, true);
}

TEST(BackendMergeDuringGba, ALoopWhoseCutShortGbaRunsAgainWhileTheMergeFusesIsOptimisedWithTheMapItsMapWentInto) {
  MissionRegistry registry;
  loopWaitingForAMapThatIsMergedAway(registry, true, false, true);
}

}  // namespace
}  // namespace cvislam::server::backend
