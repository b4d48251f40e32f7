// MapContent: keyframes, points and observations stay linked on both sides, and every covisibility weight equals
// a recount from scratch after each operation (adds, observations, merges, removals, and a long seeded random
// sequence of them).
#include "server_cloud/stack/map_content.hpp"
#include "server_cloud/stack/map_stack.hpp"

#include <algorithm>
#include <cstdint>
#include <map>
#include <random>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

namespace cvislam::server {
namespace {

using ::testing::HasSubstr;

constexpr AgentId kAgent = 3;
constexpr std::uint16_t kKeypointsPerKeyframe = 20;

KeyframeId kfId(std::uint32_t counter) {
  return KeyframeId{kAgent, counter};
}
MapPointId ptId(std::uint32_t counter) {
  return MapPointId{kAgent, counter};
}

ServerKeyframe makeKeyframe(std::uint32_t counter, std::uint16_t keypoints = kKeypointsPerKeyframe) {
  ServerKeyframe kf;
  kf.id = kfId(counter);
  kf.t_ns = 1'000'000'000 + static_cast<std::int64_t>(counter) * 50'000'000;
  kf.keypoints.resize(keypoints);
  kf.descriptors.resize(keypoints);
  return kf;
}

ServerMapPoint makePoint(std::uint32_t counter, std::uint32_t reference) {
  ServerMapPoint p;
  p.id = ptId(counter);
  p.reference = kfId(reference);
  p.p_w = Eigen::Vector3d(static_cast<double>(counter), 1.0, 2.0);
  return p;
}

// The covisibility graph recounted from the keyframes' own links: for every pair, the number of points both
// observe. Only pairs with a positive count appear.
std::map<std::pair<KeyframeId, KeyframeId>, int> recountCovisibility(const MapContent& map) {
  std::map<KeyframeId, std::set<MapPointId>> observed;
  for (const auto& [id, kf] : map.keyframes()) {
    for (std::size_t k = 0; k < kf.has_point.size(); ++k) {
      if (kf.has_point[k] != 0) observed[id].insert(kf.point[k]);
    }
  }
  std::map<std::pair<KeyframeId, KeyframeId>, int> weights;
  for (const auto& [a, points_a] : observed) {
    for (const auto& [b, points_b] : observed) {
      if (!(a < b)) continue;
      int shared = 0;
      for (const MapPointId& p : points_a) shared += static_cast<int>(points_b.count(p));
      if (shared > 0) weights[{a, b}] = shared;
    }
  }
  return weights;
}

// Every weight the map reports equals the recount, for every pair of keyframes, and the edge count agrees.
void expectCovisibilityEqualsRecount(const MapContent& map) {
  const auto expected = recountCovisibility(map);
  for (const auto& [a, kf_a] : map.keyframes()) {
    for (const auto& [b, kf_b] : map.keyframes()) {
      if (!(a < b)) continue;
      const auto it = expected.find({a, b});
      const int want = it == expected.end() ? 0 : it->second;
      EXPECT_EQ(map.covisibility(a, b), want) << a.toString() << "-" << b.toString();
      EXPECT_EQ(map.covisibility(b, a), want) << b.toString() << "-" << a.toString();
    }
  }
  EXPECT_EQ(map.covisibilityEdges(), expected.size());
}

class MapContentTest : public ::testing::Test {
 protected:
  void addKeyframes(std::uint32_t count) {
    for (std::uint32_t c = 0; c < count; ++c) ASSERT_TRUE(sut.addKeyframe(makeKeyframe(c)).ok());
  }
  void observe(std::uint32_t kf, std::uint16_t keypoint, std::uint32_t point) {
    const Status s = sut.addObservation(kfId(kf), keypoint, ptId(point));
    ASSERT_TRUE(s.ok()) << s.error().toString();
  }
  void expectConsistent() {
    const Status s = sut.checkConsistency();
    EXPECT_TRUE(s.ok()) << s.error().toString();
    expectCovisibilityEqualsRecount(sut);
  }

  MapContent sut{7};
};

TEST_F(MapContentTest, AddKeyframeTwiceIsRefusedAsAlreadyExisting) {
  addKeyframes(1);

  const Status s = sut.addKeyframe(makeKeyframe(0));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kAlreadyExists);
  EXPECT_THAT(s.error().message(), HasSubstr("keyframe 3:0"));
  EXPECT_EQ(sut.keyframes().size(), 1U);
}

TEST_F(MapContentTest, AddKeyframeSizesThePerKeypointLinksAndRecordsTheAgent) {
  ServerKeyframe kf = makeKeyframe(4, 12);
  kf.has_point.assign(3, 1);  // whatever the caller left here is replaced

  ASSERT_TRUE(sut.addKeyframe(std::move(kf)).ok());

  const ServerKeyframe* held = sut.keyframe(kfId(4));
  ASSERT_NE(held, nullptr);
  EXPECT_EQ(held->has_point, std::vector<std::uint8_t>(12, 0));
  EXPECT_EQ(held->point.size(), 12U);
  EXPECT_EQ(held->observationCount(), 0);
  EXPECT_EQ(sut.agents(), (std::set<AgentId>{kAgent}));
  expectConsistent();
}

TEST_F(MapContentTest, AddPointWithAnUnknownReferenceKeyframeIsRefusedAsNotFound) {
  addKeyframes(1);

  const Status s = sut.addPoint(makePoint(0, 9));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(s.error().message(), HasSubstr("reference keyframe 3:9"));
  EXPECT_TRUE(sut.points().empty());
}

TEST_F(MapContentTest, AddPointTwiceIsRefusedAsAlreadyExisting) {
  addKeyframes(1);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());

  const Status s = sut.addPoint(makePoint(0, 0));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kAlreadyExists);
  EXPECT_EQ(sut.points().size(), 1U);
}

TEST_F(MapContentTest, ObservationsOfSharedPointsGiveWeightsEqualToTheSharedCount) {
  addKeyframes(3);
  for (std::uint32_t p = 0; p < 4; ++p) ASSERT_TRUE(sut.addPoint(makePoint(p, 0)).ok());

  // Keyframe 0 sees points 0-3, keyframe 1 points 0-2, keyframe 2 points 2-3.
  for (std::uint16_t p = 0; p < 4; ++p) observe(0, p, p);
  for (std::uint16_t p = 0; p < 3; ++p) observe(1, static_cast<std::uint16_t>(10 + p), p);
  observe(2, 5, 2);
  observe(2, 6, 3);

  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 3);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(2)), 2);
  EXPECT_EQ(sut.covisibility(kfId(1), kfId(2)), 1);
  EXPECT_EQ(sut.covisibilityEdges(), 3U);
  EXPECT_EQ(sut.covisible(kfId(1)).size(), 2U);
  EXPECT_EQ(sut.point(ptId(2))->observations.size(), 3U);
  expectConsistent();
}

TEST_F(MapContentTest, AddObservationOfTheSameLinkAgainChangesNothing) {
  addKeyframes(2);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  observe(0, 1, 0);
  observe(1, 2, 0);

  observe(1, 2, 0);

  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);
  EXPECT_EQ(sut.point(ptId(0))->observations.size(), 2U);
  expectConsistent();
}

TEST_F(MapContentTest, AddObservationOfAPointTheKeyframeSeesAtAnotherKeypointIsRefused) {
  addKeyframes(2);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  observe(0, 1, 0);
  observe(1, 1, 0);

  const Status s = sut.addObservation(kfId(1), 2, ptId(0));

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kAlreadyExists);
  EXPECT_THAT(s.error().message(), HasSubstr("at keypoint 1"));
  EXPECT_EQ(sut.keyframe(kfId(1))->has_point[2], 0);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);
  expectConsistent();
}

TEST_F(MapContentTest, AddObservationOnALinkedKeypointMovesItsWeightToTheNewPoint) {
  addKeyframes(3);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  ASSERT_TRUE(sut.addPoint(makePoint(1, 2)).ok());
  observe(0, 0, 0);  // point 0: keyframes 0 and 1
  observe(1, 0, 0);
  observe(2, 0, 1);  // point 1: keyframe 2
  ASSERT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);

  observe(1, 0, 1);  // keyframe 1's keypoint 0 now sees point 1 instead

  EXPECT_EQ(sut.keyframe(kfId(1))->point[0], ptId(1));
  EXPECT_EQ(sut.point(ptId(0))->observations.size(), 1U);
  EXPECT_EQ(sut.point(ptId(1))->observations.size(), 2U);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 0);
  EXPECT_EQ(sut.covisibility(kfId(1), kfId(2)), 1);
  EXPECT_EQ(sut.covisibilityEdges(), 1U);
  expectConsistent();
}

TEST_F(MapContentTest, AddObservationMissingEitherSideIsRefusedAsNotFound) {
  addKeyframes(1);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());

  const Status unknown_keyframe = sut.addObservation(kfId(5), 0, ptId(0));
  const Status unknown_point = sut.addObservation(kfId(0), 0, ptId(5));
  const Status keypoint_out_of_range = sut.addObservation(kfId(0), kKeypointsPerKeyframe, ptId(0));

  ASSERT_FALSE(unknown_keyframe.ok());
  EXPECT_EQ(unknown_keyframe.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(unknown_keyframe.error().message(), HasSubstr("keyframe 3:5"));
  ASSERT_FALSE(unknown_point.ok());
  EXPECT_EQ(unknown_point.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(unknown_point.error().message(), HasSubstr("map point 3:5"));
  ASSERT_FALSE(keypoint_out_of_range.ok());
  EXPECT_EQ(keypoint_out_of_range.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(keypoint_out_of_range.error().message(), HasSubstr("has 20 keypoints"));
  expectConsistent();
}

TEST_F(MapContentTest, MergeMovesEveryObservationOfTheDroppedPointToTheKeptOne) {
  addKeyframes(3);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());  // drop: keyframes 0 and 1
  ASSERT_TRUE(sut.addPoint(makePoint(1, 2)).ok());  // keep: keyframe 2
  observe(0, 0, 0);
  observe(1, 0, 0);
  observe(2, 0, 1);
  ASSERT_EQ(sut.covisibility(kfId(0), kfId(2)), 0);

  ASSERT_TRUE(sut.mergePoints(ptId(0), ptId(1)).ok());

  EXPECT_EQ(sut.point(ptId(0)), nullptr);
  ASSERT_NE(sut.point(ptId(1)), nullptr);
  EXPECT_EQ(sut.point(ptId(1))->observations.size(), 3U);
  EXPECT_EQ(sut.keyframe(kfId(0))->point[0], ptId(1));
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(2)), 1);
  EXPECT_EQ(sut.covisibility(kfId(1), kfId(2)), 1);
  expectConsistent();
}

TEST_F(MapContentTest, MergeWhereAKeyframeObservesBothPointsKeepsOneLink) {
  addKeyframes(3);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());  // drop: keyframe 0 (keypoint 0) and keyframe 1
  ASSERT_TRUE(sut.addPoint(makePoint(1, 0)).ok());  // keep: keyframe 0 (keypoint 1) and keyframe 2
  observe(0, 0, 0);
  observe(1, 4, 0);
  observe(0, 1, 1);
  observe(2, 4, 1);
  ASSERT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);
  ASSERT_EQ(sut.covisibility(kfId(0), kfId(2)), 1);
  ASSERT_EQ(sut.covisibility(kfId(1), kfId(2)), 0);

  ASSERT_TRUE(sut.mergePoints(ptId(0), ptId(1)).ok());

  const ServerKeyframe* kf0 = sut.keyframe(kfId(0));
  EXPECT_EQ(kf0->observationCount(), 1);  // one link to the kept point, not two
  EXPECT_EQ(kf0->has_point[0], 0);
  EXPECT_EQ(kf0->has_point[1], 1);
  EXPECT_EQ(kf0->point[1], ptId(1));
  EXPECT_EQ(sut.point(ptId(1))->observations.size(), 3U);  // keyframes 0, 2 and 1
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(2)), 1);
  EXPECT_EQ(sut.covisibility(kfId(1), kfId(2)), 1);
  expectConsistent();
}

TEST_F(MapContentTest, MergeOfAPointIntoItselfOrAnUnknownPointIsRefused) {
  addKeyframes(1);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());

  const Status into_itself = sut.mergePoints(ptId(0), ptId(0));
  const Status unknown = sut.mergePoints(ptId(0), ptId(8));

  ASSERT_FALSE(into_itself.ok());
  EXPECT_EQ(into_itself.error().code(), ErrorCode::kInvalidArgument);
  ASSERT_FALSE(unknown.ok());
  EXPECT_EQ(unknown.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(unknown.error().message(), HasSubstr("map point 3:8"));
  EXPECT_NE(sut.point(ptId(0)), nullptr);
}

TEST_F(MapContentTest, RemovePointUnlinksItsKeyframesAndDropsItsWeights) {
  addKeyframes(3);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  ASSERT_TRUE(sut.addPoint(makePoint(1, 0)).ok());
  observe(0, 0, 0);
  observe(1, 0, 0);
  observe(2, 0, 0);
  observe(0, 1, 1);
  observe(1, 1, 1);

  ASSERT_TRUE(sut.removePoint(ptId(0)).ok());

  EXPECT_EQ(sut.point(ptId(0)), nullptr);
  EXPECT_EQ(sut.keyframe(kfId(2))->observationCount(), 0);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(1)), 1);
  EXPECT_EQ(sut.covisibility(kfId(0), kfId(2)), 0);
  EXPECT_EQ(sut.covisibility(kfId(1), kfId(2)), 0);
  EXPECT_EQ(sut.covisibilityEdges(), 1U);
  EXPECT_TRUE(sut.covisible(kfId(2)).empty());
  expectConsistent();
}

TEST_F(MapContentTest, RemoveKeyframeMovesThePointReferenceToAnotherObserver) {
  addKeyframes(3);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  observe(0, 0, 0);
  observe(1, 0, 0);
  observe(2, 0, 0);

  ASSERT_TRUE(sut.removeKeyframe(kfId(0)).ok());

  EXPECT_EQ(sut.keyframe(kfId(0)), nullptr);
  ASSERT_NE(sut.point(ptId(0)), nullptr);
  const KeyframeId reference = sut.point(ptId(0))->reference;
  EXPECT_TRUE(reference == kfId(1) || reference == kfId(2)) << reference.toString();
  EXPECT_EQ(sut.point(ptId(0))->observations.size(), 2U);
  EXPECT_EQ(sut.covisibility(kfId(1), kfId(2)), 1);
  EXPECT_EQ(sut.covisibilityEdges(), 1U);
  expectConsistent();
}

TEST_F(MapContentTest, RemoveKeyframeRemovesThePointsNoOtherKeyframeObserves) {
  addKeyframes(2);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());  // seen by keyframe 0 only
  ASSERT_TRUE(sut.addPoint(makePoint(1, 0)).ok());  // seen by both
  observe(0, 0, 0);
  observe(0, 1, 1);
  observe(1, 1, 1);

  ASSERT_TRUE(sut.removeKeyframe(kfId(0)).ok());

  EXPECT_EQ(sut.point(ptId(0)), nullptr);
  ASSERT_NE(sut.point(ptId(1)), nullptr);
  EXPECT_EQ(sut.point(ptId(1))->reference, kfId(1));
  EXPECT_EQ(sut.covisibilityEdges(), 0U);
  expectConsistent();
}

TEST_F(MapContentTest, RemoveKeyframeRemovesAPointLeftWithoutObserversThatAnotherKeyframeReferences) {
  // The point was made by keyframe 0 but only keyframe 1 observes it (keyframe 0's keypoint moved on). With
  // keyframe 1 gone, nothing observes it: "or go when none is left" (map_content.hpp).
  addKeyframes(2);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  observe(1, 0, 0);

  ASSERT_TRUE(sut.removeKeyframe(kfId(1)).ok());

  EXPECT_EQ(sut.point(ptId(0)), nullptr);
  expectConsistent();
}

TEST_F(MapContentTest, RemoveKeyframeRemovesAnUnobservedPointItWasTheReferenceOf) {
  addKeyframes(2);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());  // never observed
  ASSERT_TRUE(sut.addPoint(makePoint(1, 1)).ok());  // never observed, another reference

  ASSERT_TRUE(sut.removeKeyframe(kfId(0)).ok());

  EXPECT_EQ(sut.point(ptId(0)), nullptr);
  EXPECT_NE(sut.point(ptId(1)), nullptr);
  expectConsistent();
}

TEST_F(MapContentTest, RemoveKeyframeDropsTheImuLinkOfTheKeyframeThatFollowedIt) {
  ASSERT_TRUE(sut.addKeyframe(makeKeyframe(0)).ok());
  ServerKeyframe next = makeKeyframe(1);
  next.imu_from = kfId(0);
  next.imu.resize(11);
  next.preintegration.emplace();
  ASSERT_TRUE(sut.addKeyframe(std::move(next)).ok());

  ASSERT_TRUE(sut.removeKeyframe(kfId(0)).ok());

  const ServerKeyframe* held = sut.keyframe(kfId(1));
  ASSERT_NE(held, nullptr);
  EXPECT_FALSE(held->imu_from.has_value());
  EXPECT_FALSE(held->preintegration.has_value());
  EXPECT_TRUE(held->imu.empty());
}

TEST_F(MapContentTest, RemoveOfUnknownIdsIsRefusedAsNotFound) {
  addKeyframes(1);

  const Status keyframe = sut.removeKeyframe(kfId(4));
  const Status point = sut.removePoint(ptId(4));

  ASSERT_FALSE(keyframe.ok());
  EXPECT_EQ(keyframe.error().code(), ErrorCode::kNotFound);
  ASSERT_FALSE(point.ok());
  EXPECT_EQ(point.error().code(), ErrorCode::kNotFound);
  EXPECT_EQ(sut.keyframes().size(), 1U);
}

TEST_F(MapContentTest, CheckConsistencyReportsAWeightThatDisagreesWithTheObservations) {
  // The checker itself must be able to fail: break a link from outside and expect it to notice.
  addKeyframes(2);
  ASSERT_TRUE(sut.addPoint(makePoint(0, 0)).ok());
  observe(0, 0, 0);
  observe(1, 0, 0);
  sut.point(ptId(0))->observations.pop_back();

  const Status s = sut.checkConsistency();

  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code(), ErrorCode::kInternal);
}

// A long seeded sequence of every operation, valid and invalid, on a small map (so that points are shared a
// lot); after each one the map is consistent and every weight equals the recount.
TEST_F(MapContentTest, RandomSequenceOfOperationsKeepsTheMapConsistent) {
  constexpr int kOperations = 3000;
  constexpr std::size_t kMaxKeyframes = 12;
  constexpr std::size_t kMaxPoints = 60;
  std::mt19937 rng(20261123);
  const auto pick = [&](std::size_t n) { return std::uniform_int_distribution<std::size_t>(0, n - 1)(rng); };
  // Mostly a live id (sorted, so the choice does not depend on hash order), sometimes one never used.
  const auto some_keyframe = [&](std::uint32_t next) {
    std::vector<KeyframeId> live;
    for (const auto& [id, kf] : sut.keyframes()) live.push_back(id);
    std::sort(live.begin(), live.end());
    return live.empty() || pick(10) == 0 ? kfId(next + 1) : live[pick(live.size())];
  };
  const auto some_point = [&](std::uint32_t next) {
    std::vector<MapPointId> live;
    for (const auto& [id, p] : sut.points()) live.push_back(id);
    std::sort(live.begin(), live.end());
    return live.empty() || pick(10) == 0 ? ptId(next + 1) : live[pick(live.size())];
  };
  std::uint32_t next_keyframe = 0;
  std::uint32_t next_point = 0;
  std::map<std::string, int> applied;

  for (int i = 0; i < kOperations; ++i) {
    const std::size_t op = pick(100);
    Status s = Error{ErrorCode::kInternal, "not run"};
    std::string name;
    if (op < 6) {
      name = "addKeyframe";
      if (sut.keyframes().size() < kMaxKeyframes) s = sut.addKeyframe(makeKeyframe(next_keyframe++));
    } else if (op < 20) {
      name = "addPoint";
      if (sut.points().size() < kMaxPoints) {
        ServerMapPoint p = makePoint(next_point++, 0);
        p.reference = some_keyframe(next_keyframe);
        s = sut.addPoint(std::move(p));
      }
    } else if (op < 78) {
      name = "addObservation";
      s = sut.addObservation(some_keyframe(next_keyframe), static_cast<std::uint16_t>(pick(kKeypointsPerKeyframe)),
                             some_point(next_point));
    } else if (op < 88) {
      name = "mergePoints";
      s = sut.mergePoints(some_point(next_point), some_point(next_point));
    } else if (op < 95) {
      name = "removePoint";
      s = sut.removePoint(some_point(next_point));
    } else {
      name = "removeKeyframe";
      s = sut.removeKeyframe(some_keyframe(next_keyframe));
    }
    if (s.ok()) ++applied[name];

    const Status consistent = sut.checkConsistency();
    ASSERT_TRUE(consistent.ok()) << "after operation " << i << " (" << name << "): " << consistent.error().toString();
    if (i % 50 == 0) {
      expectCovisibilityEqualsRecount(sut);
      ASSERT_FALSE(HasFailure()) << "after operation " << i << " (" << name << ")";
    }
  }
  expectCovisibilityEqualsRecount(sut);

  // The sequence exercised every operation many times, not just its refusals.
  for (const char* name :
       {"addKeyframe", "addPoint", "addObservation", "mergePoints", "removePoint", "removeKeyframe"}) {
    EXPECT_GE(applied[name], 20) << name;
  }
}

TEST(LatencySamples, GivesNearestRankPercentilesOverTheNewestSamplesOnly) {
  LatencySamples sut;
  EXPECT_EQ(sut.percentile(0.5), 0.0);  // no samples
  for (int i = 1; i <= 100; ++i) sut.add(static_cast<double>(i));
  EXPECT_EQ(sut.percentile(0.5), 50.0);
  EXPECT_EQ(sut.percentile(0.99), 99.0);
  EXPECT_EQ(sut.percentile(1.0), 100.0);
  // A full ring forgets the oldest: after kCapacity samples of 1000, the 100 small ones are gone.
  for (std::size_t i = 0; i < LatencySamples::kCapacity; ++i) sut.add(1000.0);
  EXPECT_EQ(sut.size(), LatencySamples::kCapacity);
  EXPECT_EQ(sut.percentile(0.0), 1000.0);
}

}  // namespace
}  // namespace cvislam::server
