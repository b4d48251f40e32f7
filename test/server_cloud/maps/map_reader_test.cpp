// The map service's read side without gRPC: listings count what the stack holds, GetMap's chunks carry every
// keyframe and point exactly once with their values, within the byte budget, from one moment's copy; the
// trajectory and the exported files agree with the map; unknown names get errors that say what exists.
#include "server_cloud/maps/map_reader.hpp"

#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "cvislam/v1/map_service.pb.h"
#include "server_cloud/maps/map_export.hpp"
#include "test/server_cloud/maps/example_maps.hpp"

namespace cvislam::server::maps {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

class MapReaderTest : public ::testing::Test {
 protected:
  void SetUp() override { test::fillExampleMission(missions_, options_); }

  // Every chunk of map `id`, with the given budget and options.
  std::vector<v1::MapChunk> chunks(MapId id, std::size_t budget, const SnapshotOptions& options = {}) {
    auto snapshot = snapshotMap(missions_, options_.name, id, options);
    EXPECT_TRUE(snapshot.ok()) << snapshot.error().toString();
    auto chunker = MapChunker::create(std::move(snapshot).value(), budget);
    EXPECT_TRUE(chunker.ok()) << chunker.error().toString();
    std::vector<v1::MapChunk> out;
    v1::MapChunk chunk;
    while (chunker->next(chunk)) out.push_back(chunk);
    return out;
  }

  test::ExampleMissionOptions options_;
  MissionRegistry missions_;
};

TEST_F(MapReaderTest, ListMissionsCountsAgentsMapsKeyframesAndPointsOfEveryMission) {
  test::ExampleMissionOptions other = options_;
  other.name = "another";
  other.keyframes_per_agent = 4;
  test::fillExampleMission(missions_, other);

  v1::ListMissionsResponse response;
  listMissions(missions_, response);

  ASSERT_EQ(response.missions_size(), 2);
  const v1::MissionInfo& another = response.missions(0);  // by name
  const v1::MissionInfo& survey = response.missions(1);
  EXPECT_EQ(another.name(), "another");
  EXPECT_EQ(survey.name(), "survey");
  EXPECT_THAT(survey.agents(), ElementsAre(1U, 2U, 3U));
  EXPECT_EQ(survey.maps(), 2U);
  EXPECT_EQ(survey.connected_agents(), 0U);
  // 12 keyframes of agents 1 and 2, 6 of agent 3, 30 new points each.
  EXPECT_EQ(survey.keyframes(), 30U);
  EXPECT_EQ(survey.points(), 30U * 30U);
  EXPECT_EQ(another.keyframes(), 10U);
}

TEST_F(MapReaderTest, ListMapsGivesEachMapsAgentsCountsAndFrame) {
  v1::ListMapsResponse response;
  const Status s = listMaps(missions_, "survey", response);

  ASSERT_TRUE(s.ok()) << s.error().toString();
  ASSERT_EQ(response.maps_size(), 2);
  const v1::MapInfo& shared = response.maps(0);
  EXPECT_EQ(shared.map_id(), 0U);
  EXPECT_THAT(shared.agents(), ElementsAre(1U, 2U));
  EXPECT_EQ(shared.keyframes(), 24U);
  EXPECT_EQ(shared.points(), 24U * 30U);
  // Each keyframe observes its 30 points and the previous keyframe's 30 (the first has none before it).
  EXPECT_EQ(shared.observations(), 24U * 30U + 23U * 30U);
  EXPECT_EQ(shared.refined_keyframes(), 2U * 4U);  // counters 0, 3, 6, 9 of each agent
  EXPECT_EQ(shared.covisibility_edges(), 23U);
  EXPECT_EQ(shared.origin_agent(), 1U);
  EXPECT_EQ(response.maps(1).origin_agent(), 3U);
  EXPECT_THAT(response.maps(1).agents(), ElementsAre(3U));
}

TEST_F(MapReaderTest, UnknownOrMissingMissionNamesAreRefusedNamingNoOtherMission) {
  v1::ListMapsResponse response;

  const Status unknown = listMaps(missions_, "surv", response);
  const Status empty = listMaps(missions_, "", response);
  auto no_map = snapshotMap(missions_, "survey", 9);

  ASSERT_FALSE(unknown.ok());
  EXPECT_EQ(unknown.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(unknown.error().message(), HasSubstr("no mission 'surv'"));
  EXPECT_THAT(unknown.error().message(), ::testing::Not(HasSubstr("survey")));  // no other mission is named
  ASSERT_FALSE(empty.ok());
  EXPECT_EQ(empty.error().code(), ErrorCode::kInvalidArgument);
  ASSERT_FALSE(no_map.ok());
  EXPECT_EQ(no_map.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(no_map.error().message(), HasSubstr("no map 9"));
  EXPECT_THAT(no_map.error().message(), HasSubstr("its maps: 0, 1"));
}

TEST_F(MapReaderTest, AMapMergedAwayIsNotFoundAndSaysItWasMerged) {
  auto mission = missions_.find("survey");
  auto target = mission->stack().find(0);
  auto merged = mission->stack().find(1);
  target->write()->absorb(*merged->write(), geometry::SE3d());
  mission->stack().remove(1);

  auto snapshot = snapshotMap(missions_, "survey", 1);

  ASSERT_FALSE(snapshot.ok());
  EXPECT_THAT(snapshot.error().message(), HasSubstr("merged into another map"));
  EXPECT_THAT(snapshot.error().message(), HasSubstr("its maps: 0"));
}

TEST_F(MapReaderTest, ChunksCarryEveryKeyframeAndPointOnceInIdOrderWithinTheBudget) {
  constexpr std::size_t kBudget = 4096;
  const auto all = chunks(0, kBudget);

  ASSERT_GT(all.size(), 5U);
  EXPECT_TRUE(all.front().has_map());
  EXPECT_EQ(all.front().map().keyframes(), 24U);
  std::vector<KeyframeId> keyframes;
  std::vector<MapPointId> points;
  for (std::size_t i = 0; i < all.size(); ++i) {
    const v1::MapChunk& c = all[i];
    EXPECT_EQ(c.index(), i);
    EXPECT_EQ(c.last(), i + 1 == all.size()) << "chunk " << i;
    if (i > 0) {
      EXPECT_FALSE(c.has_map()) << "chunk " << i;
    }
    EXPECT_LE(c.ByteSizeLong(), kBudget) << "chunk " << i;
    EXPECT_GT(c.keyframes_size() + c.points_size(), 0) << "chunk " << i << " makes no progress";
    for (const auto& kf : c.keyframes()) {
      keyframes.push_back({static_cast<AgentId>(kf.id().agent()), kf.id().counter()});
      EXPECT_TRUE(points.empty()) << "keyframes come before points";
    }
    for (const auto& p : c.points()) points.push_back({static_cast<AgentId>(p.id().agent()), p.id().counter()});
  }
  ASSERT_EQ(keyframes.size(), 24U);
  ASSERT_EQ(points.size(), 24U * 30U);
  EXPECT_TRUE(std::is_sorted(keyframes.begin(), keyframes.end()));
  EXPECT_TRUE(std::is_sorted(points.begin(), points.end()));
  EXPECT_EQ(std::set<KeyframeId>(keyframes.begin(), keyframes.end()).size(), keyframes.size());
  EXPECT_EQ(std::set<MapPointId>(points.begin(), points.end()).size(), points.size());
}

TEST_F(MapReaderTest, TheDefaultBudgetSendsASmallMapInOneChunk) {
  const auto all = chunks(0, 0);

  ASSERT_EQ(all.size(), 1U);
  EXPECT_TRUE(all[0].last());
  EXPECT_EQ(all[0].keyframes_size(), 24);
  EXPECT_EQ(all[0].points_size(), 720);
}

TEST_F(MapReaderTest, AKeyframeLargerThanTheBudgetGoesAloneSoEveryChunkMakesProgress) {
  MissionRegistry big;
  test::ExampleMissionOptions options = options_;
  options.points_per_keyframe = 400;
  options.keypoints_per_keyframe = 800;  // ~400-800 observations, well over 4096 bytes each
  test::fillExampleMission(big, options);
  SnapshotOptions with;
  with.observations = true;
  auto snapshot = snapshotMap(big, "survey", 0, with);
  ASSERT_TRUE(snapshot.ok());
  auto chunker = MapChunker::create(std::move(snapshot).value(), MapChunker::kMinChunkBytes);
  ASSERT_TRUE(chunker.ok());

  v1::MapChunk chunk;
  std::size_t keyframes = 0;
  while (chunker->next(chunk)) {
    if (chunk.keyframes_size() > 0) {
      EXPECT_EQ(chunk.keyframes_size(), 1);
      keyframes += static_cast<std::size_t>(chunk.keyframes_size());
    }
  }
  EXPECT_EQ(keyframes, 24U);
}

TEST_F(MapReaderTest, ABudgetOutsideTheLimitsIsRefusedNamingThem) {
  auto snapshot = snapshotMap(missions_, "survey", 0);
  ASSERT_TRUE(snapshot.ok());

  auto small = MapChunker::create(snapshot.value(), 100);
  auto large = MapChunker::create(snapshot.value(), 8U << 20U);

  ASSERT_FALSE(small.ok());
  EXPECT_EQ(small.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(small.error().message(), HasSubstr("max_chunk_bytes 100 is outside 4096 to"));
  ASSERT_FALSE(large.ok());
  EXPECT_THAT(large.error().message(), HasSubstr("max_chunk_bytes 8388608"));
}

TEST_F(MapReaderTest, KeyframeAndPointValuesAreTheMapsWithObservationsAndDescriptorsWhenAsked) {
  SnapshotOptions with;
  with.observations = true;
  with.descriptors = true;
  const auto all = chunks(0, 0, with);
  ASSERT_EQ(all.size(), 1U);
  auto map = missions_.find("survey")->stack().find(0);
  auto content = map->read();

  for (const v1::MapKeyframe& got : all[0].keyframes()) {
    const ServerKeyframe* kf = content->keyframe({static_cast<AgentId>(got.id().agent()), got.id().counter()});
    ASSERT_NE(kf, nullptr);
    EXPECT_EQ(got.t_ns(), kf->t_ns);
    EXPECT_NEAR(got.t_m_s().px(), kf->T_w_s.translation().x(), 1e-12);
    EXPECT_NEAR(got.t_m_s().qw(), kf->T_w_s.quaternion().w(), 1e-6);
    EXPECT_NEAR(got.v_m().y(), kf->v_w.y(), 1e-12);
    EXPECT_NEAR(got.bias_accel().z(), kf->bias.accel.z(), 1e-12);
    EXPECT_EQ(got.refined(), kf->refined);
    EXPECT_EQ(got.keypoints(), kf->keypoints.size());
    ASSERT_EQ(got.observations_size(), static_cast<int>(got.observed_points()));
    for (const v1::MapObservation& o : got.observations()) {
      ASSERT_LT(o.keypoint(), kf->keypoints.size());
      ASSERT_EQ(kf->has_point[o.keypoint()], 1);
      EXPECT_EQ(kf->point[o.keypoint()], (MapPointId{static_cast<AgentId>(o.point().agent()), o.point().counter()}));
      EXPECT_EQ(o.u(), kf->keypoints[o.keypoint()].px.x());
    }
  }
  for (const v1::MapPointState& got : all[0].points()) {
    const ServerMapPoint* p = content->point({static_cast<AgentId>(got.id().agent()), got.id().counter()});
    ASSERT_NE(p, nullptr);
    EXPECT_EQ(got.p_m().x(), p->p_w.x());
    EXPECT_EQ(got.observations(), p->observations.size());
    ASSERT_EQ(got.orb_descriptor().size(), 32U);
    EXPECT_EQ(static_cast<std::uint8_t>(got.orb_descriptor()[5]), p->descriptor[5]);
  }
}

TEST_F(MapReaderTest, WithoutOptionsNeitherObservationsNorDescriptorsAreSent) {
  const auto all = chunks(0, 0);

  ASSERT_EQ(all.size(), 1U);
  EXPECT_EQ(all[0].keyframes(3).observations_size(), 0);
  EXPECT_GT(all[0].keyframes(3).observed_points(), 0U);
  EXPECT_TRUE(all[0].points(0).orb_descriptor().empty());
}

TEST_F(MapReaderTest, ASnapshotIsOneMomentsMapWhateverIngestAddsAfterIt) {
  auto snapshot = snapshotMap(missions_, "survey", 0);
  ASSERT_TRUE(snapshot.ok());
  {
    auto content = missions_.find("survey")->stack().find(0)->write();
    ServerKeyframe late;
    late.id = KeyframeId{1, 500};
    ASSERT_TRUE(content->addKeyframe(late).ok());
    ASSERT_TRUE(content->removeKeyframe(KeyframeId{2, 0}).ok());
  }
  auto chunker = MapChunker::create(std::move(snapshot).value(), 0);
  ASSERT_TRUE(chunker.ok());

  v1::MapChunk chunk;
  ASSERT_TRUE(chunker->next(chunk));

  EXPECT_EQ(chunk.keyframes_size(), 24);
  EXPECT_EQ(chunk.keyframes(0).id().agent(), 1U);
  bool has_removed = false;
  for (const auto& kf : chunk.keyframes()) has_removed |= kf.id().agent() == 2 && kf.id().counter() == 0;
  EXPECT_TRUE(has_removed);
}

TEST_F(MapReaderTest, TrajectoryIsTheAgentsKeyframesByTimeWithTheirMap) {
  v1::GetTrajectoryResponse response;

  const Status s = getTrajectory(missions_, "survey", 2, response);
  v1::GetTrajectoryResponse none;
  const Status unknown = getTrajectory(missions_, "survey", 9, none);

  ASSERT_TRUE(s.ok()) << s.error().toString();
  ASSERT_EQ(response.poses_size(), 12);
  for (int i = 1; i < response.poses_size(); ++i) EXPECT_LT(response.poses(i - 1).t_ns(), response.poses(i).t_ns());
  EXPECT_EQ(response.poses(0).map_id(), 0U);
  EXPECT_TRUE(response.poses(0).refined());
  EXPECT_FALSE(response.poses(1).refined());
  auto content = missions_.find("survey")->stack().find(0)->read();
  EXPECT_NEAR(response.poses(4).t_m_s().pz(), content->keyframe({2, 4})->T_w_s.translation().z(), 1e-12);
  ASSERT_FALSE(unknown.ok());
  EXPECT_EQ(unknown.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(unknown.error().message(), HasSubstr("agent 9"));
}

TEST_F(MapReaderTest, ExportWritesAPlyATumFilePerAgentAndASummaryThatAgreeWithTheMap) {
  auto snapshots = snapshotMission(missions_, "survey");
  ASSERT_TRUE(snapshots.ok());

  const auto files = exportMaps(snapshots.value());

  std::map<std::string, std::string> by_name;
  for (const auto& f : files) by_name[f.name] = f.data;
  ASSERT_EQ(by_name.size(), 7U);  // map0: ply, 2 TUM, json; map1: ply, 1 TUM, json
  ASSERT_EQ(by_name.count("map0.ply"), 1U);
  ASSERT_EQ(by_name.count("keyframes_agent3_map1.txt"), 1U);

  // PLY: the header's vertex count, then one row per point with its position.
  std::istringstream ply(by_name["map0.ply"]);
  std::string line;
  std::size_t vertices = 0;
  while (std::getline(ply, line) && line != "end_header") {
    if (line.rfind("element vertex ", 0) == 0) vertices = std::stoul(line.substr(15));
  }
  EXPECT_EQ(vertices, 720U);
  const auto& first_point = snapshots.value()[0].points.front();
  double x = 0;
  double y = 0;
  double z = 0;
  unsigned n = 0;
  ply >> x >> y >> z >> n;
  EXPECT_NEAR(x, first_point.p_m.x(), 1e-5);
  EXPECT_NEAR(z, first_point.p_m.z(), 1e-5);
  EXPECT_EQ(n, first_point.observations);
  std::size_t rows = 1;  // the one read above; getline then finishes its line (empty) and reads the rest
  while (std::getline(ply, line)) rows += line.empty() ? 0 : 1;
  EXPECT_EQ(rows, 720U);

  // TUM: agent 1's 12 keyframes by time; the first row is its keyframe 0.
  std::istringstream tum(by_name["keyframes_agent1_map0.txt"]);
  double t = 0;
  double px = 0;
  tum >> t >> px;
  const auto& kf0 = snapshots.value()[0].keyframes.front();
  EXPECT_NEAR(t, static_cast<double>(kf0.t_ns) * 1e-9, 1e-9);
  EXPECT_NEAR(px, kf0.T_m_s.translation().x(), 1e-6);
  std::size_t tum_rows = 0;
  std::istringstream count(by_name["keyframes_agent1_map0.txt"]);
  while (std::getline(count, line)) ++tum_rows;
  EXPECT_EQ(tum_rows, 12U);

  const auto summary = nlohmann::json::parse(by_name["map0.json"]);
  EXPECT_EQ(summary["keyframes"], 24);
  EXPECT_EQ(summary["points"], 720);
  EXPECT_EQ(summary["keyframes_per_agent"]["2"], 12);
  EXPECT_EQ(summary["frame"]["origin_agent"], 1);
  EXPECT_EQ(summary["refined_keyframes"], 8);
}

}  // namespace
}  // namespace cvislam::server::maps
