// What the server sends down, applied by the mapper (Mapper::applyDownlink) on the synthetic scene of
// mapper_fixture.hpp: another agent's keyframes and points as anchors held fixed in local BA, messages twice, out of
// order or about what the agent let go, corrections of the agent's own keyframes, and the older keyframes the
// server's map takes the place of.
#include <cstdio>
#include <memory>
#include <vector>

#include <gtest/gtest.h>

#include "test/agent_rt/mapping/mapper_fixture.hpp"

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

// Another agent's keyframes and points as the server sends them: in this agent's world frame (here the scene
// in the monocular map's scale), observations in normalised coordinates, point ids of agent 7.
class MapperDownlinkTest : public MapperTest {
 protected:
  void adjust(MapperOptions& options) override { options.downlink.apply_corrections = true; }
  void SetUp() override {
    MapperTest::SetUp();
    downlink_ = std::make_unique<AnchorMessage>();
    ASSERT_TRUE(mapper_->process(keyframe(0, KeyframeKind::kNewMap, truePose(0)), *snapshot_).ok());
    auto r2 = mapper_->process(keyframe(2, KeyframeKind::kTracked, truePose(0)), *snapshot_);
    ASSERT_TRUE(r2.ok() && r2->mono_initialised_now);
    // The map's scale: keyframe 2's distance from keyframe 0 against the truth's.
    const auto& kfs = mapper_->map().keyframes();
    std::vector<SE3d> poses;
    kfs.forEach([&](PoolHandle, const KeyframeData& kf) { poses.push_back(kf.T_w_s); });
    ASSERT_EQ(poses.size(), 2u);
    scale_ = (poses[1].translation() - poses[0].translation()).norm() /
             (truePose(2).translation() - truePose(0).translation()).norm();
    for (int k = 3; k <= 4; ++k)
      ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_).ok());
  }

  static MapPointId serverPoint(std::size_t j) { return MapPointId{7, static_cast<std::uint32_t>(j)}; }

  // Agent 7's keyframe at the pose of keyframe k of this agent's path, observing every scene point it sees.
  void addAnchor(AnchorMessage& m, int k, std::uint32_t counter, bool with_points = true) {
    AnchorKeyframeMsg& a = m.keyframes[m.keyframe_count++];
    a.id = KeyframeId{7, counter};
    a.t_ns = 1'000'000'000LL * (k + 1);
    const SE3d T_w_c = truePose(k, scale_) * T_s_c_;
    a.T_w_c = toMsg(T_w_c);
    a.observation_count = 0;
    const SE3d T_c_w_true = (truePose(k) * T_s_c_).inverse();
    for (std::size_t j = 0; j < scene_.p_w.size() && a.observation_count < kMaxKeypointsPerKeyframe; ++j) {
      const Vector3d p_c = T_c_w_true * scene_.p_w[j];
      const auto px = camera_->project(p_c);
      if (p_c.z() < 0.5 || !px || px->x() < 20 || px->y() < 20 || px->x() > 730 || px->y() > 460) continue;
      a.observations[a.observation_count++] = AnchorObservationMsg{
          static_cast<float>(p_c.x() / p_c.z()), static_cast<float>(p_c.y() / p_c.z()), serverPoint(j), 0};
      if (!with_points) continue;
      bool listed = false;
      for (std::uint32_t i = 0; i < m.point_count && !listed; ++i) listed = m.points[i].id == serverPoint(j);
      if (listed) continue;
      AnchorPointMsg& p = m.points[m.point_count++];
      p.id = serverPoint(j);
      const Vector3d p_w = scale_ * scene_.p_w[j];
      p.p_w = {p_w.x(), p_w.y(), p_w.z()};
      p.descriptor = scene_.descriptors[j];
    }
    m.selected[m.selected_count++] = a.id;
  }

  AnchorMessage& message(std::uint32_t stream, std::uint64_t sequence) {
    AnchorMessage& m = *downlink_;
    m = AnchorMessage{};
    m.stream = stream;
    m.sequence = sequence;
    m.has_covisible = 1;
    m.agent_map = 1;  // the map the fixture's keyframe 0 started
    return m;
  }

  [[nodiscard]] int anchorsHeld() const {
    int n = 0;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { n += kf.anchor ? 1 : 0; });
    return n;
  }
  [[nodiscard]] int serverPointsHeld() const {
    int n = 0;
    mapper_->map().mapPoints().forEach([&](PoolHandle, const MapPointData& p) { n += p.from_server ? 1 : 0; });
    return n;
  }
  [[nodiscard]] const KeyframeData* keyframeById(const KeyframeId& id) const {
    const KeyframeData* found = nullptr;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
      if (kf.id == id) found = &kf;
    });
    return found;
  }

  double scale_ = 1.0;
  std::unique_ptr<AnchorMessage> downlink_;
};

TEST_F(MapperDownlinkTest, AnAnchorFromAnotherAgentTakesPartInLocalBaWithoutMovingAndStaysOffTheUplink) {
  AnchorMessage& m = message(1, 1);
  addAnchor(m, 5, 100);
  addAnchor(m, 6, 101);
  auto applied = mapper_->applyDownlink(m);
  ASSERT_TRUE(applied.ok()) << applied.error().toString();
  EXPECT_EQ(applied->anchors_added, 2);
  EXPECT_EQ(applied->anchors_held, 2);
  EXPECT_GT(applied->points_added, 150);
  EXPECT_EQ(applied->unknown_references, 0);
  const SE3d anchor_before = keyframeById(KeyframeId{7, 100})->T_w_s;

  // The agent's next keyframe sees the same place: mapping finds the server's points in it, and local BA holds
  // the anchors fixed while their observations constrain the window. The estimate handed in is off by 3 cm.
  auto delta = std::make_unique<MapDeltaMessage>();
  SE3d estimate = truePose(5, scale_);
  estimate.translation() += Vector3d(0.03, -0.02, 0.01) * scale_;
  auto r5 = mapper_->process(keyframe(5, KeyframeKind::kTracked, estimate), *snapshot_, delta.get());
  ASSERT_TRUE(r5.ok()) << r5.error().toString();
  ASSERT_TRUE(r5->ba_ran);
  std::printf(
      "with anchors: fused %d, merged %d; BA %d window + %d fixed (%d anchors), %d factors of which %d by "
      "anchors\n",
      r5->fused, r5->merged, r5->ba.window_keyframes, r5->ba.fixed_keyframes, r5->ba.anchor_keyframes,
      r5->ba.reprojection_factors, r5->ba.anchor_factors);
  EXPECT_EQ(r5->ba.anchor_keyframes, 2);
  EXPECT_GT(r5->ba.anchor_factors, 100) << "the anchors' observations are residuals of local BA";
  const KeyframeData* anchor = keyframeById(KeyframeId{7, 100});
  ASSERT_NE(anchor, nullptr);
  // Held fixed by local BA. Not compared bit for bit: the frame bookkeeping re-expresses anchors with a change
  // that is the identity up to rounding, and on aarch64 (fused multiply-adds) that leaves 1e-19 m.
  EXPECT_LT((anchor->T_w_s.translation() - anchor_before.translation()).norm(), 1e-12) << "held fixed";
  EXPECT_LT((anchor->T_w_s.so3().inverse() * anchor_before.so3()).log().norm(), 1e-12);
  const KeyframeData* own = keyframeById(KeyframeId{0, 5});
  ASSERT_NE(own, nullptr);
  EXPECT_LT((own->T_w_s.translation() - truePose(5, scale_).translation()).norm(), 0.005 * scale_)
      << "the window keyframe is pulled onto the anchors' map";

  // The server's points that duplicated the agent's went into the agent's (the anchors observe those now); the
  // rest are in the snapshot, for tracking to match.
  EXPECT_GT(r5->merged, 150);
  int server_in_snapshot = 0;
  for (std::uint32_t i = 0; i < snapshot_->point_count; ++i) server_in_snapshot += snapshot_->points[i].id.agent == 7;
  EXPECT_GT(server_in_snapshot, 0);
  EXPECT_EQ(server_in_snapshot, serverPointsHeld());
  // The snapshot marks the anchors, so that nothing records them as this agent's keyframes (their counters are
  // another agent's).
  int anchors_marked = 0;
  for (std::uint16_t i = 0; i < snapshot_->keyframe_count; ++i) {
    EXPECT_EQ(snapshot_->keyframe_is_anchor[i] != 0, snapshot_->keyframes[i].id.agent == 7) << i;
    anchors_marked += snapshot_->keyframe_is_anchor[i];
  }
  EXPECT_EQ(anchors_marked, 2);

  // Nothing of the server's goes back up: no anchor state, no server point, no event or observation of one.
  for (std::uint16_t i = 0; i < delta->keyframe_count; ++i) EXPECT_EQ(delta->keyframes[i].id.agent, 0) << i;
  for (std::uint32_t i = 0; i < delta->point_count; ++i) EXPECT_EQ(delta->points[i].id.agent, 0) << i;
  for (std::uint16_t i = 0; i < delta->event_count; ++i) {
    EXPECT_EQ(delta->events[i].keyframe.agent, 0) << i;
    EXPECT_EQ(delta->events[i].point.agent, 0) << i;
    EXPECT_EQ(delta->events[i].other.agent, 0) << i;
  }
  ASSERT_EQ(delta->has_keyframe, 1);
  for (std::uint16_t k = 0; k < delta->keypoint_count; ++k) {
    if (delta->has_observation[k] != 0) {
      EXPECT_EQ(delta->observation[k].agent, 0) << k;
    }
  }
}

class MapperDownlinkWithPlaceKeyframesTest : public MapperDownlinkTest {
  void adjust(MapperOptions& options) override { options.retention.place_keyframes = 3; }
};

// Alone, the map keeps three older keyframes for their places beside the newest six; once the server's covisible
// map is held, it keeps the newest six only, and the oldest go.
TEST_F(MapperDownlinkWithPlaceKeyframesTest, TheServersMapTakesThePlaceOfTheOlderKeyframes) {
  const auto own = [&] {
    int n = 0;
    mapper_->map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { n += kf.anchor ? 0 : 1; });
    return n;
  };
  for (int k = 5; k <= 12; ++k) {
    ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_).ok());
  }
  ASSERT_EQ(own(), 9);
  ASSERT_NE(keyframeById(KeyframeId{0, 0}), nullptr);  // no older keyframe covers the first one's place
  AnchorMessage& m = message(1, 1);
  addAnchor(m, 12, 100);
  ASSERT_TRUE(mapper_->applyDownlink(m).ok());
  ASSERT_EQ(anchorsHeld(), 1);
  auto r13 = mapper_->process(keyframe(13, KeyframeKind::kTracked, truePose(13, scale_)), *snapshot_);
  ASSERT_TRUE(r13.ok());
  EXPECT_EQ(r13->evicted, 4);  // room for the new keyframe among the newest six
  EXPECT_EQ(own(), 6);
  EXPECT_EQ(keyframeById(KeyframeId{0, 0}), nullptr);
  EXPECT_NE(keyframeById(KeyframeId{0, 8}), nullptr);  // the newest six: 8-13
}

TEST_F(MapperDownlinkTest, MessagesTwiceOutOfOrderOrReferringToWhatTheAgentLetGoAreHandled) {
  AnchorMessage& m = message(1, 5);
  addAnchor(m, 5, 100);
  ASSERT_TRUE(mapper_->applyDownlink(m).ok());
  const int points = serverPointsHeld();
  ASSERT_GT(points, 100);

  // The same message again: stale, nothing changes.
  auto twice = mapper_->applyDownlink(m);
  ASSERT_TRUE(twice.ok());
  EXPECT_TRUE(twice->stale);
  // Its content again under a newer sequence (a resend): the anchor is held already, nothing is added twice.
  m.sequence = 6;
  auto resent = mapper_->applyDownlink(m);
  ASSERT_TRUE(resent.ok());
  EXPECT_FALSE(resent->stale);
  EXPECT_EQ(resent->anchors_added, 0);
  EXPECT_EQ(serverPointsHeld(), points);
  // An older one arriving late: ignored.
  AnchorMessage& late = message(1, 4);
  addAnchor(late, 6, 200);
  auto older = mapper_->applyDownlink(late);
  ASSERT_TRUE(older.ok());
  EXPECT_TRUE(older->stale);
  EXPECT_EQ(anchorsHeld(), 1);

  // Updates of a keyframe and points the agent does not hold, and a keyframe observing points that are in
  // neither the message nor the map (the agent let them go): skipped, counted, the rest applied.
  AnchorMessage& next = message(1, 7);
  next.selected[next.selected_count++] = KeyframeId{7, 100};
  addAnchor(next, 6, 201, /*with_points=*/false);
  next.keyframe_updates[next.keyframe_update_count++] = AnchorPoseUpdateMsg{KeyframeId{7, 999}, toMsg(SE3d())};
  next.point_updates[next.point_update_count++] = AnchorPointUpdateMsg{MapPointId{7, 99999}, {1.0, 2.0, 3.0}};
  auto partial = mapper_->applyDownlink(next);
  ASSERT_TRUE(partial.ok());
  EXPECT_EQ(partial->anchors_added, 1);
  EXPECT_GE(partial->unknown_references, 2);
  EXPECT_GT(partial->points_linked, 50) << "the new anchor's points held already are linked to it";
  EXPECT_EQ(anchorsHeld(), 2);

  // A new stream (the link reconnected) starts its sequences again; its selection drops keyframe 100, which
  // leaves with the points only it observed.
  AnchorMessage& reconnected = message(2, 1);
  reconnected.selected[reconnected.selected_count++] = KeyframeId{7, 201};
  auto after = mapper_->applyDownlink(reconnected);
  ASSERT_TRUE(after.ok());
  EXPECT_FALSE(after->stale);
  EXPECT_EQ(after->anchors_released, 1);
  EXPECT_EQ(anchorsHeld(), 1);
  EXPECT_LT(serverPointsHeld(), points);
  EXPECT_GT(serverPointsHeld(), 0) << "points keyframe 201 observes stay";

  // A covisible map in another agent map's frame is not used.
  AnchorMessage& other_map = message(2, 2);
  other_map.agent_map = 5;
  addAnchor(other_map, 6, 300);
  auto skipped = mapper_->applyDownlink(other_map);
  ASSERT_TRUE(skipped.ok());
  EXPECT_NE(skipped->skipped.find("agent map 5"), std::string::npos) << skipped->skipped;
  EXPECT_EQ(anchorsHeld(), 1);

  // Counts beyond the message's capacities (a corrupt chunk): refused, nothing applied.
  AnchorMessage& corrupt = message(2, 3);
  corrupt.point_count = static_cast<std::uint32_t>(kMaxAnchorPointsPerMessage + 1);
  EXPECT_FALSE(mapper_->applyDownlink(corrupt).ok());
  EXPECT_EQ(anchorsHeld(), 1);

  // The local map's next keyframe is processed as before.
  auto r = mapper_->process(keyframe(5, KeyframeKind::kTracked, truePose(5, scale_)), *snapshot_);
  ASSERT_TRUE(r.ok());
  EXPECT_GT(r->fused, 50);
}

TEST_F(MapperDownlinkTest, CorrectionsMoveOwnKeyframesOutsideTheLocalWindowAndTheNextKeyframesGoOn) {
  for (int k = 5; k <= 6; ++k) {
    ASSERT_TRUE(mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_).ok());
  }
  // Own keyframes 0, 2, 3, 4, 5, 6 (6 = N); the window (4) is 3..6, so 0 and 2 are outside it. The server
  // removed drift that grows with age (none at the newest), and its frame for this agent is 5 cm off the
  // agent's (a merge's error): the offset is taken out, the drift is applied.
  AnchorMessage& m = message(1, 1);
  m.has_covisible = 0;
  const Vector3d drift = Vector3d(0.02, 0.0, -0.01) * scale_;  // at keyframe 0
  const Vector3d offset(0.05, -0.03, 0.01);
  const auto drift_at = [&](std::uint32_t k) { return drift * (6.0 - k) / 6.0; };
  for (std::uint32_t k : {0U, 2U, 3U, 4U, 5U, 6U, 77U}) {
    const KeyframeData* kf = keyframeById(KeyframeId{0, k});
    KeyframeStateMsg& c = m.corrections[m.correction_count++];
    c.id = KeyframeId{0, k};
    SE3d T = kf != nullptr ? kf->T_w_s : SE3d();
    T.translation() += drift_at(k) + offset;
    c.T_w_s = toMsg(T);
  }
  const SE3d before_3 = keyframeById(KeyframeId{0, 3})->T_w_s;
  const SE3d before_0 = keyframeById(KeyframeId{0, 0})->T_w_s;
  auto applied = mapper_->applyDownlink(m);
  ASSERT_TRUE(applied.ok());
  EXPECT_EQ(applied->corrections_applied, 2);
  EXPECT_EQ(applied->corrections_deferred, 4) << "in the window";
  EXPECT_EQ(applied->corrections_skipped, 1) << "no longer in the map";
  EXPECT_NEAR(applied->frame_change_m, offset.norm(), 1e-9) << "the newest corrected keyframe keeps its pose";
  EXPECT_NEAR(applied->largest_correction_m, drift.norm(), 1e-9);
  EXPECT_NEAR((keyframeById(KeyframeId{0, 0})->T_w_s.translation() - before_0.translation() - drift).norm(), 0.0,
              1e-12);
  EXPECT_EQ((keyframeById(KeyframeId{0, 3})->T_w_s.translation() - before_3.translation()).norm(), 0.0)
      << "the window keeps its own states while it is the window";

  // The next keyframes are processed against the corrected map: points found, local BA converging.
  for (int k = 7; k <= 8; ++k) {
    auto r = mapper_->process(keyframe(k, KeyframeKind::kTracked, truePose(k, scale_)), *snapshot_);
    ASSERT_TRUE(r.ok()) << r.error().toString();
    EXPECT_GT(r->fused, 50) << k;
    EXPECT_TRUE(r->ba_ran);
    EXPECT_LE(r->ba.final_cost, r->ba.initial_cost);
    if (k == 7) {
      EXPECT_NEAR((keyframeById(KeyframeId{0, 3})->T_w_s.translation() - before_3.translation() - drift_at(3)).norm(),
                  0.0, 1e-12)
          << "keyframe 3 left the window and took the server's state, held fixed since";
    }
  }
}

}  // namespace
}  // namespace cvislam::agent
