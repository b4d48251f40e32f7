// Map merges in the back-end's worker (CVI-SLAM IV-E): a map match joins the query's map to the candidate's, fuses
// their points, and the GBA after it refines the result; with a merge correction the match's error goes at once,
// and on a large map the GBA frees only the smaller map's part. Same synthetic maps as backend_test.cpp
// (backend_test_maps.hpp); real Ceres solves and worker threads.
#include <cmath>
#include <cstdint>
#include <map>
#include <memory>
#include <vector>

#include <gtest/gtest.h>

#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/backend/map_fusion.hpp"
#include "server_cloud/backend/merge_correction.hpp"
#include "test/server_cloud/backend/backend_test_maps.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::server::backend {
namespace {

using namespace test_maps;  // NOLINT(google-build-using-namespace): the tests' shared maps and fixture
using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

// Agent 2's map frame against the truth (agent 1's map frame): turned by 40 deg about gravity and moved.
const SE3d kT_2_truth(SO3d::exp(Vector3d(0.0, 0.0, 0.7)), Vector3d(3.0, -2.0, 0.5));
// A match's transform off as place recognition's are on the hall8 mission (5.4 cm p50, 7.6 cm max): 6 cm and
// 0.6 deg of yaw.
const SE3d kRecognitionError(SO3d::exp(Vector3d(0.0, 0.0, 0.6 * M_PI / 180.0)), Vector3d(0.04, -0.03, 0.03));

class MergeTest : public BackendWorkerTest {
 protected:
  // Agent 2's map of scenario keyframes [first, last], in its own frame (kT_2_truth).
  std::shared_ptr<ServerMap> addAgent2(const test::ViScenario& s, int first, int last) {
    return addAgent(s, AgentPlan{.agent = 2, .first = first, .last = last, .E = [](int) { return kT_2_truth; }});
  }
  // No redundancy removal, no fusion of new keyframes and no merge correction: the merge alone changes the maps.
  static BackendOptions mergeOnly() {
    BackendOptions options;
    options.redundancy.enabled = false;
    options.fuse_new_keyframes = false;
    options.merge_correction_keyframes = 0;
    return options;
  }
  // Agent 2's keyframe `query` seen from agent 1's `candidate`, with the transform between the maps off by `error`.
  static recognition::MatchRecord mapMatch(const ServerMap& map2, std::uint32_t query, const ServerMap& map1,
                                           std::uint32_t candidate, const SE3d& error = SE3d()) {
    recognition::MatchRecord record = matchRecord(recognition::QueryKind::kMapMatch, KeyframeId{2, query}, map2.id(),
                                                  KeyframeId{1, candidate}, map1.id());
    record.match.T_qmap_cmap = error * kT_2_truth;
    return record;
  }
};

TEST_F(MergeTest, AMapMatchMergesTheQueryMapWithTheKnownTransformFusesItsPointsAndOptimises) {
  const test::ViScenario s = scenario(16, 0.5, 0.3);
  // Agent 1's map is the truth frame; agent 2's map frame is turned by 40 deg about gravity and moved.
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 7});
  const auto map2 = addAgent2(s, 8, 15);
  const std::size_t points_before = map1->read()->points().size() + map2->read()->points().size();

  BackendOptions options;
  options.redundancy.enabled = false;
  options.merge_correction_keyframes = 10;
  BackendWorker worker(options, registry_, nullptr);
  // What place recognition would report: agent 2's keyframe 9 seen from agent 1's keyframe 6, with the
  // match's rotation off by 0.3 deg of roll (the merge keeps 4 DoF and drops it).
  const recognition::MatchRecord record =
      mapMatch(*map2, 9, *map1, 6, SE3d(SO3d::exp(Vector3d(0.005, 0.0, 0.0)), Vector3d::Zero()));
  ASSERT_TRUE(worker.onMatch("m", record));
  worker.drain(false);

  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.merges.size(), 1U);
  EXPECT_EQ(mission_->stack().find(map2->id()), nullptr) << "the query's map went into the candidate's";
  const auto merged = map1->read();
  EXPECT_EQ(merged->agents(), (std::set<AgentId>{1, 2}));
  EXPECT_TRUE(merged->checkConsistency().ok());
  // The transform is recovered: agent 2's keyframes sit on the truth (4-DoF from a roll-perturbed match).
  EXPECT_LT(maxPositionError(*merged, s, 2), 0.02);
  EXPECT_LT(stats.merges[0].T_into_from.so3().log().head<2>().norm(), 1e-9) << "no roll or pitch";
  // Duplicated points became one.
  EXPECT_GT(stats.merges[0].fusion.projection_fused, 50);
  EXPECT_LT(merged->points().size(), points_before - 50);
  // The GBA after the merge ran and reported the time from the match to the optimised map.
  ASSERT_FALSE(stats.gba.empty());
  EXPECT_FALSE(stats.gba.back().summary.cancelled);
  EXPECT_GE(stats.merges[0].match_to_optimised_s, stats.merges[0].match_to_merged_s);
  // The records follow: agent 2's map is map 1, and its world frame maps into it by the inverse transform.
  const auto agent2 = mission_->findAgent(2)->read();
  EXPECT_EQ(agent2->agent_maps.at(0).map, map1->id());
  const SE3d T_m_w = agent2->agent_maps.at(0).T_m_w;
  EXPECT_LT((T_m_w * kT_2_truth).translation().norm(), 0.05);
  EXPECT_EQ(agent2->keyframes.at(9).map, map1->id());
  // Watchers of the mission saw the merge, the correction right after it (it moves agent 2's 8 keyframes, the
  // query's map, as one), then the GBA's.
  const auto events = mission_->events().read(1, 100).events;
  ASSERT_GE(events.size(), 3U);
  EXPECT_EQ(events[0].kind, MissionEvent::Kind::kMapsMerged);
  EXPECT_EQ(events[0].map, map1->id());
  EXPECT_EQ(events[0].from_map, map2->id());
  EXPECT_EQ(events[1].kind, MissionEvent::Kind::kMapCorrected);
  EXPECT_EQ(events[1].cause, "merge correction");
  EXPECT_EQ(events[1].keyframes, 8U);
  EXPECT_EQ(events[2].kind, MissionEvent::Kind::kMapCorrected);
  EXPECT_EQ(events[2].cause, "global BA");
  EXPECT_EQ(events[2].keyframes, 16U);
  EXPECT_GE(stats.merges[0].match_to_corrected_s, stats.merges[0].match_to_merged_s);
  EXPECT_LE(stats.merges[0].match_to_corrected_s, stats.merges[0].match_to_optimised_s);
}

// Agent `agent`'s keyframes in `map`, with their state's standing.
struct HeldPose {
  SE3d T_w_s;
  bool refined = false;
  bool provisional = false;
};
std::map<std::uint32_t, HeldPose> posesOf(const MapContent& map, AgentId agent) {
  std::map<std::uint32_t, HeldPose> out;
  for (const auto& [id, kf] : map.keyframes()) {
    if (id.agent == agent) out.emplace(id.counter, HeldPose{kf.T_w_s, kf.refined, kf.provisional});
  }
  return out;
}

// The match's transform comes from one keyframe and is a few cm off. The correction right after the merge (a BA of
// the query's window over the fused points, and the 4-DoF change that fits it, applied to the query's whole map)
// takes that out before any GBA has run: the test holds the GBA after its snapshot and looks at the map meanwhile.
// The query's map moves as one: every relative pose within it, each keyframe's standing and the agent's frame
// against its own keyframes stay as they were.
TEST_F(MergeTest, AMergesCorrectionTakesOutTheMatchsErrorBeforeAnyGbaRunsAndMovesTheQueryMapRigidly) {
  const test::ViScenario s = scenario(32, 0.5, 0.3);
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 15});
  const auto map2 = addAgent2(s, 8, 31);
  {
    // Some of agent 2's keyframes refined by an earlier GBA, the rest not: the correction keeps both as they are.
    auto content = map2->write();
    std::vector<KeyframeId> ids;
    for (const auto& [id, kf] : content->keyframes()) ids.push_back(id);
    for (const KeyframeId& id : ids) content->keyframe(id)->refined = id.counter % 2 == 0;
  }
  const std::map<std::uint32_t, HeldPose> before = posesOf(*map2->read(), 2);
  const SE3d T_m_w_before = mission_->findAgent(2)->read()->agent_maps.at(0).T_m_w;

  BackendOptions options = mergeOnly();
  options.merge_correction_keyframes = 10;
  GbaGate gate(map1->id());
  options.on_gba_solve_start = gate.hook();
  BackendWorker worker(options, registry_, nullptr);
  const recognition::MatchRecord record = mapMatch(*map2, 10, *map1, 10, kRecognitionError);
  ASSERT_TRUE(worker.onMatch("m", record));
  gate.waitUntilHeld();

  // Without the correction, agent 2's keyframes would sit where the match put them: 5 cm and more off.
  double rigid_error = 0.0;
  const SE3d T_into_from =
      fourDofTransform(record.match.T_qmap_cmap.inverse(), (kT_2_truth * s.keyframe_states[10].T_w_s).translation());
  for (int k = 8; k <= 31; ++k) {
    const Vector3d p = (T_into_from * kT_2_truth * s.keyframe_states[static_cast<std::size_t>(k)].T_w_s).translation();
    rigid_error =
        std::max(rigid_error, (p - s.keyframe_states[static_cast<std::size_t>(k)].T_w_s.translation()).norm());
  }
  ASSERT_GT(rigid_error, 0.05);
  const BackendStats during = worker.stats("m");
  ASSERT_EQ(during.merges.size(), 1U);
  const MergeRecord& merge = during.merges[0];
  {
    const auto merged = map1->read();
    EXPECT_TRUE(merged->checkConsistency().ok());
    EXPECT_LT(maxPositionError(*merged, s, 2), 0.01) << "the transform alone: " << rigid_error;
    EXPECT_LT(maxPositionError(*merged, s, 1), 0.005) << "agent 1's map stays where it is";
    // Rigid: the merge's transform and the correction's change move every keyframe of agent 2 alike.
    const SE3d change = merge.correction_change * T_into_from;
    const std::map<std::uint32_t, HeldPose> after = posesOf(*merged, 2);
    ASSERT_EQ(after.size(), before.size());
    for (const auto& [counter, held] : after) {
      const HeldPose& was = before.at(counter);
      const SE3d residual = held.T_w_s * (change * was.T_w_s).inverse();
      EXPECT_LT(residual.translation().norm(), 1e-9) << "keyframe " << counter;
      EXPECT_LT(residual.so3().log().norm(), 1e-9) << "keyframe " << counter;
      EXPECT_EQ(held.refined, was.refined) << "keyframe " << counter;
      EXPECT_EQ(held.provisional, was.provisional) << "keyframe " << counter;
    }
    // 4 DoF: gravity stays where the agents' IMUs put it.
    EXPECT_LT(merge.correction_change.so3().log().head<2>().norm(), 1e-12);
    // The agent's frame moved with its map, so its own keyframes sent down match its local map as before.
    const SE3d T_m_w = mission_->findAgent(2)->read()->agent_maps.at(0).T_m_w;
    const SE3d frame_residual = T_m_w * (change * T_m_w_before).inverse();
    EXPECT_LT(frame_residual.translation().norm(), 1e-9);
    EXPECT_LT(frame_residual.so3().log().norm(), 1e-9);
  }
  EXPECT_TRUE(during.gba.empty()) << "no GBA has finished";
  EXPECT_GE(merge.match_to_corrected_s, merge.match_to_merged_s);
  EXPECT_GT(merge.correction_m, 0.03);
  // The BA covered the query's window and its held border, not the whole map; the change all of agent 2's map.
  EXPECT_LT(merge.correction_ba.keyframes, 40);
  EXPECT_EQ(merge.correction_keyframes, 24);
  const auto events = mission_->events().read(1, 100).events;
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].kind, MissionEvent::Kind::kMapsMerged);
  EXPECT_EQ(events[1].cause, "merge correction");
  EXPECT_EQ(events[1].keyframes, 24U);

  gate.release();
  worker.drain(false);
  const BackendStats after = worker.stats("m");
  ASSERT_EQ(after.gba.size(), 1U);
  EXPECT_GE(after.merges[0].match_to_optimised_s, after.merges[0].match_to_corrected_s);
  EXPECT_LT(maxPositionError(*map1->read(), s, 2), 0.01);
}

// The change is fitted to the window's moves: a known 4-DoF change comes back from moves that also carry noise and
// roll and pitch, which it drops.
TEST(FitFourDofChange, RecoversAKnownChangeFromNoisyMovesAndDropsRollAndPitch) {
  const SE3d truth(SO3d::exp(Vector3d(0.0, 0.0, 0.02)), Vector3d(0.05, -0.03, 0.02));
  std::vector<SE3d> before;
  std::vector<SE3d> after;
  for (int i = 0; i < 10; ++i) {
    const SE3d pose(SO3d::exp(Vector3d(0.1, -0.05, 0.3 * i)), Vector3d(2.0 + 0.4 * i, 1.0 - 0.2 * i, 0.3 * (i % 3)));
    // Each move off the truth by up to 2 mm and 0.06 deg, alternating, including about x and y.
    const double sign = i % 2 == 0 ? 1.0 : -1.0;
    const SE3d noise(SO3d::exp(sign * Vector3d(0.001, 0.001, 0.001)), sign * Vector3d(0.002, -0.001, 0.002));
    before.push_back(pose);
    after.push_back(noise * truth * pose);
  }
  const SE3d fitted = fitFourDofChange(before, after);
  EXPECT_LT(fitted.so3().log().head<2>().norm(), 1e-12) << "yaw only";
  EXPECT_NEAR(fitted.so3().log().z(), 0.02, 2e-4);
  for (const SE3d& pose : before) {
    EXPECT_LT(((fitted * pose).translation() - (truth * pose).translation()).norm(), 3e-3);
  }
}

// On a large map (gba_window_above_keyframes) the GBA after a merge frees what the merge changed: the keyframes
// of the smaller map's agents, those they add meanwhile included. Agent 1's map (28 keyframes) takes agent 2's
// (20) through a match off as recognition's are; while the GBA solves, agent 2 adds four keyframes where the merge put
// its frame.
TEST_F(MergeTest, AMergesGbaOnALargeMapFreesTheSmallerMapsAgentsAndHoldsTheRest) {
  const test::ViScenario s = scenario(44, 0.5, 0.3);
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 27});
  const auto map2 = addAgent2(s, 20, 39);
  std::map<std::uint32_t, SE3d> agent1_before;
  for (const auto& [id, kf] : map1->read()->keyframes()) agent1_before.emplace(id.counter, kf.T_w_s);

  BackendOptions options = mergeOnly();
  options.gba_window_above_keyframes = 40;
  GbaGate gate(map1->id());
  options.on_gba_solve_start = gate.hook();
  BackendWorker worker(options, registry_, nullptr);
  const recognition::MatchRecord record = mapMatch(*map2, 24, *map1, 24, kRecognitionError);
  ASSERT_TRUE(worker.onMatch("m", record));
  gate.waitUntilHeld();
  const SE3d T_into_from = worker.stats("m").merges.at(0).T_into_from;
  ASSERT_TRUE(addArrivingKeyframes(
      *map1, s, AgentPlan{.agent = 2, .first = 40, .last = 43, .E = [&](int) { return T_into_from * kT_2_truth; }}));
  ASSERT_GT(maxPositionError(*map1->read(), s, 2), 0.04) << "the match's error";
  gate.release();
  worker.drain(false);

  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.gba.size(), 1U);
  const GbaRecord& gba = stats.gba[0];
  EXPECT_TRUE(gba.windowed);
  EXPECT_FALSE(gba.summary.cancelled);
  // Free: agent 2's 20 keyframes; held: agent 1's that see their points.
  EXPECT_EQ(gba.summary.keyframes - gba.held_keyframes, 20);
  EXPECT_GT(gba.held_keyframes, 0);
  EXPECT_EQ(gba.keyframes_propagated, 4);
  EXPECT_GE(stats.merges[0].match_to_optimised_s, stats.merges[0].match_to_merged_s);
  const auto merged = map1->read();
  EXPECT_TRUE(merged->checkConsistency().ok());
  // Agent 1's keyframes did not move at all. Agent 2's, the four that came during the solve included, sit on the
  // truth: the solve took the match's error out of its frame.
  for (const auto& [counter, T_w_s] : agent1_before) {
    const ServerKeyframe* kf = merged->keyframe(KeyframeId{1, counter});
    ASSERT_NE(kf, nullptr);
    EXPECT_EQ(kf->T_w_s.matrix(), T_w_s.matrix()) << "keyframe 1/" << counter;
  }
  for (const auto& [id, kf] : merged->keyframes()) {
    if (id.agent == 2 && id.counter < 40) {
      EXPECT_TRUE(kf.refined) << "2/" << id.counter;
    }
  }
  EXPECT_LT(maxPositionError(*merged, s, 2), 0.01);
  EXPECT_LT(maxPositionError(*merged, s, 1), 0.01);
}

// Below the size, and at the mission's end, a GBA frees the whole map.
TEST_F(MergeTest, ASmallMapsMergeAndTheFinalGbaFreeTheWholeMap) {
  const test::ViScenario s = scenario(40, 0.5, 0.3);
  const auto map1 = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 27});
  const auto map2 = addAgent2(s, 20, 39);
  BackendOptions options = mergeOnly();
  options.gba_window_above_keyframes = 48;  // the merged map's size
  BackendWorker worker(options, registry_, nullptr);
  const recognition::MatchRecord record = mapMatch(*map2, 24, *map1, 24);
  ASSERT_TRUE(worker.onMatch("m", record));
  worker.drain(true);
  const BackendStats stats = worker.stats("m");
  ASSERT_EQ(stats.gba.size(), 2U);
  for (const GbaRecord& gba : stats.gba) {
    EXPECT_FALSE(gba.windowed);
    EXPECT_EQ(gba.held_keyframes, 0);
    EXPECT_EQ(gba.summary.keyframes, 48);
  }
  EXPECT_TRUE(stats.gba[1].final);
}

}  // namespace
}  // namespace cvislam::server::backend
