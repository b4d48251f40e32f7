// Verification of place-recognition candidates on rendered simulator views with the shipped vocabulary: a true
// revisit from another agent's map (in another frame) is found through the database and verified with the right
// transform; a near miss (the same corridor, another place), a mirror-like place and a map tilted by 20 degrees
// of roll are rejected, each for its own reason.
#include "server_cloud/recognition/place_recognition.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <tuple>
#include <unordered_set>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/euroc_calibration.hpp"
#include "common/features/vocabulary.hpp"
#include "common/geometry/alignment.hpp"
#include "test/server_cloud/recognition/synthetic_keyframes.hpp"
#include "test/sim/presets.hpp"

namespace cvislam::server::recognition {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;

geometry::SE3d yawAndShift(double yaw_deg, const Eigen::Vector3d& t) {
  return geometry::SE3d(geometry::rotationAboutZ(yaw_deg * kDeg), t);
}

class PlaceRecognitionTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    Result<features::Vocabulary> vocabulary = features::Vocabulary::load(CVISLAM_VOCABULARY_FILE);
    ASSERT_TRUE(vocabulary.ok()) << vocabulary.error().message();
    vocabulary_ = std::make_unique<features::Vocabulary>(std::move(vocabulary).value());
    Result<sim::MissionPlan> plan = sim::planPreset("loop", 1, 60.0);
    ASSERT_TRUE(plan.ok()) << plan.error().message();
    plan_ = std::make_unique<sim::MissionPlan>(std::move(plan).value());
    sim::WorldOptions world_options;
    world_options.seed = 1;
    world_ = std::make_unique<sim::World>(plan_->layout, world_options);
  }
  static void TearDownTestSuite() {
    world_.reset();
    plan_.reset();
    vocabulary_.reset();
  }

  void SetUp() override {
    Result<test::ViewMaker> maker = test::ViewMaker::create(dataset::eurocCam0());
    ASSERT_TRUE(maker.ok()) << maker.error().message();
    maker_ = std::make_unique<test::ViewMaker>(std::move(maker).value());
    camera_ = std::make_unique<AgentCamera>(AgentCamera{maker_->camera(), maker_->T_s_c()});
  }

  // The body pose of the loop agent at t_s, moved by `offset` (in the body frame).
  [[nodiscard]] geometry::SE3d pose(double t_s, const geometry::SE3d& offset = {}) const {
    return plan_->agents[0].trajectory.state(t_s).T_w_b * offset;
  }

  // Builds a map of `agent` from views at the given poses, each moved into the map by E_map_w.
  void buildMap(MapContent& map, AgentId agent, const std::vector<geometry::SE3d>& poses, const geometry::SE3d& E_map_w,
                bool mirror = false) {
    test::SyntheticMap builder(map, *world_, agent, test::SyntheticMapOptions{});
    for (const geometry::SE3d& T_w_s : poses) {
      const test::SyntheticView view = maker_->render(*world_, T_w_s, mirror);
      Result<KeyframeId> id = builder.add(view, E_map_w);
      ASSERT_TRUE(id.ok()) << id.error().message();
      features::BowVector bow;
      features::FeatureVector fv;
      vocabulary_->transform(map.keyframe(*id)->descriptors, bow, &fv, options_.direct_level);
      ASSERT_TRUE(database_.add(*id, map.id(), std::move(bow), std::move(fv)).ok());
    }
  }

  [[nodiscard]] CameraLookup cameras() const {
    return [this](AgentId) { return camera_.get(); };
  }

  Verification verify(const MapContent& a, const KeyframeId& q, const MapContent& b, const KeyframeId& c) const {
    const double score = features::bowScore(database_.find(q)->bow, database_.find(c)->bow);
    return verifyCandidate(database_, a, q, b, c, score, cameras(), options_);
  }

  static std::unique_ptr<features::Vocabulary> vocabulary_;
  static std::unique_ptr<sim::MissionPlan> plan_;
  static std::unique_ptr<sim::World> world_;
  std::unique_ptr<test::ViewMaker> maker_;
  std::unique_ptr<AgentCamera> camera_;
  RecognitionOptions options_;
  KeyframeDatabase database_{1'000'000};
};

std::unique_ptr<features::Vocabulary> PlaceRecognitionTest::vocabulary_;
std::unique_ptr<sim::MissionPlan> PlaceRecognitionTest::plan_;
std::unique_ptr<sim::World> PlaceRecognitionTest::world_;

// Map A (agent 0) is the simulator's frame; map B (agent 1) sits 40 deg of yaw and a few metres away.
const geometry::SE3d kE_b_w = yawAndShift(40.0, Eigen::Vector3d(3.0, -2.0, 0.5));

TEST_F(PlaceRecognitionTest, FindsAndVerifiesATrueRevisitInAnotherMap) {
  ASSERT_TRUE(options_.validate().ok());
  MapContent a(0);
  MapContent b(1);
  // B flies past the place; A comes back to it 0.3 m to the side and turned by 8 deg.
  buildMap(b, 1, {pose(14.0), pose(14.5), pose(15.0), pose(15.5)}, kE_b_w);
  const geometry::SE3d offset = yawAndShift(0.0, Eigen::Vector3d(0.0, 0.3, 0.0)) *
                                geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(8.0 * kDeg, 0.0, 0.0)),
                                               Eigen::Vector3d::Zero());  // body x is up: a turn about it
  buildMap(a, 0, {pose(14.6, offset), pose(15.1, offset)}, geometry::SE3d());
  const KeyframeId query{0, 1};

  const MapLookup maps = [&](MapId id) -> const MapContent* { return id == 0 ? &a : id == 1 ? &b : nullptr; };
  Result<RecognitionResult> result = recognize(database_, a, query, QueryKind::kMapMatch, maps, cameras(), options_);
  ASSERT_TRUE(result.ok()) << result.error().message();
  ASSERT_FALSE(result->search.candidates.empty());
  ASSERT_TRUE(result->best.has_value()) << (result->verifications.empty() ? "" : result->verifications[0].detail);
  const VerifiedMatch& m = *result->best;
  EXPECT_EQ(m.candidate_map, 1U);
  EXPECT_GE(m.inliers, options_.min_inliers);
  EXPECT_LT(m.tilt_deg, 1.0);
  // The true transform from B into A is the inverse of B's frame offset.
  const geometry::SE3d error = m.T_qmap_cmap * kE_b_w;
  EXPECT_LT(error.translation().norm(), 0.10) << error.translation().transpose();
  EXPECT_LT(error.so3().log().norm() / kDeg, 1.0);
  EXPECT_GE(m.point_pairs.size(), 0U);
  // Loop detection inside A has nothing to find: A's only other keyframe is covisible with the query.
  Result<RecognitionResult> loop = recognize(database_, a, query, QueryKind::kLoop, maps, cameras(), options_);
  ASSERT_TRUE(loop.ok());
  EXPECT_FALSE(loop->best.has_value());
}

// The server verifies on copies taken under short locks: once copied, the maps may change or go, and the
// verification still gives, to the last inlier, what verifying on the maps gave.
TEST_F(PlaceRecognitionTest, AVerificationNeedsNothingOfTheMapsOnceTheyAreCopied) {
  options_.guided_neighbours = 3;  // fewer than B's other keyframes: the copy is a strict part of B
  MapContent a(0);
  MapContent b(1);
  buildMap(b, 1, {pose(13.0), pose(13.5), pose(14.0), pose(14.5), pose(15.0), pose(15.5), pose(16.0), pose(16.5)},
           kE_b_w);
  buildMap(a, 0, {pose(14.6), pose(15.1)}, geometry::SE3d());
  const KeyframeId query{0, 1};
  const KeyframeId candidate{1, 4};
  const Verification whole = verify(a, query, b, candidate);
  ASSERT_TRUE(whole.accepted()) << whole.detail;

  VerificationInput input;
  ASSERT_TRUE(copyQuery(a, query, input).ok());
  ASSERT_TRUE(copyCandidate(b, candidate, options_, input).ok());
  EXPECT_EQ(input.query_map, 0U);
  EXPECT_EQ(input.candidate_map, 1U);
  EXPECT_LT(input.points.size(), b.points().size()) << "the neighbourhood, not the map";
  // The guided search's points, worked out here from the map: the candidate's, then those of its three most
  // covisible keyframes (most shared points first, ties by id), each once, in that order.
  std::vector<std::pair<int, KeyframeId>> ranked;
  for (const auto& [n, shared] : b.covisible(candidate)) ranked.emplace_back(shared, n);
  std::sort(ranked.begin(), ranked.end(),
            [](const auto& x, const auto& y) { return x.first != y.first ? x.first > y.first : x.second < y.second; });
  ASSERT_GT(ranked.size(), 3U);
  std::vector<KeyframeId> neighbourhood{candidate};
  for (std::size_t i = 0; i < 3; ++i) neighbourhood.push_back(ranked[i].second);
  std::vector<MapPointId> expected;
  std::unordered_set<MapPointId> seen;
  for (const KeyframeId& id : neighbourhood) {
    const ServerKeyframe& kf = *b.keyframe(id);
    for (std::size_t k = 0; k < kf.point.size(); ++k) {
      if (kf.has_point[k] != 0 && seen.insert(kf.point[k]).second) expected.push_back(kf.point[k]);
    }
  }
  std::vector<MapPointId> copied_ids;
  for (const VerificationInput::Point& p : input.points) copied_ids.push_back(p.id);
  EXPECT_EQ(copied_ids, expected);
  // Every keypoint link of both keyframes leads to the point the map links it to.
  for (const auto& [kf, points, map] :
       {std::tuple{&input.query, &input.query_points, &a}, std::tuple{&input.candidate, &input.points, &b}}) {
    const ServerKeyframe& held = *map->keyframe(kf->id);
    ASSERT_EQ(kf->point.size(), held.keypoints.size());
    for (std::size_t k = 0; k < kf->point.size(); ++k) {
      ASSERT_EQ(kf->point[k] >= 0, held.has_point[k] != 0) << k;
      if (kf->point[k] < 0) continue;
      const VerificationInput::Point& p = (*points)[static_cast<std::size_t>(kf->point[k])];
      EXPECT_EQ(p.id, held.point[k]);
      EXPECT_EQ(p.p_w, map->point(p.id)->p_w);
    }
  }
  a = MapContent(0);
  b = MapContent(1);
  const double score = features::bowScore(database_.find(query)->bow, database_.find(candidate)->bow);
  const Verification copied = verifyCopied(database_, input, score, cameras(), options_);
  ASSERT_TRUE(copied.accepted()) << copied.detail;
  EXPECT_EQ(copied.match->matches, whole.match->matches);
  EXPECT_EQ(copied.match->ransac_inliers, whole.match->ransac_inliers);
  EXPECT_EQ(copied.match->inliers, whole.match->inliers);
  EXPECT_EQ(copied.match->keypoint_matches, whole.match->keypoint_matches);
  EXPECT_EQ(copied.match->point_pairs, whole.match->point_pairs);
  EXPECT_EQ(copied.match->scale, whole.match->scale);
  const geometry::SE3d difference = whole.match->T_qmap_cmap.inverse() * copied.match->T_qmap_cmap;
  EXPECT_LT(difference.log().norm(), 1e-12);
  // A keyframe gone before its copy is a missing candidate, named.
  EXPECT_EQ(copyCandidate(b, candidate, options_, input).error().code(), ErrorCode::kNotFound);
  EXPECT_NE(copyQuery(a, query, input).error().message().find(query.toString()), std::string::npos);
}

TEST_F(PlaceRecognitionTest, RejectsANearMissInTheSameCorridor) {
  MapContent a(0);
  MapContent b(1);
  buildMap(b, 1, {pose(14.0), pose(14.5), pose(15.0)}, kE_b_w);
  // The same ring corridor, 3 s (about 3 m) further on, looking the same way.
  buildMap(a, 0, {pose(18.0), pose(18.5)}, geometry::SE3d());
  const Verification v = verify(a, KeyframeId{0, 1}, b, KeyframeId{1, 1});
  EXPECT_FALSE(v.accepted()) << v.detail;
  EXPECT_NE(v.rejection, Rejection::kMissing) << v.detail;
}

TEST_F(PlaceRecognitionTest, RejectsAMirrorLikePlace) {
  MapContent a(0);
  MapContent b(1);
  buildMap(b, 1, {pose(14.0), pose(14.5), pose(15.0)}, kE_b_w, /*mirror=*/true);
  buildMap(a, 0, {pose(14.5), pose(15.0)}, geometry::SE3d());
  const Verification v = verify(a, KeyframeId{0, 0}, b, KeyframeId{1, 1});
  EXPECT_FALSE(v.accepted()) << v.detail;
  EXPECT_NE(v.rejection, Rejection::kMissing) << v.detail;
  // The same place unmirrored is accepted, so the rejection is the mirror's doing.
  MapContent c(2);
  buildMap(c, 2, {pose(14.0), pose(14.5), pose(15.0)}, kE_b_w);
  const Verification same = verify(a, KeyframeId{0, 0}, c, KeyframeId{2, 1});
  EXPECT_TRUE(same.accepted()) << same.detail;
}

TEST_F(PlaceRecognitionTest, RejectsATransformWithTwentyDegreesOfRoll) {
  MapContent a(0);
  MapContent b(1);
  // B's frame is not gravity-aligned with A's: 20 deg of roll about the world's x axis.
  const geometry::SE3d E_b_w =
      geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(20.0 * kDeg, 0.0, 0.0)), Eigen::Vector3d(1.0, 2.0, 0.0)) *
      kE_b_w;
  buildMap(b, 1, {pose(14.0), pose(14.5), pose(15.0)}, E_b_w);
  buildMap(a, 0, {pose(14.5), pose(15.0)}, geometry::SE3d());
  const Verification v = verify(a, KeyframeId{0, 0}, b, KeyframeId{1, 1});
  ASSERT_EQ(v.rejection, Rejection::kTilted) << v.detail;
  ASSERT_TRUE(v.match.has_value());
  EXPECT_NEAR(v.match->tilt_deg, 20.0, 1.0);
  // Geometrically it is a good match: with the gravity check relaxed it is accepted.
  options_.max_tilt_deg = 30.0;
  EXPECT_TRUE(verify(a, KeyframeId{0, 0}, b, KeyframeId{1, 1}).accepted());
}

TEST_F(PlaceRecognitionTest, OptionsNameTheBadField) {
  RecognitionOptions o;
  o.min_inliers = 3;
  const Status s = o.validate();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message().find("min_inliers"), std::string::npos);
  o = RecognitionOptions{};
  o.max_tilt_deg = 0.0;
  EXPECT_NE(o.validate().error().message().find("max_tilt_deg"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::server::recognition
