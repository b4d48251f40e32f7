// Joining a mission's traces: the clock offset between an agent and the server is recovered from the link's own
// messages within the bound it states, other missions' events are left out, contradictions are refused, and a
// keyframe is followed link by link from the camera to the server and back.
#include "common/trace/trace_join.hpp"

#include <random>

#include <gtest/gtest.h>

#include "common/trace/trace.hpp"

namespace cvislam::trace {
namespace {

constexpr std::int64_t kAgent = 3;

TraceRecord span(const std::string& name, double ts_us, double dur_us, std::map<std::string, std::int64_t> args) {
  TraceRecord r;
  r.name = name;
  r.phase = "X";
  r.ts_us = ts_us;
  r.dur_us = dur_us;
  r.tid = 1;
  r.args = std::move(args);
  return r;
}

TraceRecord instantAt(const std::string& name, double ts_us, std::map<std::string, std::int64_t> args) {
  TraceRecord r = span(name, ts_us, 0.0, std::move(args));
  r.phase = "i";
  return r;
}

struct Pair {
  ProcessTrace agent;
  ProcessTrace server;
};

// An agent sending 50 batches (one keyframe each) and receiving one acknowledgement per batch, with the server's
// clock `offset_us` ahead of the agent's and one-way delays drawn from [0.2, 4] ms (seeded).
Pair linkTraffic(double offset_us, const std::string& mission = "m") {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> delay_us(200.0, 4000.0);
  Pair p;
  p.agent.process = "agent 3";
  p.agent.agent = kAgent;
  p.agent.mission = mission;
  p.agent.mission_key = missionKey(mission);
  p.server.process = "server";
  const std::int64_t key = missionKey(mission);
  for (std::int64_t b = 1; b <= 50; ++b) {
    const double t_a = 200'000.0 * static_cast<double>(b);  // agent clock
    p.agent.records.push_back(span("keyframe_write", t_a - 50'000.0, 1000.0, {{"keyframe", b}}));
    p.agent.records.push_back(instantAt("keyframe_sent", t_a + 100.0, {{"keyframe", b}, {"batch", b}}));
    p.agent.records.push_back(span("uplink_batch", t_a, 300.0, {{"batch", b}}));
    const double ingest_s = t_a + 300.0 + delay_us(rng) + offset_us;  // server clock
    p.server.records.push_back(span("ingest", ingest_s, 2000.0, {{"mission", key}, {"agent", kAgent}, {"batch", b}}));
    const double built_s = ingest_s + 5000.0;
    p.server.records.push_back(span("downlink_build", built_s - 100.0, 100.0,
                                    {{"mission", key}, {"agent", kAgent}, {"downlink", b}, {"corrections", 0}}));
    p.agent.records.push_back(instantAt("downlink_received", built_s + delay_us(rng) - offset_us, {{"downlink", b}}));
  }
  return p;
}

TEST(TraceJoin, TheClockOffsetIsRecoveredWithinItsStatedBound) {
  for (const double offset_us : {0.0, 250'000.0, -1.5e9}) {
    const Pair p = linkTraffic(offset_us);
    auto c = estimateClockOffset(p.agent, p.server);
    ASSERT_TRUE(c) << c.error().message();
    EXPECT_EQ(c->uplink_pairs, 50U);
    EXPECT_EQ(c->downlink_pairs, 50U);
    EXPECT_LE(std::abs(c->offset_us - offset_us), c->uncertainty_us + 1e-6) << "offset " << offset_us;
    // Fifty messages each way leave the offset known to within a millisecond, where single delays reach 4 ms: the
    // interval's width is the send span (0.3 ms) plus the smallest delay each way.
    EXPECT_LT(c->uncertainty_us, 1000.0);
    EXPECT_GT(c->uncertainty_us, 0.0);
  }
}

TEST(TraceJoin, AnotherMissionsEventsAreLeftOut) {
  Pair p = linkTraffic(250'000.0);
  // The same agent id in another mission, its batches ingested far earlier on the server's clock: counted, they
  // would pull the upper bound below the true offset.
  const Pair other = linkTraffic(-1e6, "other");
  for (const TraceRecord& r : other.server.records) p.server.records.push_back(r);
  auto c = estimateClockOffset(p.agent, p.server);
  ASSERT_TRUE(c) << c.error().message();
  EXPECT_EQ(c->uplink_pairs, 50U);
  EXPECT_LE(std::abs(c->offset_us - 250'000.0), c->uncertainty_us + 1e-6);
}

TEST(TraceJoin, BoundsThatContradictEachOtherAreRefused) {
  Pair p = linkTraffic(0.0);
  // The downlink of another run: received long before the server built it.
  for (TraceRecord& r : p.agent.records) {
    if (r.name == "downlink_received") r.ts_us -= 60e6;
  }
  auto c = estimateClockOffset(p.agent, p.server);
  ASSERT_FALSE(c);
  EXPECT_NE(c.error().message().find("contradict"), std::string::npos) << c.error().message();
}

TEST(TraceJoin, OneDirectionAloneIsNotEnough) {
  Pair p = linkTraffic(0.0);
  std::erase_if(p.agent.records, [](const TraceRecord& r) { return r.name == "downlink_received"; });
  auto c = estimateClockOffset(p.agent, p.server);
  ASSERT_FALSE(c);
  EXPECT_NE(c.error().message().find("0 downlink messages"), std::string::npos) << c.error().message();
}

TEST(TraceJoin, AKeyframeIsFollowedLinkByLink) {
  const std::int64_t key = missionKey("m");
  ProcessTrace agent;
  agent.agent = kAgent;
  agent.mission = "m";
  agent.mission_key = key;
  // Times in us on one clock; each link below differs, so that a swapped link shows.
  agent.records = {
      span("track_frame", 1000.0, 9000.0, {{"frame", 5}, {"keyframe", 7}, {"since_capture_us", 500}}),
      span("keyframe_write", 8000.0, 1000.0, {{"keyframe", 7}}),    // decided at 9 ms; captured at 0.5 ms
      span("map_keyframe", 10'000.0, 30'000.0, {{"keyframe", 7}}),  // local BA done at 40 ms
      instantAt("map_ready", 5'000.0, {{"map", 0}}),                // before it was decided: its wait was the link's
      instantAt("keyframe_sent", 60'000.0, {{"keyframe", 7}, {"batch", 2}, {"map", 0}}),
      // Decided before its map's frame was final (at 80 ms), stored at 95 ms: out of the steady-state link.
      span("keyframe_write", 70'000.0, 1000.0, {{"keyframe", 8}}),
      instantAt("map_ready", 80'000.0, {{"map", 1}}),
      instantAt("keyframe_sent", 90'000.0, {{"keyframe", 8}, {"batch", 3}, {"map", 1}}),
      span("apply_downlink", 400'000.0, 500.0, {{"downlink", 4}, {"corrections", 0}}),  // no corrections: skipped
      span("apply_downlink", 900'000.0, 500.0, {{"downlink", 5}, {"corrections", 3}}),
  };
  ProcessTrace server;
  server.agent = -1;
  server.records = {
      span("ingest", 61'000.0, 4000.0, {{"mission", key}, {"agent", kAgent}, {"batch", 2}}),  // stored at 65 ms
      span("ingest", 91'000.0, 4000.0, {{"mission", key}, {"agent", kAgent}, {"batch", 3}}),
      span("recognition_query", 100'000.0, 10'000.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 7}}),
      span("merge", 120'000.0, 30'000.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 7}, {"map", 1}}),
      instantAt("merged_map_agent", 130'000.0, {{"mission", key}, {"map", 1}, {"agent", kAgent}}),
      span("global_ba", 100'000.0, 20'000.0, {{"mission", key}, {"map", 1}}),   // before the merge: not its GBA
      span("global_ba", 200'000.0, 300'000.0, {{"mission", key}, {"map", 2}}),  // another map
      span("global_ba", 300'000.0, 400'000.0, {{"mission", key}, {"map", 1}}),  // optimised at 700 ms
  };
  const Journeys j = followKeyframes(server, {agent});
  EXPECT_EQ(j.keyframes, 2U);
  // Keyframe 7's way; keyframe 8 (decided at 71 ms) adds its own sent and stored links, but not the steady one.
  const std::vector<std::vector<double>> expected_ms = {{8.5},  {31.0}, {51.0, 19.0}, {5.0, 5.0}, {56.0, 24.0},
                                                        {56.0}, {45.0}, {40.0},       {550.0},    {200.0}};
  ASSERT_EQ(j.links.size(), expected_ms.size());
  for (std::size_t i = 0; i < expected_ms.size(); ++i) {
    ASSERT_EQ(j.links[i].ms.size(), expected_ms[i].size()) << j.links[i].name;
    for (std::size_t k = 0; k < expected_ms[i].size(); ++k) {
      EXPECT_NEAR(j.links[i].ms[k], expected_ms[i][k], 1e-9) << j.links[i].name;
    }
  }
  // The match (its query's end, 110 ms) to the one agent of the merged map applying corrections (900 ms).
  ASSERT_EQ(j.match_to_all_agents_corrected_ms.size(), 1U);
  EXPECT_NEAR(j.match_to_all_agents_corrected_ms[0], 790.0, 1e-9);
  EXPECT_EQ(j.merges_not_reaching_every_agent, 0U);
  const std::vector<LinkSummary> s = summarise(j);
  ASSERT_GE(s.size(), 2U);
  EXPECT_EQ(s[s.size() - 2].ms.count, 1U);
  EXPECT_NEAR(s[s.size() - 2].ms.p99, 790.0, 1e-9);
}

// A merge's map corrected at once. The first message the server builds for each agent of the merged map after the
// correction decides: with corrections or covisible keyframes, the agent holds the corrected map once it applied
// it; with neither, nothing it holds had changed, and it held the corrected map when that message was built.
TEST(TraceJoin, EveryAgentHoldsTheCorrectedMapOnceTheFirstMessageBuiltAfterTheCorrectionReachedIt) {
  const std::int64_t key = missionKey("m");
  ProcessTrace query_agent;  // its keyframes moved: it gets corrections
  query_agent.agent = kAgent;
  query_agent.mission_key = key;
  query_agent.records = {
      span("apply_downlink", 200'000.0, 500.0, {{"downlink", 3}, {"corrections", 2}, {"covisible", 1}}),  // before
      span("apply_downlink", 520'000.0, 500.0, {{"downlink", 4}, {"corrections", 5}, {"covisible", 0}}),
  };
  ProcessTrace candidate_agent;  // its anchors include moved keyframes: it gets their updates
  candidate_agent.agent = 9;
  candidate_agent.mission_key = key;
  candidate_agent.records = {
      // Built from 389 ms, before the correction ended (400 ms), and applied after it: not yet.
      span("apply_downlink", 450'000.0, 500.0, {{"downlink", 7}, {"corrections", 0}, {"covisible", 1}}),
      span("apply_downlink", 700'000.0, 500.0, {{"downlink", 8}, {"corrections", 0}, {"covisible", 1}}),
  };
  ProcessTrace far_agent;  // elsewhere in the map: nothing it holds moved
  far_agent.agent = 10;
  far_agent.mission_key = key;
  far_agent.records = {
      span("apply_downlink", 900'000.0, 500.0, {{"downlink", 2}, {"corrections", 0}, {"covisible", 1}}),
  };
  ProcessTrace server;
  server.records = {
      span("recognition_query", 100'000.0, 10'000.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 7}}),
      span("merge", 120'000.0, 30'000.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 7}, {"map", 1}}),
      instantAt("merged_map_agent", 130'000.0, {{"mission", key}, {"map", 1}, {"agent", kAgent}}),
      instantAt("merged_map_agent", 131'000.0, {{"mission", key}, {"map", 1}, {"agent", 9}}),
      instantAt("merged_map_agent", 132'000.0, {{"mission", key}, {"map", 1}, {"agent", 10}}),
      span("merge_correction", 150'000.0, 250'000.0, {{"mission", key}, {"map", 1}}),  // corrected at 400 ms
      span("global_ba", 900'000.0, 100'000.0, {{"mission", key}, {"map", 1}}),
      span("downlink_build", 199'000.0, 500.0,
           {{"mission", key}, {"agent", kAgent}, {"downlink", 3}, {"corrections", 2}, {"covisible", 1}}),
      span("downlink_build", 500'000.0, 500.0,
           {{"mission", key}, {"agent", kAgent}, {"downlink", 4}, {"corrections", 5}, {"covisible", 0}}),
      span("downlink_build", 389'000.0, 1000.0,
           {{"mission", key}, {"agent", 9}, {"downlink", 7}, {"corrections", 0}, {"covisible", 1}}),
      span("downlink_build", 590'000.0, 500.0,
           {{"mission", key}, {"agent", 9}, {"downlink", 8}, {"corrections", 0}, {"covisible", 1}}),
      span("downlink_build", 450'000.0, 500.0,
           {{"mission", key}, {"agent", 10}, {"downlink", 1}, {"corrections", 0}, {"covisible", 0}}),
      span("downlink_build", 890'000.0, 500.0,
           {{"mission", key}, {"agent", 10}, {"downlink", 2}, {"corrections", 0}, {"covisible", 1}}),
      // A stale match later (its maps were one already, no agent joined): not a merge to follow.
      span("merge", 800'000.0, 10.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 8}, {"map", 1}}),
  };
  const Journeys j = followKeyframes(server, {query_agent, candidate_agent, far_agent});
  // From the match (110 ms): the query's agent at 520 ms, the far agent at 450.5 ms, the candidate's agent at 700 ms.
  ASSERT_EQ(j.match_to_all_agents_holding_corrected_map_ms.size(), 1U);
  EXPECT_NEAR(j.match_to_all_agents_holding_corrected_map_ms[0], 590.0, 1e-9);
  EXPECT_EQ(j.merges_not_reaching_every_agent_corrected_map, 0U);
  // By corrections alone, the other two agents never got any: counted apart, and the stale match not at all.
  EXPECT_TRUE(j.match_to_all_agents_corrected_ms.empty());
  EXPECT_EQ(j.merges_not_reaching_every_agent, 1U);
  EXPECT_NEAR(summarise(j).back().ms.p99, 590.0, 1e-9);
}

// Without a merge correction, the map's first GBA after the merge is its first correction.
TEST(TraceJoin, WithoutAMergeCorrectionTheCorrectedMapIsTheGbas) {
  const std::int64_t key = missionKey("m");
  ProcessTrace agent;
  agent.agent = kAgent;
  agent.mission_key = key;
  agent.records = {
      span("apply_downlink", 300'000.0, 500.0, {{"downlink", 3}, {"corrections", 0}, {"covisible", 1}}),  // before
      span("apply_downlink", 800'000.0, 500.0, {{"downlink", 4}, {"corrections", 0}, {"covisible", 1}}),
  };
  ProcessTrace server;
  server.records = {
      span("merge", 120'000.0, 30'000.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 7}, {"map", 1}}),
      instantAt("merged_map_agent", 130'000.0, {{"mission", key}, {"map", 1}, {"agent", kAgent}}),
      span("global_ba", 160'000.0, 540'000.0, {{"mission", key}, {"map", 1}}),  // optimised at 700 ms
      span("downlink_build", 290'000.0, 500.0,
           {{"mission", key}, {"agent", kAgent}, {"downlink", 3}, {"covisible", 1}}),
      span("downlink_build", 790'000.0, 500.0,
           {{"mission", key}, {"agent", kAgent}, {"downlink", 4}, {"covisible", 1}}),
  };
  const Journeys j = followKeyframes(server, {agent});
  ASSERT_EQ(j.match_to_all_agents_holding_corrected_map_ms.size(), 1U);
  EXPECT_NEAR(j.match_to_all_agents_holding_corrected_map_ms[0], 680.0, 1e-9);  // from the merge's start
}

TEST(TraceJoin, AMergeSomeAgentNeverHeardOfIsCountedApart) {
  const std::int64_t key = missionKey("m");
  ProcessTrace agent;
  agent.agent = kAgent;
  agent.mission_key = key;
  ProcessTrace server;
  server.records = {
      span("merge", 120'000.0, 30'000.0, {{"mission", key}, {"agent", kAgent}, {"keyframe", 7}, {"map", 1}}),
      instantAt("merged_map_agent", 130'000.0, {{"mission", key}, {"map", 1}, {"agent", kAgent}}),
      instantAt("merged_map_agent", 131'000.0, {{"mission", key}, {"map", 1}, {"agent", 9}}),  // no trace of it
  };
  const Journeys j = followKeyframes(server, {agent});
  EXPECT_TRUE(j.match_to_all_agents_corrected_ms.empty());
  EXPECT_EQ(j.merges_not_reaching_every_agent, 1U);
  EXPECT_TRUE(j.match_to_all_agents_holding_corrected_map_ms.empty());
  EXPECT_EQ(j.merges_not_reaching_every_agent_corrected_map, 1U);
}

}  // namespace
}  // namespace cvislam::trace
