// The covisible map of the downlink (server_cloud/ingest/covisible_downlink.hpp) on a hand-built server map with
// exact geometry: agent 1 flies out along x and back, so its newest keyframes see what its first ones saw; agent
// 2 flies over the same start. Every keypoint is the exact projection of its point.
#include "server_cloud/ingest/covisible_downlink.hpp"

#include <algorithm>
#include <cmath>
#include <random>
#include <set>

#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.pb.h"

namespace cvislam::server {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

// The two agents' cameras differ, so that using the wrong agent's intrinsics shows.
CovisibleCamera cameraOf(AgentId agent) {
  if (agent == 1) return CovisibleCamera{400.0, 410.0, 320.0, 240.0, {}};
  return CovisibleCamera{350.0, 360.0, 300.0, 230.0, {}};
}

// The camera looks along the map's +z; the IMU frame is turned against it, so that T_s_c matters.
SE3d cameraExtrinsics(AgentId agent) {
  return SE3d(SO3d::exp(Vector3d(0.0, 0.0, agent == 1 ? 0.3 : -0.2)), Vector3d(0.02 * agent, -0.01, 0.03));
}

struct Scene {
  MapContent map{0};
  CovisibleCameras cameras;
  std::vector<KeyframeId> agent1;  // by counter

  Scene() {
    for (AgentId agent : {AgentId{1}, AgentId{2}}) {
      cameras[agent] = cameraOf(agent);
      cameras[agent].T_s_c = cameraExtrinsics(agent);
    }
    // Points on a wall 5 m ahead, from x = -2 to 8 m.
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> y(-1.5, 1.5);
    for (std::uint32_t i = 0; i < 400; ++i) wall.push_back(Vector3d(-2.0 + 0.025 * i, y(rng), 5.0));
    // Agent 1: 30 keyframes out (x = 0 .. 2.9 m), 30 back (x = 2.9 .. 0).
    for (std::uint32_t c = 0; c < 60; ++c) {
      const double x = c < 30 ? 0.1 * c : 0.1 * (59 - c);
      addKeyframe(KeyframeId{1, c}, Vector3d(x, 0.0, 0.0));
      agent1.push_back(KeyframeId{1, c});
    }
    // Agent 2: over the start, 0.3 m to the side; a GBA has refined its keyframes.
    for (std::uint32_t c = 0; c < 10; ++c) {
      addKeyframe(KeyframeId{2, c}, Vector3d(0.05 * c, 0.3, 0.0));
      map.keyframe(KeyframeId{2, c})->refined = true;
    }
  }

  // A keyframe at camera position p_c (looking along +z), observing every wall point within 1 m in x.
  void addKeyframe(const KeyframeId& id, const Vector3d& p_c) {
    const SE3d T_m_c(SO3d(), p_c);
    ServerKeyframe kf;
    kf.id = id;
    kf.t_ns = 1'000'000'000 + static_cast<std::int64_t>(id.counter) * 100'000'000;
    kf.T_w_s = T_m_c * cameraExtrinsics(id.agent).inverse();
    std::vector<std::size_t> seen;
    for (std::size_t i = 0; i < wall.size(); ++i) {
      if (std::abs(wall[i].x() - p_c.x()) > 1.0) continue;
      const Vector3d X_c = T_m_c.inverse() * wall[i];
      const CovisibleCamera c = cameraOf(id.agent);
      const Eigen::Vector2f pinhole(static_cast<float>(c.fx * X_c.x() / X_c.z() + c.cx),
                                    static_cast<float>(c.fy * X_c.y() / X_c.z() + c.cy));
      features::Keypoint key;
      key.px = pinhole + Eigen::Vector2f(3.0F, -2.0F);  // as a lens would distort it: only the pinhole one is exact
      key.octave = static_cast<std::uint8_t>(i % 3);
      kf.keypoints.push_back(key);
      kf.keypoints_undistorted.push_back(pinhole);
      features::Descriptor d{};
      d[0] = static_cast<std::uint8_t>(i);
      kf.descriptors.push_back(d);
      seen.push_back(i);
    }
    ASSERT_TRUE(map.addKeyframe(std::move(kf)).ok());
    for (std::size_t k = 0; k < seen.size(); ++k) {
      const MapPointId pid{1, static_cast<std::uint32_t>(seen[k])};  // one point per wall point
      if (map.point(pid) == nullptr) {
        ServerMapPoint point;
        point.id = pid;
        point.reference = id;
        point.p_w = wall[seen[k]];
        point.octave = static_cast<std::uint8_t>(seen[k] % 3);
        ASSERT_TRUE(map.addPoint(std::move(point)).ok());
      }
      ASSERT_TRUE(map.addObservation(id, static_cast<std::uint16_t>(k), pid).ok());
    }
  }

  // Agent 1's newest keyframes, newest first.
  [[nodiscard]] std::vector<KeyframeId> seeds() const { return {agent1[59], agent1[58], agent1[57]}; }

  std::vector<Vector3d> wall;
};

std::vector<KeyframeId> idsOf(const std::vector<std::pair<KeyframeId, int>>& ranked) {
  std::vector<KeyframeId> out;
  for (const auto& [id, w] : ranked) out.push_back(id);
  return out;
}

TEST(CovisibleDownlink, SelectsTheKMostCovisibleKeyframesOfOtherAgentsAndTheAgentsOwnPast) {
  const Scene scene;
  CovisibleOptions options;  // K = 10
  options.own_recent_excluded = 50;
  const auto ranked = selectCovisible(scene.map, scene.seeds(), options);

  ASSERT_EQ(ranked.size(), 10U);
  bool other_agent = false;
  bool own_past = false;
  for (const auto& [id, weight] : ranked) {
    EXPECT_TRUE(id.agent == 2 || id.counter <= 9) << id.toString() << " is in the agent's local map already";
    other_agent |= id.agent == 2;
    own_past |= id.agent == 1;
  }
  EXPECT_TRUE(other_agent);
  EXPECT_TRUE(own_past);
  // Best first, and nothing left out that beats the weakest selected one.
  for (std::size_t i = 1; i < ranked.size(); ++i) EXPECT_GE(ranked[i - 1].second, ranked[i].second);
  const std::vector<KeyframeId> selected = idsOf(ranked);
  for (const auto& [id, kf] : scene.map.keyframes()) {
    if (std::find(selected.begin(), selected.end(), id) != selected.end()) continue;
    if (id.agent == 1 && id.counter > 9) continue;
    int weight = 0;
    for (const KeyframeId& seed : scene.seeds()) weight += scene.map.covisibility(seed, id);
    EXPECT_LE(weight, ranked.back().second) << id.toString();
  }
}

// Another agent's keyframe that holds its agent's onboard estimate (no GBA since it arrived, or its agent updated
// it after one) would pull that agent's drift into this one's local BA: it waits until the server refined it.
// The agent's own past goes down either way.
TEST(CovisibleDownlink, AnotherAgentsKeyframesGoDownOnlyWhileTheirStateIsTheServersRefinedOne) {
  Scene scene;
  CovisibleOptions options;
  options.own_recent_excluded = 50;
  const auto agentsIn = [&](const CovisibleOptions& o) {
    std::set<std::uint32_t> agent2;
    int agent1 = 0;
    for (const auto& [id, weight] : selectCovisible(scene.map, scene.seeds(), o)) {
      if (id.agent == 2) agent2.insert(id.counter);
      agent1 += id.agent == 1 ? 1 : 0;
    }
    return std::make_pair(agent2, agent1);
  };
  // Agent 1 never had a GBA here: its own keyframes all hold its onboard estimates.
  for (const auto& [id, kf] : scene.map.keyframes()) ASSERT_TRUE(id.agent == 2 || !kf.refined) << id.toString();
  ASSERT_GE(agentsIn(options).first.size(), 3U) << "refined, agent 2's keyframes compete";
  // Agent 2 updates keyframes 0..4 (its local BA): those hold its onboard estimate again.
  for (std::uint32_t c = 0; c < 5; ++c) scene.map.keyframe(KeyframeId{2, c})->refined = false;

  const auto [agent2, agent1] = agentsIn(options);
  for (std::uint32_t c : agent2) EXPECT_GE(c, 5U) << "agent 2's keyframe " << c << " holds its onboard estimate";
  EXPECT_GT(agent1, 0) << "the agent's own past, unrefined, is not held back";

  options.foreign_refined_only = false;  // the rule off: every keyframe competes again
  const auto all = agentsIn(options).first;
  EXPECT_TRUE(std::any_of(all.begin(), all.end(), [](std::uint32_t c) { return c < 5; }));
}

// A pose graph (a loop's, or a merge's correction) moves keyframes without their points' evidence: until the GBA
// after it, none of them goes down, the agent's own included, and a moved anchor the agent holds is not updated.
TEST(CovisibleDownlink, KeyframesAPoseGraphMovedWaitForTheGbaOwnOnesToo) {
  Scene scene;
  CovisibleOptions options;
  options.own_recent_excluded = 50;
  CovisibleSender sut{options};
  v1::CovisibleMap first;
  sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, first);
  ASSERT_GT(first.keyframes_size(), 0);
  const KeyframeId held{static_cast<AgentId>(first.keyframes(0).agent()), first.keyframes(0).counter()};
  std::set<KeyframeId> before;
  for (const auto& [id, weight] : selectCovisible(scene.map, scene.seeds(), options)) before.insert(id);
  ASSERT_TRUE(std::any_of(before.begin(), before.end(), [](const KeyframeId& id) { return id.agent == 1; }));
  // A pose graph moves every keyframe by 5 cm.
  for (const auto& [id, kf_const] : scene.map.keyframes()) {
    ServerKeyframe* kf = scene.map.keyframe(id);
    kf->T_w_s.translation() += Vector3d(0.05, 0.0, 0.0);
    kf->refined = false;
    kf->provisional = true;
  }
  EXPECT_TRUE(selectCovisible(scene.map, scene.seeds(), options).empty());
  v1::CovisibleMap moved;
  const CovisibleReport report = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, moved);
  EXPECT_EQ(report.keyframe_updates, 0) << held.toString() << " keeps the state the agent holds";
  // The agent updates its own keyframes (its local BA): they hold its estimate again and go down.
  for (const KeyframeId& id : before) {
    if (id.agent == 1) scene.map.keyframe(id)->provisional = false;
  }
  const auto again = selectCovisible(scene.map, scene.seeds(), options);
  EXPECT_FALSE(again.empty());
  for (const auto& [id, weight] : again) EXPECT_EQ(id.agent, 1U);
}

// A keyframe its agent sent before its local BA holds tracking's state until the update after the BA: no agent
// gets it as an anchor before then.
TEST(CovisibleDownlink, AKeyframeSentBeforeItsLocalBaGoesToNoAgentUntilItsUpdate) {
  Scene scene;
  CovisibleOptions options;
  options.own_recent_excluded = 50;
  const auto selected = [&] {
    std::set<KeyframeId> out;
    for (const auto& [id, weight] : selectCovisible(scene.map, scene.seeds(), options)) out.insert(id);
    return out;
  };
  const std::set<KeyframeId> before = selected();
  ASSERT_GE(before.size(), 2U);
  const KeyframeId waiting = *before.begin();
  scene.map.keyframe(waiting)->awaiting_local_ba = true;
  const std::set<KeyframeId> meanwhile = selected();
  EXPECT_EQ(meanwhile.count(waiting), 0U);
  EXPECT_FALSE(meanwhile.empty());
  scene.map.keyframe(waiting)->awaiting_local_ba = false;  // its update came
  EXPECT_EQ(selected(), before);
}

TEST(CovisibleDownlink, TheLocalMapSizeTheAgentsHelloGaveDecidesWhichOfItsOwnKeyframesAreLeftOut) {
  const Scene scene;
  const auto own_above = [](const v1::CovisibleMap& m, std::uint32_t counter) {
    for (int i = 0; i < m.selected_counter_size(); ++i) {
      if (m.selected_agent(i) == 1 && m.selected_counter(i) > counter) return true;
    }
    return false;
  };
  CovisibleOptions options;
  options.keyframes = 20;  // room for the way back too
  v1::CovisibleMap keeps_50;
  v1::CovisibleMap keeps_5;
  CovisibleSender{options}.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, keeps_50, 50);
  CovisibleSender{options}.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, keeps_5, 5);

  EXPECT_FALSE(own_above(keeps_50, 9)) << "an agent keeping 50 holds keyframes 10..59 itself";
  EXPECT_TRUE(own_above(keeps_5, 40)) << "an agent keeping 5 gets its keyframes from 54 down, near its start";
  EXPECT_FALSE(own_above(keeps_5, 54));
}

TEST(CovisibleDownlink, EverythingIsInTheAgentsWorldFrameAndEveryObservationProjects) {
  const Scene scene;
  // The agent's world frame is not the server map's (a merge moved the agent's map).
  const SE3d T_w_m(SO3d::exp(Vector3d(0.02, -0.01, 0.7)), Vector3d(3.0, -1.0, 0.5));
  CovisibleSender sut{CovisibleOptions{}};
  v1::CovisibleMap out;
  const CovisibleReport report = sut.fill(scene.map, scene.seeds(), 4, T_w_m, scene.cameras, out);

  ASSERT_EQ(report.keyframes, 10);
  EXPECT_EQ(out.agent_map(), 4U);
  EXPECT_EQ(out.selected_counter_size(), 10);
  std::map<MapPointId, Vector3d> points;
  for (const v1::CovisiblePoint& p : out.points()) {
    const MapPointId id{static_cast<AgentId>(p.agent()), p.counter()};
    ASSERT_EQ(p.p_w_size(), 3);
    const Vector3d p_w = Eigen::Vector3f(p.p_w(0), p.p_w(1), p.p_w(2)).cast<double>();
    EXPECT_LT((p_w - T_w_m * scene.map.point(id)->p_w).norm(), 1e-5);
    EXPECT_TRUE(points.emplace(id, p_w).second) << "point " << id.toString() << " sent twice";
  }
  int observations = 0;
  for (const v1::CovisibleKeyframe& kf : out.keyframes()) {
    const SE3d T_w_c(
        SO3d(Eigen::Quaternionf(kf.t_w_c().qw(), kf.t_w_c().qx(), kf.t_w_c().qy(), kf.t_w_c().qz()).cast<double>()),
        Vector3d(kf.t_w_c().px(), kf.t_w_c().py(), kf.t_w_c().pz()));
    const int n = kf.point_counter_size();
    ASSERT_EQ(kf.xy_size(), 2 * n);
    ASSERT_EQ(kf.point_agent_size(), n);
    ASSERT_EQ(static_cast<int>(kf.octave().size()), n);
    for (int i = 0; i < n; ++i) {
      const MapPointId id{static_cast<AgentId>(kf.point_agent(i)), kf.point_counter(i)};
      ASSERT_EQ(points.count(id), 1U) << "an observation of a point the message does not carry";
      const Vector3d X_c = T_w_c.inverse() * points.at(id);
      EXPECT_NEAR(X_c.x() / X_c.z(), kf.xy(2 * i), 1e-5);
      EXPECT_NEAR(X_c.y() / X_c.z(), kf.xy(2 * i + 1), 1e-5);
      ++observations;
    }
  }
  EXPECT_GT(observations, 500);
}

TEST(CovisibleDownlink, AKeyframeGoesInFullOnceAndAfterwardsOnlyWhenTheServerMovesIt) {
  Scene scene;
  CovisibleSender sut{CovisibleOptions{}};
  v1::CovisibleMap first;
  v1::CovisibleMap second;
  sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, first);
  const CovisibleReport again = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, second);

  ASSERT_EQ(first.keyframes_size(), 10);
  std::set<MapPointId> observed;  // every point the selected keyframes observe
  for (const auto& kf : first.keyframes()) {
    for (const MapPointId& p : scene.map.keyframe(KeyframeId{static_cast<AgentId>(kf.agent()), kf.counter()})->point) {
      observed.insert(p);
    }
  }
  EXPECT_EQ(static_cast<std::size_t>(first.points_size()), observed.size());
  EXPECT_FALSE(again.carriesData());
  EXPECT_EQ(second.ByteSizeLong(), 0U) << "nothing changed, nothing to say";

  // The server moves one selected keyframe by 1 cm and one of its points by 1 cm (a GBA).
  const KeyframeId moved{static_cast<AgentId>(first.keyframes(0).agent()), first.keyframes(0).counter()};
  const MapPointId point{static_cast<AgentId>(first.keyframes(0).point_agent(0)), first.keyframes(0).point_counter(0)};
  scene.map.keyframe(moved)->T_w_s.translation() += Vector3d(0.01, 0.0, 0.0);
  scene.map.point(point)->p_w += Vector3d(0.0, 0.01, 0.0);
  v1::CovisibleMap third;
  const CovisibleReport update = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, third);

  EXPECT_EQ(third.keyframes_size(), 0);
  EXPECT_EQ(third.points_size(), 0);
  ASSERT_EQ(update.keyframe_updates, 1);
  EXPECT_EQ(third.keyframe_updates(0).counter(), moved.counter);
  EXPECT_NEAR(third.keyframe_updates(0).t_w_c().px(),
              (scene.map.keyframe(moved)->T_w_s * cameraExtrinsics(moved.agent)).translation().x(), 1e-9);
  ASSERT_EQ(update.point_updates, 1);
  EXPECT_EQ(third.point_update_counter(0), point.counter);
  EXPECT_NEAR(third.point_update_p_w(1), scene.map.point(point)->p_w.y(), 1e-6);
}

TEST(CovisibleDownlink, AKeyframeThatLeftTheSelectionGoesInFullAgainWhenSelectedAgain) {
  // The agent holds only the selected keyframes: when the selection moves away, it lets them go, so the server
  // must send them whole (with their points) when they come back.
  const Scene scene;
  CovisibleSender sut{CovisibleOptions{}};
  v1::CovisibleMap first;
  sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, first);
  ASSERT_EQ(first.keyframes_size(), 10);
  ASSERT_GT(first.points_size(), 0);
  // Agent 1 at the far end (x = 2.9 m): little of the start is covisible with it, and its own keyframes out
  // there are too recent to send.
  v1::CovisibleMap away;
  sut.fill(scene.map, {scene.agent1[29], scene.agent1[28], scene.agent1[27]}, 0, SE3d(), scene.cameras, away);
  std::set<KeyframeId> first_ids;
  for (const auto& kf : first.keyframes()) first_ids.insert(KeyframeId{static_cast<AgentId>(kf.agent()), kf.counter()});
  std::set<KeyframeId> let_go = first_ids;  // the start's keyframes the far end's selection does not hold
  for (int i = 0; i < away.selected_counter_size(); ++i) {
    let_go.erase(KeyframeId{static_cast<AgentId>(away.selected_agent(i)), away.selected_counter(i)});
  }
  ASSERT_GE(let_go.size(), 5U) << "the far end sees little of the start";
  EXPECT_EQ(sut.keyframesSent(), static_cast<std::size_t>(away.selected_counter_size()));

  v1::CovisibleMap back;
  const CovisibleReport came_back = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, back);
  std::set<KeyframeId> resent;
  for (const auto& kf : back.keyframes()) resent.insert(KeyframeId{static_cast<AgentId>(kf.agent()), kf.counter()});
  EXPECT_EQ(resent, let_go) << "the keyframes let go go in full again, and only they";
  EXPECT_GT(back.points_size(), 0) << "with their points";
  EXPECT_EQ(came_back.selected, 10);
}

TEST(CovisibleDownlink, TheBudgetSendsTheBestRankedFirstAndTheRestInTheNextMessages) {
  const Scene scene;
  CovisibleOptions options;
  options.budget_bytes = 6000;  // room for a keyframe or two with their points
  CovisibleSender sut{options};
  const std::vector<KeyframeId> ranked = idsOf(selectCovisible(scene.map, scene.seeds(), options));
  std::vector<KeyframeId> order;
  std::size_t total_bytes = 0;
  int messages = 0;
  while (order.size() < ranked.size() && messages < 50) {
    v1::CovisibleMap out;
    const CovisibleReport report = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, out);
    ++messages;
    total_bytes += out.ByteSizeLong();
    EXPECT_LE(out.ByteSizeLong(), options.budget_bytes);
    ASSERT_GT(report.keyframes, 0) << "message " << messages << " made no progress";
    if (order.size() + static_cast<std::size_t>(report.keyframes) < ranked.size()) {
      EXPECT_GT(report.deferred, 0);
    }
    for (const auto& kf : out.keyframes()) order.push_back(KeyframeId{static_cast<AgentId>(kf.agent()), kf.counter()});
  }
  EXPECT_EQ(order, ranked) << "sent best first, each once";
  EXPECT_GT(total_bytes, options.budget_bytes) << "the budget had to split the selection";
}

TEST(CovisibleDownlink, AKeyframeLargerThanTheBudgetGoesAloneSoThatEveryMessageMakesProgress) {
  const Scene scene;
  CovisibleOptions options;
  options.budget_bytes = 1024;  // less than any keyframe with its points
  CovisibleSender sut{options};
  for (int message = 1; message <= 10; ++message) {
    v1::CovisibleMap out;
    const CovisibleReport report = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, out);
    EXPECT_EQ(report.keyframes, 1) << "message " << message;
    EXPECT_EQ(report.deferred, 10 - message);
  }
}

TEST(CovisibleDownlink, ANewAgentMapStartsAfreshAndNoSeedsSendNothing) {
  const Scene scene;
  CovisibleSender sut{CovisibleOptions{}};
  v1::CovisibleMap out;
  sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, out);
  const CovisibleReport same_map = sut.fill(scene.map, scene.seeds(), 0, SE3d(), scene.cameras, out);
  const CovisibleReport new_map = sut.fill(scene.map, scene.seeds(), 1, SE3d(), scene.cameras, out);
  const CovisibleReport no_seeds = sut.fill(scene.map, {}, 1, SE3d(), scene.cameras, out);

  EXPECT_EQ(same_map.keyframes, 0);
  EXPECT_EQ(new_map.keyframes, 10) << "a new world frame: everything again";
  EXPECT_EQ(no_seeds.selected, 0);
  EXPECT_FALSE(no_seeds.carriesData());
  EXPECT_EQ(out.selected_counter_size(), 0) << "the selection is now empty, and the message says so";
  EXPECT_EQ(out.keyframes_size() + out.points_size() + out.keyframe_updates_size(), 0);
  EXPECT_EQ(out.agent_map(), 1U);
}

TEST(CovisibleDownlink, OptionsOutOfRangeAreRefusedByName) {
  CovisibleOptions options;
  options.keyframes = 0;
  const Status s = options.validate();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message().find("keyframes"), std::string::npos);
  options = CovisibleOptions{};
  options.budget_bytes = 10;
  EXPECT_FALSE(options.validate().ok());
  options = CovisibleOptions{};
  options.update_translation_m = std::nan("");
  EXPECT_FALSE(options.validate().ok());
}

}  // namespace
}  // namespace cvislam::server
