// LocalMap: capacity reporting and eviction, re-anchoring of map points when their reference keyframe goes,
// anchors that stay, the culling policy, and the merging of duplicate points.
#include "agent_rt/map/local_map.hpp"

#include <memory>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/euroc_calibration.hpp"

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;

class LocalMapTest : public ::testing::Test {
 protected:
  LocalMapTest() : sut_(std::make_unique<LocalMap>(dataset::eurocCam0().T_b_c)) {}

  // A keyframe at x = position along the world x axis, looking along world +x like the EuRoC camera does
  // when the body is turned so; 10 keypoints.
  PoolHandle addKeyframe(double x, bool anchor = false) {
    auto kf = std::make_unique<KeyframeData>();
    kf->id = ids_.next();
    kf->T_w_s = SE3d(geometry::SO3d(), Vector3d(x, 0.0, 0.0));
    kf->anchor = anchor;
    kf->keypoint_count = 10;
    auto handle = sut_->insertKeyframe(*kf);
    EXPECT_TRUE(handle.ok()) << handle.error().toString();
    return handle.ok() ? *handle : PoolHandle{};
  }

  std::unique_ptr<LocalMap> sut_;
  IdCounter<KeyframeId> ids_{0};
  IdCounter<MapPointId> point_ids_{0};
};

TEST_F(LocalMapTest, AFullMapRefusesAKeyframeUntilTheOldestIsEvicted) {
  for (std::size_t i = 0; i < kMaxKeyframes; ++i) addKeyframe(static_cast<double>(i));
  auto extra = std::make_unique<KeyframeData>();
  extra->id = ids_.next();
  extra->T_w_s = SE3d(geometry::SO3d(), Vector3d(1000.0, 0.0, 0.0));
  auto refused = sut_->insertKeyframe(*extra);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code(), ErrorCode::kCapacityExceeded);
  EXPECT_NE(refused.error().message().find("evict"), std::string::npos);

  ASSERT_TRUE(sut_->evictOldestKeyframe().ok());
  EXPECT_TRUE(sut_->insertKeyframe(*extra).ok());
  // The oldest (x = 0) went, the one at x = 1 stayed.
  bool has_first = false;
  bool has_second = false;
  sut_->keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
    has_first = has_first || kf.T_w_s.translation().x() == 0.0;
    has_second = has_second || kf.T_w_s.translation().x() == 1.0;
  });
  EXPECT_FALSE(has_first);
  EXPECT_TRUE(has_second);
}

TEST_F(LocalMapTest, RemovingTheReferenceKeyframeReanchorsItsPointsOrRemovesThem) {
  const PoolHandle kf0 = addKeyframe(0.0);
  const PoolHandle kf1 = addKeyframe(0.5);
  auto shared = sut_->createMapPoint(kf0, 3, Vector3d(0.1, -0.05, 1.0), 4.0, point_ids_.next());
  auto lonely = sut_->createMapPoint(kf0, 4, Vector3d(-0.2, 0.1, 1.0), 6.0, point_ids_.next());
  ASSERT_TRUE(shared.ok() && lonely.ok());
  ASSERT_TRUE(sut_->addObservation(kf1, 7, *shared).ok());
  const Vector3d p_w_before = *sut_->pointInWorld(*shared);

  ASSERT_TRUE(sut_->removeKeyframe(kf0).ok());
  ASSERT_TRUE(sut_->mapPoints().valid(*shared));
  EXPECT_EQ(sut_->mapPoints().get(*shared)->reference, kf1);
  EXPECT_EQ(sut_->mapPoints().get(*shared)->observation_count, 1);
  EXPECT_LT((*sut_->pointInWorld(*shared) - p_w_before).norm(), 1e-9);
  EXPECT_FALSE(sut_->mapPoints().valid(*lonely));  // nobody else saw it
  EXPECT_FALSE(sut_->keyframes().valid(kf0));
}

// Records what the local map reports.
struct RecordedEvents final : MapEventSink {
  void record(const MapEvent& e) override { events.push_back(e); }
  std::vector<MapEvent> events;
};

TEST_F(LocalMapTest, NothingAboutTheServersKeyframesAndPointsIsReported) {
  RecordedEvents recorded;
  sut_->setEventSink(&recorded);
  const PoolHandle anchor = addKeyframe(0.0, /*anchor=*/true);
  const PoolHandle own = addKeyframe(0.5);
  auto server = sut_->createMapPoint(anchor, 2, Vector3d(0.1, -0.05, 1.0), 4.0, MapPointId{7, 40});
  ASSERT_TRUE(server.ok());
  sut_->mapPoints().get(*server)->from_server = true;
  ASSERT_TRUE(sut_->addObservation(own, 5, *server).ok());
  EXPECT_EQ(sut_->cullMapPoints(CullOptions{}), 0) << "the server's points are not culled";
  EXPECT_TRUE(recorded.events.empty()) << "an anchor's point, and an own keyframe's view of it: not reported";

  // The agent's own point, observed by the anchor too: its creation is reported, the anchor's view of it is not.
  auto own_point = sut_->createMapPoint(own, 6, Vector3d(-0.1, 0.05, 1.0), 3.0, MapPointId{0, 9});
  ASSERT_TRUE(own_point.ok());
  ASSERT_TRUE(sut_->addObservation(anchor, 3, *own_point).ok());
  ASSERT_EQ(recorded.events.size(), 1U);
  EXPECT_EQ(recorded.events[0].type, MapEventType::kPointCreated);
  EXPECT_EQ(recorded.events[0].keyframe, sut_->keyframes().get(own)->id);

  ASSERT_TRUE(sut_->removeKeyframe(anchor).ok());
  EXPECT_EQ(recorded.events.size(), 1U) << "an anchor leaving is not reported, nor its point going with it";
  ASSERT_TRUE(sut_->mapPoints().valid(*server)) << "the own keyframe observes it too: it stays, with that reference";
  EXPECT_EQ(sut_->mapPoints().get(*server)->reference, own);
  EXPECT_TRUE(sut_->mapPoints().get(*server)->from_server);
  sut_->setEventSink(nullptr);
}

TEST_F(LocalMapTest, AnchorsAreNeverEvicted) {
  addKeyframe(0.0, true);
  const PoolHandle own = addKeyframe(1.0);
  ASSERT_TRUE(sut_->evictOldestKeyframe().ok());
  EXPECT_FALSE(sut_->keyframes().valid(own));  // the older keyframe is an anchor, so the newer one went
  const Status none = sut_->evictOldestKeyframe();
  ASSERT_FALSE(none.ok());
  EXPECT_NE(none.error().message().find("anchor"), std::string::npos);
}

TEST_F(LocalMapTest, CullingRemovesRarelyFoundAndUnconfirmedPointsOnly) {
  const PoolHandle kf0 = addKeyframe(0.0);
  const PoolHandle kf1 = addKeyframe(0.5);
  auto rarely_found = sut_->createMapPoint(kf0, 0, Vector3d(0.0, 0.0, 1.0), 5.0, point_ids_.next());
  auto confirmed = sut_->createMapPoint(kf0, 1, Vector3d(0.1, 0.0, 1.0), 5.0, point_ids_.next());
  auto unconfirmed = sut_->createMapPoint(kf1, 2, Vector3d(0.0, 0.1, 1.0), 5.0, point_ids_.next());
  ASSERT_TRUE(rarely_found.ok() && confirmed.ok() && unconfirmed.ok());
  ASSERT_TRUE(sut_->addObservation(kf1, 0, *rarely_found).ok());
  ASSERT_TRUE(sut_->addObservation(kf1, 1, *confirmed).ok());
  sut_->mapPoints().get(*rarely_found)->visible = 20;
  sut_->mapPoints().get(*rarely_found)->found = 3;  // 15 % < 25 %
  sut_->mapPoints().get(*confirmed)->visible = 20;
  sut_->mapPoints().get(*confirmed)->found = 12;

  EXPECT_EQ(sut_->cullMapPoints({}), 1);  // only the rarely found one: the others are young
  EXPECT_FALSE(sut_->mapPoints().valid(*rarely_found));
  addKeyframe(1.0);
  addKeyframe(1.5);  // two keyframes newer than the unconfirmed point, which still has one observation
  EXPECT_EQ(sut_->cullMapPoints({}), 1);
  EXPECT_FALSE(sut_->mapPoints().valid(*unconfirmed));
  EXPECT_TRUE(sut_->mapPoints().valid(*confirmed));
  EXPECT_FALSE(sut_->keyframes().get(kf1)->has_map_point[2]);  // the observation went with the point
}

// A point whose observers leave the bounded map falls under the observation threshold, but it was confirmed: the
// local map lets it go as evicted, so the server (which mirrors the map through these events) keeps it. Only
// points that were never confirmed, or are rarely found, are culled (forgotten everywhere).
TEST_F(LocalMapTest, APointThatOutlivedItsObserversIsEvictedNotCulled) {
  struct Recorder final : MapEventSink {
    void record(const MapEvent& e) override {
      if (e.type == MapEventType::kPointRemoved) reasons.push_back({e.point.counter, e.reason});
    }
    std::vector<std::pair<std::uint32_t, MapEventReason>> reasons;
  } recorder;
  sut_->setEventSink(&recorder);
  const PoolHandle kf0 = addKeyframe(0.0);
  const PoolHandle kf1 = addKeyframe(0.5);
  auto confirmed = sut_->createMapPoint(kf1, 1, Vector3d(0.1, 0.0, 1.0), 5.0, point_ids_.next());
  auto unconfirmed = sut_->createMapPoint(kf1, 2, Vector3d(0.0, 0.1, 1.0), 5.0, point_ids_.next());
  ASSERT_TRUE(confirmed.ok() && unconfirmed.ok());
  ASSERT_TRUE(sut_->addObservation(kf0, 1, *confirmed).ok());
  addKeyframe(1.0);
  addKeyframe(1.5);
  ASSERT_TRUE(sut_->evictOldestKeyframe().ok());  // kf0: the confirmed point keeps one observer
  ASSERT_EQ(sut_->mapPoints().get(*confirmed)->observation_count, 1);
  EXPECT_EQ(sut_->mapPoints().get(*confirmed)->most_observations, 2);

  EXPECT_EQ(sut_->cullMapPoints({}), 2);
  EXPECT_FALSE(sut_->mapPoints().valid(*confirmed));
  EXPECT_FALSE(sut_->mapPoints().valid(*unconfirmed));
  ASSERT_EQ(recorder.reasons.size(), 2U);
  for (const auto& [counter, reason] : recorder.reasons) {
    EXPECT_EQ(reason, counter == 0 ? MapEventReason::kEvicted : MapEventReason::kCulled) << "point " << counter;
  }
  sut_->setEventSink(nullptr);
}

TEST_F(LocalMapTest, MergingADuplicateMovesItsObservationsAndCountsAndRemovesIt) {
  const PoolHandle a = addKeyframe(0.0);
  const PoolHandle b = addKeyframe(0.5);
  const PoolHandle c = addKeyframe(1.0);
  // keep: seen by a (keypoint 0) and b (keypoint 0). drop: seen by b (keypoint 1, so b saw both: it only loses
  // the link) and c (keypoint 2, which moves).
  auto keep = sut_->createMapPoint(a, 0, Vector3d::UnitZ(), 4.0, point_ids_.next());
  auto drop = sut_->createMapPoint(c, 2, Vector3d::UnitZ(), 4.1, point_ids_.next());
  ASSERT_TRUE(keep.ok() && drop.ok());
  ASSERT_TRUE(sut_->addObservation(b, 0, *keep).ok());
  ASSERT_TRUE(sut_->addObservation(b, 1, *drop).ok());
  sut_->mapPoints().get(*keep)->visible = 5;
  sut_->mapPoints().get(*keep)->found = 4;
  sut_->mapPoints().get(*drop)->visible = 3;
  sut_->mapPoints().get(*drop)->found = 1;

  auto moved = sut_->mergeMapPoints(*keep, *drop);
  ASSERT_TRUE(moved.ok()) << moved.error().toString();
  EXPECT_EQ(*moved, 1);
  EXPECT_FALSE(sut_->mapPoints().valid(*drop));
  const MapPointData& kept = *sut_->mapPoints().get(*keep);
  EXPECT_EQ(kept.observation_count, 3);  // a, b, c
  EXPECT_EQ(kept.visible, 8U);
  EXPECT_EQ(kept.found, 5U);
  const KeyframeData& kb = *sut_->keyframes().get(b);
  EXPECT_TRUE(kb.has_map_point[0]);
  EXPECT_FALSE(kb.has_map_point[1]);
  const KeyframeData& kc = *sut_->keyframes().get(c);
  ASSERT_TRUE(kc.has_map_point[2]);
  EXPECT_EQ(kc.map_point[2], *keep);

  EXPECT_FALSE(sut_->mergeMapPoints(*keep, *keep).ok());
  EXPECT_EQ(sut_->mergeMapPoints(*keep, *drop).error().code(), ErrorCode::kNotFound);  // gone already
}

TEST_F(LocalMapTest, BadObservationsAreRefusedWithTheirReason) {
  const PoolHandle kf0 = addKeyframe(0.0);
  auto point = sut_->createMapPoint(kf0, 0, Vector3d(0.0, 0.0, 1.0), 5.0, point_ids_.next());
  ASSERT_TRUE(point.ok());
  const Status twice = sut_->addObservation(kf0, 1, *point);
  ASSERT_FALSE(twice.ok());
  EXPECT_NE(twice.error().message().find("already observed"), std::string::npos);
  EXPECT_FALSE(sut_->addObservation(kf0, 0, *point).ok());    // keypoint taken
  EXPECT_FALSE(sut_->addObservation(kf0, 500, *point).ok());  // out of range
  EXPECT_FALSE(sut_->createMapPoint(kf0, 2, Vector3d(0.0, 0.0, 1.0), -1.0, point_ids_.next()).ok());
}

}  // namespace
}  // namespace cvislam::agent
