// The viewer's feed without any network: the first look sends the whole scene, later looks only what changed (a
// moved keyframe and the ones linked to it, a removed one as a deletion, a live pose in its map's frame), point
// clouds stay within their budget with a stable subset, events become log lines, and a late client's full state
// holds every keyframe.
#include "server_cloud/viewer/mission_feed.hpp"

#include <map>
#include <set>
#include <string>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/mcap/reader.hpp"
#include "server_cloud/stack/map_stack.hpp"
#include "server_cloud/viewer/viewer_publisher.hpp"
#include "test/server_cloud/maps/example_maps.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server::viewer {
namespace {

using nlohmann::json;
using ::testing::HasSubstr;

class MissionFeedTest : public ::testing::Test {
 protected:
  void SetUp() override {
    test::fillExampleMission(missions_, example_);
    mission_ = missions_.find(example_.name);
    ASSERT_NE(mission_, nullptr);
    // The agents' records say which server map holds each agent map, as ingest keeps them.
    for (auto [agent, map] : {std::pair<AgentId, MapId>{1, 0}, {2, 0}, {3, 1}}) {
      mission_->agent(agent)->write()->agent_maps[0].map = map;
    }
    options_.max_points_per_map = 50;
    options_.points_period_s = 0.0;
  }

  // One look; the messages by topic.
  std::multimap<std::string, json> look(MissionFeed& feed) {
    std::vector<FeedMessage> out;
    now_ += std::chrono::seconds(2);
    feed.update(*mission_, t_ns_ += 1'000'000'000, now_, out);
    return byTopic(feed, out);
  }
  static std::multimap<std::string, json> byTopic(const MissionFeed& feed, const std::vector<FeedMessage>& messages) {
    std::multimap<std::string, json> out;
    for (const FeedMessage& m : messages) {
      EXPECT_LT(m.channel, feed.channels().size());
      out.emplace(feed.channels()[m.channel].topic, json::parse(m.payload));
    }
    return out;
  }
  std::size_t keyframesHeld() const {
    std::size_t n = 0;
    for (const auto& map : mission_->stack().maps()) n += map->read()->keyframes().size();
    return n;
  }
  static std::set<std::string> entityIds(const json& scene) {
    std::set<std::string> ids;
    for (const json& e : scene["entities"]) ids.insert(e["id"].get<std::string>());
    return ids;
  }

  test::ExampleMissionOptions example_;
  MissionRegistry missions_;
  std::shared_ptr<Mission> mission_;
  FeedOptions options_;
  std::int64_t t_ns_ = 1'700'000'000'000'000'000;
  MissionFeed::Clock::time_point now_ = MissionFeed::Clock::now();
};

TEST_F(MissionFeedTest, TheFirstLookSendsTheWholeSceneOnTheMissionsChannels) {
  MissionFeed feed(example_.name, options_);
  const auto first = look(feed);
  ASSERT_EQ(first.count("/survey/keyframes"), 1U);
  const json& scene = first.find("/survey/keyframes")->second;
  EXPECT_EQ(scene["entities"].size(), keyframesHeld());
  EXPECT_TRUE(scene["deletions"].empty());
  // Each entity is in its map's frame, with the agent's colour on its cube, and linked to older keyframes.
  std::size_t with_lines = 0;
  for (const json& e : scene["entities"]) {
    EXPECT_THAT(e["frame_id"].get<std::string>(), ::testing::StartsWith("survey/map"));
    ASSERT_EQ(e["cubes"].size(), 1U);
    with_lines += e["lines"].empty() ? 0 : 1;
  }
  EXPECT_GT(with_lines, scene["entities"].size() / 2);
  // One point cloud per map, each within the budget, and one trajectory per agent.
  for (const auto& map : mission_->stack().maps()) {
    const std::string topic = "/survey/map" + std::to_string(map->id()) + "/points";
    ASSERT_EQ(first.count(topic), 1U) << topic;
    const json& cloud = first.find(topic)->second;
    const std::size_t points = cloud["data"].get<std::string>().size() / 4 * 3 / 12;
    EXPECT_GT(points, 0U);
    EXPECT_LE(points, options_.max_points_per_map);
  }
  for (int agent : {1, 2, 3}) {
    EXPECT_EQ(first.count("/survey/agent" + std::to_string(agent) + "/trajectory"), 1U) << agent;
  }
  EXPECT_EQ(first.count("/survey/stats"), 1U);
  EXPECT_GE(first.count("/survey/tf"), 3U);  // every agent map's world frame
}

TEST_F(MissionFeedTest, ALaterLookSendsOnlyWhatMovedOrWent) {
  MissionFeed feed(example_.name, options_);
  (void)look(feed);
  const auto idle = look(feed);
  EXPECT_EQ(idle.count("/survey/keyframes"), 0U) << "nothing changed, nothing is sent";
  EXPECT_EQ(idle.count("/survey/map0/points"), 0U);
  EXPECT_EQ(idle.count("/survey/agent1/trajectory"), 0U);

  // Move one keyframe of map 0 by 5 cm: it goes again, with the keyframes whose lines end at it, and nothing else.
  auto map = mission_->stack().find(0);
  KeyframeId moved;
  {
    auto content = map->write();
    moved = content->keyframes().begin()->first;
    content->keyframe(moved)->T_w_s.translation().x() += 0.05;
  }
  const auto after_move = look(feed);
  ASSERT_EQ(after_move.count("/survey/keyframes"), 1U);
  const std::set<std::string> sent = entityIds(after_move.find("/survey/keyframes")->second);
  EXPECT_EQ(sent.count(keyframeEntityId(moved)), 1U);
  EXPECT_LT(sent.size(), map->read()->keyframes().size() / 2);
  EXPECT_EQ(after_move.count("/survey/map0/points"), 1U) << "the map's keyframes moved: its cloud goes again";
  EXPECT_EQ(after_move.count("/survey/map1/points"), 0U);

  // Remove a keyframe: a deletion of its entity.
  KeyframeId removed;
  {
    auto content = map->write();
    removed = content->keyframes().begin()->first;
    ASSERT_TRUE(content->removeKeyframe(removed).ok());
  }
  const auto after_removal = look(feed);
  ASSERT_EQ(after_removal.count("/survey/keyframes"), 1U);
  const json& deletions = after_removal.find("/survey/keyframes")->second["deletions"];
  ASSERT_EQ(deletions.size(), 1U);
  EXPECT_EQ(deletions[0]["id"], keyframeEntityId(removed));
}

// A keyframe's links (a walk of its covisibility under the map's read lock) are looked up at its first look, then
// once in every links_every_looks looks, the keyframes staggered over them; at once when one of its links went.
TEST_F(MissionFeedTest, LinksAreLookedUpAtFirstThenOnceEveryFewLooksStaggeredAndAtOnceWhenALinkWent) {
  options_.links_every_looks = 4;
  MissionFeed feed(example_.name, options_);
  (void)look(feed);
  const std::uint64_t n = keyframesHeld();
  ASSERT_GT(n, 8U);
  EXPECT_EQ(feed.linkLookups(), n) << "every keyframe's at the first look";
  std::uint64_t most_in_one_look = 0;
  for (int i = 0; i < 4; ++i) {
    const std::uint64_t before = feed.linkLookups();
    (void)look(feed);
    most_in_one_look = std::max(most_in_one_look, feed.linkLookups() - before);
  }
  EXPECT_EQ(feed.linkLookups(), 2 * n) << "each keyframe once more over four looks";
  EXPECT_LE(most_in_one_look, n / 2) << "staggered over the looks, not all at one";

  options_.links_every_looks = 1000;  // no keyframe's turn comes in this test
  MissionFeed rare(example_.name, options_);
  (void)look(rare);
  (void)look(rare);
  EXPECT_EQ(rare.linkLookups(), n);
  // The oldest keyframe of map 0 is its successor's IMU link: removed, the successor is looked up at once.
  auto map = mission_->stack().find(0);
  {
    auto content = map->write();
    KeyframeId oldest = content->keyframes().begin()->first;
    for (const auto& [id, kf] : content->keyframes()) oldest = std::min(oldest, id);
    ASSERT_TRUE(content->removeKeyframe(oldest).ok());
  }
  (void)look(rare);
  EXPECT_GT(rare.linkLookups(), n);
  EXPECT_LT(rare.linkLookups(), n + n / 2) << "only the keyframes linked to it";

  FeedOptions bad = options_;
  bad.links_every_looks = 0;
  EXPECT_THAT(bad.validate().error().message(), HasSubstr("links every looks"));
}

TEST_F(MissionFeedTest, ATrajectoryGoesAtMostOncePerPeriod) {
  options_.trajectory_period_s = 5.0;
  MissionFeed feed(example_.name, options_);
  ASSERT_EQ(look(feed).count("/survey/agent3/trajectory"), 1U);
  {
    auto content = mission_->stack().find(1)->write();
    content->keyframe(content->keyframes().begin()->first)->T_w_s.translation().y() += 0.05;
  }
  EXPECT_EQ(look(feed).count("/survey/agent3/trajectory"), 0U) << "2 s after the last";
  EXPECT_EQ(look(feed).count("/survey/agent3/trajectory"), 0U) << "4 s after";
  EXPECT_EQ(look(feed).count("/survey/agent3/trajectory"), 1U) << "6 s after: the change goes";
}

TEST_F(MissionFeedTest, TheLivePoseGoesInItsServerMapsFrameOncePerPose) {
  MissionFeed feed(example_.name, options_);
  const geometry::SE3d T_m_w(Eigen::Quaterniond(Eigen::AngleAxisd(0.5, Eigen::Vector3d::UnitZ())),
                             Eigen::Vector3d(1.0, 2.0, 0.5));
  const geometry::SE3d T_w_s(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.3, 0.0, 0.0));
  {
    auto record = mission_->agent(1)->write();
    record->agent_maps[0].T_m_w = T_m_w;
    record->live_pose = AgentRecord::LivePose{42, 0, T_w_s, true};
  }
  const auto first = look(feed);
  ASSERT_EQ(first.count("/survey/agent1/pose"), 1U);
  const json& pose = first.find("/survey/agent1/pose")->second;
  EXPECT_EQ(pose["frame_id"], "survey/map0");
  const Eigen::Vector3d expected = (T_m_w * T_w_s).translation();
  EXPECT_NEAR(pose["pose"]["position"]["x"].get<double>(), expected.x(), 1e-6);  // floats in the JSON
  EXPECT_NEAR(pose["pose"]["position"]["y"].get<double>(), expected.y(), 1e-6);
  EXPECT_EQ(first.count("/survey/agent2/pose"), 0U) << "agent 2 sent no pose";
  EXPECT_EQ(look(feed).count("/survey/agent1/pose"), 0U) << "the same pose is not sent twice";
  mission_->agent(1)->write()->live_pose->t_ns = 43;
  EXPECT_EQ(look(feed).count("/survey/agent1/pose"), 1U);
}

TEST_F(MissionFeedTest, PointCloudsKeepTheSameSubsetWithinTheirBudget) {
  MissionFeed a(example_.name, options_);
  MissionFeed b(example_.name, options_);
  const auto first = look(a);
  const auto second = look(b);
  EXPECT_EQ(first.find("/survey/map0/points")->second["data"], second.find("/survey/map0/points")->second["data"]);
  options_.max_points_per_map = 0;
  MissionFeed none(example_.name, options_);
  EXPECT_TRUE(look(none).find("/survey/map0/points")->second["data"].get<std::string>().empty());
}

TEST_F(MissionFeedTest, EventsBecomeLogLinesAndRemovalsAreSummed) {
  MissionFeed feed(example_.name, options_);
  (void)look(feed);
  MissionEvent merged;
  merged.kind = MissionEvent::Kind::kMapsMerged;
  merged.map = 0;
  merged.from_map = 1;
  mission_->events().append(merged);
  for (int i = 0; i < 3; ++i) {
    MissionEvent removed;
    removed.kind = MissionEvent::Kind::kKeyframeRemoved;
    removed.agent = 2;
    removed.cause = "redundant";
    mission_->events().append(removed);
  }
  const auto out = look(feed);
  std::vector<std::string> lines;
  for (auto [it, end] = out.equal_range("/survey/events"); it != end; ++it) lines.push_back(it->second["message"]);
  EXPECT_THAT(lines, ::testing::Contains(HasSubstr("map 1 merged into map 0")));
  EXPECT_THAT(lines, ::testing::Contains(HasSubstr("agent 2: 3 keyframes removed (redundant)")));
}

TEST_F(MissionFeedTest, TheFullStateHoldsEveryKeyframeAndTheNewestOfEachChannel) {
  MissionFeed feed(example_.name, options_);
  (void)look(feed);
  {
    auto content = mission_->stack().find(0)->write();
    content->keyframe(content->keyframes().begin()->first)->T_w_s.translation().z() += 0.1;
  }
  (void)look(feed);
  std::vector<FeedMessage> full;
  feed.fullState(full);
  const auto by_topic = byTopic(feed, full);
  ASSERT_EQ(by_topic.count("/survey/keyframes"), 1U);
  EXPECT_EQ(by_topic.find("/survey/keyframes")->second["entities"].size(), keyframesHeld());
  EXPECT_EQ(by_topic.count("/survey/map0/points"), 1U);
  EXPECT_EQ(by_topic.count("/survey/agent3/trajectory"), 1U);
  EXPECT_EQ(by_topic.count("/survey/stats"), 1U);
}

TEST_F(MissionFeedTest, TheRecordingHoldsTheSceneAndARestartDoesNotOverwriteIt) {
  const test::TempDir dir;
  PublisherOptions options;
  options.record_dir = dir.path() / "recordings";
  options.period_s = 60.0;  // the test looks itself
  for (int server_run = 0; server_run < 2; ++server_run) {
    auto publisher = ViewerPublisher::start(missions_, nullptr, options);
    ASSERT_TRUE(publisher.ok()) << publisher.error().toString();
    (*publisher)->step();
    ASSERT_TRUE((*publisher)->finish().ok());
  }
  for (const char* name : {"survey.mcap", "survey.1.mcap"}) {
    auto reader = mcap::Reader::open(options.record_dir / name);
    ASSERT_TRUE(reader.ok()) << name << ": " << reader.error().toString();
    std::set<std::string> topics;
    mcap::MessageView view;
    for (auto more = reader->next(view); more.ok() && *more; more = reader->next(view)) {
      topics.insert(view.channel->topic);
    }
    EXPECT_EQ(topics.count("/survey/keyframes"), 1U) << name;
    EXPECT_EQ(topics.count("/survey/map1/points"), 1U) << name;
  }
}

TEST(FeedOptionsTest, BadValuesAreRefusedWithTheirName) {
  FeedOptions options;
  options.moved_m = -1.0;
  EXPECT_THAT(options.validate().error().message(), HasSubstr("move thresholds"));
  options = {};
  options.covisible_links = 1000;
  EXPECT_THAT(options.validate().error().message(), HasSubstr("covisible links"));
}

}  // namespace
}  // namespace cvislam::server::viewer
