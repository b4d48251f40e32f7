// The access decisions without gRPC: the tokens file (what it accepts, and the line it names when it refuses),
// who a token opens, the bearer header, and the per-client rate limit on a stepped clock.
#include <chrono>
#include <fstream>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/access/rate_limiter.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::server {
namespace {

using ::testing::HasSubstr;
using Clock = RateLimiter::Clock;

const std::string kTokenA = "aaaaaaaaaaaaaaaa0001";
const std::string kTokenB = "bbbbbbbbbbbbbbbb0002";
const std::string kOperator = "0123456789abcdef-operator";

MissionTokens twoMissions() {
  auto tokens = MissionTokens::parse(
      "# missions\nhall-a " + kTokenA + "\n  hall-b\t" + kTokenB + "   # trailing comment\n\n* " + kOperator + "\n",
      "tokens.txt");
  EXPECT_TRUE(tokens.ok()) << tokens.error().toString();
  return std::move(tokens).value();
}

TEST(MissionTokens, WithoutAFileEveryMissionIsOpen) {
  const MissionTokens open;
  EXPECT_FALSE(open.enabled());
  EXPECT_TRUE(open.authorize("anything", "").ok());
}

TEST(MissionTokens, EachMissionOpensWithItsOwnTokenOnly) {
  const MissionTokens tokens = twoMissions();
  ASSERT_TRUE(tokens.enabled());
  EXPECT_EQ(tokens.missions(), 2U);
  EXPECT_TRUE(tokens.authorize("hall-a", kTokenA).ok());
  EXPECT_TRUE(tokens.authorize("hall-b", kTokenB).ok());

  const Status missing = tokens.authorize("hall-a", "");
  const Status other_missions = tokens.authorize("hall-a", kTokenB);
  const Status near_miss = tokens.authorize("hall-a", kTokenA.substr(0, kTokenA.size() - 1) + "2");
  const Status unlisted = tokens.authorize("hall-c", kTokenA);

  for (const Status& s : {missing, other_missions, near_miss, unlisted}) {
    ASSERT_FALSE(s.ok());
    EXPECT_EQ(s.error().code(), ErrorCode::kUnauthenticated);
  }
  EXPECT_THAT(missing.error().message(), HasSubstr("needs its token"));
  EXPECT_THAT(other_missions.error().message(), HasSubstr("does not open mission 'hall-a'"));
  // A mission the file does not list reads like a wrong token: nobody learns which missions exist by trying.
  std::string unlisted_text = unlisted.error().message();
  unlisted_text.replace(unlisted_text.find("hall-c"), 6, "hall-a");
  EXPECT_EQ(unlisted_text, other_missions.error().message());
  // No token leaks into a message.
  EXPECT_THAT(other_missions.error().message(), ::testing::Not(HasSubstr(kTokenA)));
}

TEST(MissionTokens, TheOperatorTokenOpensEveryListedAndUnlistedMission) {
  const MissionTokens tokens = twoMissions();
  EXPECT_TRUE(tokens.admits("hall-a", kOperator));
  EXPECT_TRUE(tokens.admits("hall-b", kOperator));
  EXPECT_TRUE(tokens.admits("hall-c", kOperator));
}

TEST(MissionTokens, BadFilesAreRefusedNamingTheLine) {
  struct Case {
    std::string text;
    std::string says;
  };
  const Case cases[] = {
      {"hall-a\n", "line 1: 'hall-a' has no token"},
      {"# ok\nhall-a short\n", "line 2: the token of 'hall-a' has 5 characters"},
      {"hall-a " + kTokenA + " extra\n", "line 1: more than 'MISSION TOKEN'"},
      {"hall-a " + kTokenA + "\nhall-a " + kTokenB + "\n", "line 2: mission 'hall-a' is listed twice"},
      {"* " + kTokenA + "\n* " + kTokenB + "\n", "line 2: a second operator token"},
      {"# nothing\n\n", "lists no mission"},
  };
  for (const Case& c : cases) {
    const auto parsed = MissionTokens::parse(c.text, "secret/tokens");
    ASSERT_FALSE(parsed.ok()) << c.text;
    EXPECT_EQ(parsed.error().code(), ErrorCode::kParseError);
    EXPECT_THAT(parsed.error().message(), HasSubstr("secret/tokens"));
    EXPECT_THAT(parsed.error().message(), HasSubstr(c.says));
  }
}

TEST(MissionTokens, LoadsAFileAndNamesAMissingOne) {
  test::TempDir dir;
  const auto file = dir.path() / "tokens";
  std::ofstream(file) << "hall-a " << kTokenA << "\n";
  const auto loaded = MissionTokens::load(file);
  const auto missing = MissionTokens::load(dir.path() / "nope");

  ASSERT_TRUE(loaded.ok()) << loaded.error().toString();
  EXPECT_TRUE(loaded->admits("hall-a", kTokenA));
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(missing.error().message(), HasSubstr("nope"));
}

TEST(BearerToken, ReadsTheSchemeInAnyCaseAndNothingElse) {
  EXPECT_EQ(bearerToken("Bearer abc"), "abc");
  EXPECT_EQ(bearerToken("bearer   abc  "), "abc");
  EXPECT_EQ(bearerToken("BEARER abc"), "abc");
  EXPECT_EQ(bearerToken("Basic abc"), "");
  EXPECT_EQ(bearerToken("Bearer "), "");
  EXPECT_EQ(bearerToken("abc"), "");
}

TEST(RateLimiter, ABurstPassesThenTheRateHoldsAndQuietRefills) {
  RateLimitOptions options;
  options.rate_per_s = 10.0;
  options.burst = 5.0;
  RateLimiter limiter(options);
  const Clock::time_point t0{};

  int passed = 0;
  Status refused;
  for (int i = 0; i < 8; ++i) {
    const Status s = limiter.admit("10.0.0.1 (no token)", "ListMaps", t0);
    if (s.ok()) {
      ++passed;
    } else {
      refused = s;
    }
  }
  EXPECT_EQ(passed, 5);
  EXPECT_EQ(limiter.refused(), 3U);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.error().code(), ErrorCode::kResourceExhausted);
  EXPECT_THAT(refused.error().message(), HasSubstr("ListMaps refused: client 10.0.0.1 (no token)"));
  EXPECT_THAT(refused.error().message(), HasSubstr("more than 10 requests per second (burst 5); retry in 100 ms"));

  // 0.25 s later: 2.5 tokens, so 2 requests.
  const Clock::time_point t1 = t0 + std::chrono::milliseconds(250);
  EXPECT_TRUE(limiter.admit("10.0.0.1 (no token)", "ListMaps", t1).ok());
  EXPECT_TRUE(limiter.admit("10.0.0.1 (no token)", "ListMaps", t1).ok());
  EXPECT_FALSE(limiter.admit("10.0.0.1 (no token)", "ListMaps", t1).ok());
  // Another client has its own bucket.
  EXPECT_TRUE(limiter.admit("10.0.0.2 (no token)", "ListMaps", t1).ok());
  // A long quiet spell refills to the burst, not beyond.
  const Clock::time_point t2 = t1 + std::chrono::seconds(100);
  for (int i = 0; i < 5; ++i) EXPECT_TRUE(limiter.admit("10.0.0.1 (no token)", "ListMaps", t2).ok());
  EXPECT_FALSE(limiter.admit("10.0.0.1 (no token)", "ListMaps", t2).ok());
}

TEST(RateLimiter, ZeroRateIsNoLimitAndTheClientTableStaysBounded) {
  RateLimitOptions off;
  off.rate_per_s = 0.0;
  RateLimiter unlimited(off);
  for (int i = 0; i < 1000; ++i) ASSERT_TRUE(unlimited.admit("c", "GetMap").ok());

  RateLimitOptions options;
  options.rate_per_s = 1.0;
  options.burst = 2.0;
  options.max_clients = 100;
  RateLimiter limiter(options);
  const Clock::time_point t0{};
  ASSERT_TRUE(limiter.admit("busy", "GetMap", t0).ok());
  ASSERT_TRUE(limiter.admit("busy", "GetMap", t0).ok());
  for (int i = 0; i < 1000; ++i) {
    ASSERT_TRUE(limiter.admit("client-" + std::to_string(i), "GetMap", t0 + std::chrono::milliseconds(i)).ok());
    ASSERT_LE(limiter.clients(), 100U);
  }
  // The busy client's empty bucket outlived the churn of full ones: it is still limited.
  EXPECT_FALSE(limiter.admit("busy", "GetMap", t0).ok());
}

TEST(RateLimitOptions, BadValuesAreNamed) {
  RateLimitOptions negative;
  negative.rate_per_s = -1.0;
  RateLimitOptions no_burst;
  no_burst.burst = 0.5;
  EXPECT_THAT(negative.validate().error().message(), HasSubstr("limits.requests_per_s"));
  EXPECT_THAT(no_burst.validate().error().message(), HasSubstr("limits.request_burst"));
}

}  // namespace
}  // namespace cvislam::server
