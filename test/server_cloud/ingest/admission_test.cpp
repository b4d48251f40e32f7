// Who an AgentSession lets in, without gRPC: the mission's token at the Hello (refused before anything is made),
// the missions a server holds and the agents a mission holds (refused with RESOURCE_EXHAUSTED, while an agent the
// mission knows always comes back).
#include <memory>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/session_driver.hpp"

namespace cvislam::server {
namespace {

using test::batchMessage;
using test::helloMessage;
using test::makeKeyframeBatch;
using ::testing::HasSubstr;

const std::string kTokenA = "token-of-hall-a-0001";
const std::string kTokenB = "token-of-hall-b-0002";

class AdmissionTest : public ::testing::Test {
 protected:
  void start(std::size_t max_missions, std::size_t max_agents, bool tokens) {
    ServerOptions o;
    o.session.max_missions = max_missions;
    o.session.max_agents_per_mission = max_agents;
    core_ = std::make_unique<ServerCore>(o);
    if (tokens) {
      auto parsed = MissionTokens::parse("hall-a " + kTokenA + "\nhall-b " + kTokenB + "\n", "test tokens");
      ASSERT_TRUE(parsed.ok()) << parsed.error().toString();
      core_->setTokens(std::move(parsed).value());
    }
  }
  // A new stream presenting `token` says Hello; its status.
  Status hello(const std::string& mission, std::uint32_t agent, std::uint64_t process, const std::string& token,
               std::unique_ptr<AgentSession>* keep = nullptr) {
    auto session = core_->openSession({}, token);
    const Status s = test::sendTo(*session, helloMessage(mission, agent, process));
    if (keep != nullptr) *keep = std::move(session);
    return s;
  }

  std::unique_ptr<ServerCore> core_;
};

TEST_F(AdmissionTest, AHelloWithoutTheMissionsTokenIsRefusedBeforeAnythingIsMade) {
  start(64, 32, true);
  const Status none = hello("hall-a", 1, 11, "");
  const Status other = hello("hall-a", 1, 11, kTokenB);
  const Status unlisted = hello("hall-z", 1, 11, kTokenA);

  for (const Status& s : {none, other, unlisted}) {
    ASSERT_FALSE(s.ok());
    EXPECT_EQ(s.error().code(), ErrorCode::kUnauthenticated) << s.error().toString();
  }
  EXPECT_THAT(other.error().message(), HasSubstr("does not open mission 'hall-a'"));
  EXPECT_TRUE(core_->missions().missions().empty()) << "a refused Hello made a mission";
}

TEST_F(AdmissionTest, EachMissionsTokenOpensItAndWritesGoThrough) {
  start(64, 32, true);
  std::unique_ptr<AgentSession> a;
  ASSERT_TRUE(hello("hall-a", 1, 11, kTokenA, &a).ok());
  ASSERT_TRUE(hello("hall-b", 1, 12, kTokenB).ok());
  ASSERT_TRUE(test::sendTo(*a, batchMessage(makeKeyframeBatch(1, 0, 3))).ok());
  EXPECT_EQ(core_->missions().find("hall-a")->agent(1)->read()->keyframes.size(), 3U);
  EXPECT_EQ(core_->missions().find("hall-b")->agent(1)->read()->keyframes.size(), 0U);
}

TEST_F(AdmissionTest, MissionsBeyondTheServersLimitAreRefusedAndTheHeldOnesStayOpen) {
  start(2, 32, false);
  ASSERT_TRUE(hello("m1", 1, 1, "").ok());
  ASSERT_TRUE(hello("m2", 1, 2, "").ok());
  const Status third = hello("m3", 1, 3, "");
  ASSERT_FALSE(third.ok());
  EXPECT_EQ(third.error().code(), ErrorCode::kResourceExhausted);
  EXPECT_THAT(third.error().message(), HasSubstr("holds 2 missions, its limit (limits.max_missions); mission 'm3'"));
  EXPECT_EQ(core_->missions().find("m3"), nullptr);
  EXPECT_TRUE(hello("m1", 2, 4, "").ok()) << "a held mission takes new agents";
}

TEST_F(AdmissionTest, AgentsBeyondTheMissionsLimitAreRefusedAndAKnownAgentComesBack) {
  start(64, 2, false);
  std::unique_ptr<AgentSession> first;
  ASSERT_TRUE(hello("hall", 1, 101, "", &first).ok());
  ASSERT_TRUE(hello("hall", 2, 102, "").ok());
  const Status third = hello("hall", 3, 103, "");
  ASSERT_FALSE(third.ok());
  EXPECT_EQ(third.error().code(), ErrorCode::kResourceExhausted);
  EXPECT_THAT(third.error().message(),
              HasSubstr("mission 'hall' has 2 agents, its limit (limits.max_agents_per_mission); agent 3"));
  EXPECT_EQ(core_->missions().find("hall")->findAgent(3), nullptr);

  first->close(Status::Ok());
  EXPECT_TRUE(hello("hall", 1, 101, "").ok()) << "agent 1 reconnecting is not a new agent";
}

}  // namespace
}  // namespace cvislam::server
