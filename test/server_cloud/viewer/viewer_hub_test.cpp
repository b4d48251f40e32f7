// The Foxglove protocol's hub without sockets: who gets in, what each client is told of, subscriptions and their
// frames, the bounded queue of a client that does not read, and hostile client messages.
#include "server_cloud/viewer/viewer_hub.hpp"

#include <string>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/mcap/reader.hpp"
#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/viewer/mcap_recorder.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server::viewer {
namespace {

using nlohmann::json;
using ::testing::HasSubstr;

MissionTokens tokensFor() {
  auto tokens = MissionTokens::parse("survey 0123456789abcdef0123\n* ffffffffffffffffffffffff\n", "test tokens");
  EXPECT_TRUE(tokens.ok());
  return *tokens;
}

std::vector<FeedChannel> channels() {
  return {{"/survey/events", kLogSchema}, {"/survey/agent1/pose", kPoseInFrameSchema}};
}

// A client of mission "survey" subscribed (as subscription 1) to its events channel, its catch-up taken.
ViewerHub::ClientId subscribedToEvents(ViewerHub& hub) {
  hub.registerChannels("survey", channels());
  const auto client = hub.open({false, "survey"});
  EXPECT_TRUE(hub.onText(client, R"({"op":"subscribe","subscriptions":[{"id":1,"channelId":1}]})").ok());
  (void)hub.takeCatchUps();  // the subscription's own
  return client;
}

// Every frame waiting for the client.
std::vector<ViewerHub::Frame> drain(ViewerHub& hub, ViewerHub::ClientId client) {
  std::vector<ViewerHub::Frame> frames;
  ViewerHub::Frame f;
  while (hub.pop(client, f)) frames.push_back(f);
  return frames;
}

TEST(ViewerAccess, TheMissionsTokenOpensItAndNothingElseDoes) {
  const MissionTokens tokens = tokensFor();
  EXPECT_TRUE(admitViewer(tokens, "Bearer 0123456789abcdef0123", "mission=survey").ok());
  EXPECT_TRUE(admitViewer(tokens, "", "mission=survey&token=0123456789abcdef0123").ok());
  EXPECT_TRUE(admitViewer(tokens, "", "mission=survey&token=ffffffffffffffffffffffff").ok()) << "the operator's";
  const auto wrong = admitViewer(tokens, "", "mission=survey&token=0123456789abcdef0124");
  ASSERT_FALSE(wrong.ok());
  EXPECT_EQ(wrong.error().code(), ErrorCode::kUnauthenticated);
  EXPECT_THAT(wrong.error().message(), ::testing::Not(HasSubstr("0123456789abcdef0124")));
  EXPECT_FALSE(admitViewer(tokens, "", "mission=other&token=0123456789abcdef0123").ok());
  EXPECT_FALSE(admitViewer(tokens, "", "mission=survey").ok()) << "no token";
  const auto unnamed = admitViewer(tokens, "Bearer 0123456789abcdef0123", "");
  ASSERT_FALSE(unnamed.ok());
  EXPECT_THAT(unnamed.error().message(), HasSubstr("?mission=NAME"));
  // Without tokens, naming no mission sees them all.
  const auto open = admitViewer(MissionTokens(), "", "");
  ASSERT_TRUE(open.ok());
  EXPECT_TRUE(open->every_mission);
  EXPECT_EQ(queryParameter("a=1&mission=s%20x+y&token=t", "mission"), "s x y");
}

TEST(ViewerHubTest, AClientIsToldOfItsMissionsChannelsAndGetsWhatItSubscribedTo) {
  ViewerHub hub;
  hub.registerChannels("survey", channels());
  hub.registerChannels("other", {{"/other/events", kLogSchema}});
  const auto client = hub.open({false, "survey"});
  auto frames = drain(hub, client);
  ASSERT_EQ(frames.size(), 2U);
  const json info = json::parse(frames[0].bytes);
  EXPECT_EQ(info["op"], "serverInfo");
  EXPECT_THAT(info["supportedEncodings"], ::testing::Contains("json"));
  const json advertised = json::parse(frames[1].bytes);
  ASSERT_EQ(advertised["op"], "advertise");
  ASSERT_EQ(advertised["channels"].size(), 2U) << "not the other mission's";
  for (const json& c : advertised["channels"]) {
    EXPECT_EQ(c["encoding"], "json");
    EXPECT_FALSE(json::parse(c["schema"].get<std::string>()).empty());
  }
  const auto pose_channel = advertised["channels"][1]["id"].get<std::uint32_t>();

  ASSERT_TRUE(hub.onText(client, R"({"op":"subscribe","subscriptions":[{"id":7,"channelId":)" +
                                     std::to_string(pose_channel) + "}]}")
                  .ok());
  hub.publish("survey", {{0, 5, "{\"event\":1}"}, {1, 0x0102030405060708LL, "{\"pose\":1}"}});
  frames = drain(hub, client);
  ASSERT_EQ(frames.size(), 1U) << "only the subscribed channel";
  ASSERT_TRUE(frames[0].binary);
  const std::string& f = frames[0].bytes;
  EXPECT_EQ(f[0], 0x01);
  EXPECT_EQ(static_cast<unsigned char>(f[1]), 7U);
  EXPECT_EQ(static_cast<unsigned char>(f[5]), 0x08U);
  EXPECT_EQ(static_cast<unsigned char>(f[12]), 0x01U);
  EXPECT_EQ(f.substr(13), "{\"pose\":1}");

  // A channel that appears later is advertised to the clients of its mission only.
  const auto other_client = hub.open({false, "other"});
  (void)drain(hub, other_client);
  auto more = channels();
  more.push_back({"/survey/agent2/pose", kPoseInFrameSchema});
  hub.registerChannels("survey", more);
  frames = drain(hub, client);
  ASSERT_EQ(frames.size(), 1U);
  EXPECT_EQ(json::parse(frames[0].bytes)["channels"][0]["topic"], "/survey/agent2/pose");
  EXPECT_TRUE(drain(hub, other_client).empty());

  // The subscription asks for a catch-up of that channel.
  const auto catch_ups = hub.takeCatchUps();
  ASSERT_EQ(catch_ups.size(), 1U);
  EXPECT_EQ(catch_ups[0].client, client);
  EXPECT_EQ(catch_ups[0].channels, std::set<std::size_t>{1});
  EXPECT_TRUE(hub.takeCatchUps().empty());
}

TEST(ViewerHubTest, AClientThatDoesNotReadLosesItsOldestDataButNeverItsProtocolMessages) {
  ViewerHub hub({10});
  const auto client = subscribedToEvents(hub);
  for (int i = 0; i < 1000; ++i) hub.publish("survey", {{0, i, "{\"n\":" + std::to_string(i) + "}"}});
  auto more = channels();
  more.push_back({"/survey/agent2/pose", kPoseInFrameSchema});
  hub.registerChannels("survey", more);
  const auto counters = hub.counters(client);
  EXPECT_EQ(counters.dropped, 990U);
  EXPECT_EQ(hub.droppedTotal(), 990U);
  const auto frames = drain(hub, client);
  std::size_t data = 0;
  std::size_t advertises = 0;
  for (const auto& f : frames) {
    if (f.binary) {
      ++data;
    } else if (json::parse(f.bytes)["op"] == "advertise") {
      ++advertises;
    }
  }
  EXPECT_EQ(data, 10U);
  EXPECT_EQ(advertises, 2U) << "at open and the new channel";
  EXPECT_EQ(frames.back().bytes.substr(13), "{\"n\":999}") << "the newest are kept";
  // What was dropped was changes: once the client has read, it is caught up on every channel it subscribed to.
  const auto catch_ups = hub.takeCatchUps();
  ASSERT_EQ(catch_ups.size(), 1U);
  EXPECT_EQ(catch_ups[0].channels, std::set<std::size_t>{0});
  EXPECT_TRUE(hub.takeCatchUps().empty()) << "once";
}

TEST(ViewerHubTest, AClientThatStaysStalledIsNotCaughtUpIntoItsFullQueue) {
  ViewerHub hub({10});
  const auto client = subscribedToEvents(hub);
  for (int i = 0; i < 30; ++i) hub.publish("survey", {{0, i, "{}"}});
  EXPECT_TRUE(hub.takeCatchUps().empty()) << "its queue is still full";
  ViewerHub::Frame f;
  while (hub.counters(client).queued > 4) ASSERT_TRUE(hub.pop(client, f));
  EXPECT_EQ(hub.takeCatchUps().size(), 1U) << "it reads again";
}

TEST(ViewerHubTest, HostileClientMessagesGetAStatusAndTheClientGoesOn) {
  ViewerHub hub;
  hub.registerChannels("survey", channels());
  hub.registerChannels("other", {{"/other/events", kLogSchema}});
  const auto client = hub.open({false, "survey"});
  (void)drain(hub, client);
  for (const std::string& text :
       {std::string("not json"), std::string("[]"), std::string(R"({"op":"subscribe","subscriptions":[{"id":-1}]})"),
        std::string(R"({"op":"subscribe","subscriptions":[{"id":1,"channelId":3}]})"),  // the other mission's
        std::string(R"({"op":"clientAdvertise","channels":[]})"), std::string(R"({"op":5})")}) {
    EXPECT_FALSE(hub.onText(client, text).ok()) << text;
    const auto frames = drain(hub, client);
    ASSERT_EQ(frames.size(), 1U) << text;
    EXPECT_EQ(json::parse(frames[0].bytes)["op"], "status");
  }
  hub.publish("other", {{0, 1, "{}"}});
  EXPECT_TRUE(drain(hub, client).empty()) << "the other mission's channel was not subscribed";
  EXPECT_TRUE(hub.onText(client, R"({"op":"subscribe","subscriptions":[{"id":1,"channelId":1}]})").ok());
  hub.publish("survey", {{0, 1, "{}"}});
  EXPECT_EQ(drain(hub, client).size(), 1U);
}

TEST(McapRecorderTest, WhatIsRecordedReadsBackWithItsChannelsSchemasAndCounts) {
  const test::TempDir dir;
  const auto file = dir.path() / "survey.mcap";
  auto recorder = McapRecorder::create(file);
  ASSERT_TRUE(recorder.ok()) << recorder.error().toString();
  auto chs = channels();
  ASSERT_TRUE(recorder->write(chs, {{0, 100, logMessage(100, LogLevel::kInfo, "agent 1 joined")}}).ok());
  chs.push_back({"/survey/map0/points", kPointCloudSchema});
  for (int i = 0; i < 5; ++i) {
    ASSERT_TRUE(recorder
                    ->write(chs, {{1, 200 + i, poseInFrame(200 + i, "survey/map0", geometry::SE3d())},
                                  {2, 200 + i, pointCloud(200 + i, "survey/map0", {Eigen::Vector3f(1, 2, 3)})}})
                    .ok());
  }
  EXPECT_FALSE(recorder->write(chs, {{9, 1, "{}"}}).ok()) << "an unknown channel";
  ASSERT_TRUE(recorder->close().ok());

  auto reader = mcap::Reader::open(file);
  ASSERT_TRUE(reader.ok()) << reader.error().toString();
  std::map<std::string, int> counts;
  std::map<std::string, std::string> schemas;
  mcap::MessageView view;
  while (true) {
    auto next = reader->next(view);
    ASSERT_TRUE(next.ok()) << next.error().toString();
    if (!*next) break;
    ++counts[view.channel->topic];
    schemas[view.channel->topic] = view.schema->name;
    EXPECT_EQ(view.channel->message_encoding, "json");
    EXPECT_FALSE(json::parse(std::string(view.data.begin(), view.data.end())).empty());
  }
  EXPECT_EQ(counts["/survey/events"], 1);
  EXPECT_EQ(counts["/survey/agent1/pose"], 5);
  EXPECT_EQ(counts["/survey/map0/points"], 5);
  EXPECT_EQ(schemas["/survey/map0/points"], "foxglove.PointCloud");
}

}  // namespace
}  // namespace cvislam::server::viewer
