// The agent's options without running it: the config file (every section read, bad keys and values named), the
// shipped deploy/agent_config.yaml, what the run plan derives from the options, the thread schedules, and the
// bounds of the channels between the threads.
#include <fstream>
#include <initializer_list>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include "agent_rt/runtime/agent.hpp"
#include "agent_rt/runtime/channel_depths.hpp"
#include "agent_rt/runtime/run_plan.hpp"
#include "agent_rt/runtime/yield_requests.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::agent {
namespace {

// Mapping sees tracking's requests to yield only from the keyframe it took last on; requests from another thread
// are seen without a lock.
TEST(YieldRequests, MappingSeesTheRequestsSinceItTookAKeyframe) {
  YieldRequests requests;
  EXPECT_FALSE(requests.askedSinceKeyframeTaken());
  requests.request();
  EXPECT_TRUE(requests.askedSinceKeyframeTaken());
  requests.keyframeTaken();
  EXPECT_FALSE(requests.askedSinceKeyframeTaken());
  std::thread tracking([&requests] {
    for (int i = 0; i < 1000; ++i) requests.request();
  });
  tracking.join();
  EXPECT_TRUE(requests.askedSinceKeyframeTaken());
  EXPECT_EQ(requests.requests(), 1001u);
  requests.keyframeTaken();
  EXPECT_FALSE(requests.askedSinceKeyframeTaken());
}

// The keyframe pool follows the backlog's bound: with the back-off, twice max_pending_keyframes queued (8 at
// least), without it 32; every pool holds its queue plus what the reader holds and the writer loans.
TEST(ChannelDepths, TheKeyframeQueueFollowsTheBacklogsBound) {
  MappingLagOptions lag;
  EXPECT_EQ(ChannelDepths::forLag(lag).keyframes, 8U);
  lag.max_pending_keyframes = 10;
  EXPECT_EQ(ChannelDepths::forLag(lag).keyframes, 20U);
  lag.back_off = false;
  const ChannelDepths unbounded = ChannelDepths::forLag(lag);
  EXPECT_EQ(unbounded.keyframes, 32U);
  EXPECT_GE(unbounded.keyframeChunks(), unbounded.keyframes + 2);
  EXPECT_GE(unbounded.snapshotChunks(), unbounded.snapshots + 3);
  EXPECT_GE(unbounded.deltaChunks(), unbounded.deltas + 2);
  EXPECT_GE(unbounded.anchorChunks(), unbounded.anchors + 2);
}

// Writes `text` as the agent config file agent.yaml in `dir`; returns its path.
std::filesystem::path writeConfig(const test::TempDir& dir, const std::string& text) {
  std::ofstream(dir.path() / "agent.yaml") << text;
  return dir.path() / "agent.yaml";
}

// Each of `bad` ("key: value") under `section`, loaded into fresh options and checked by `validate`, is refused
// with a message that names the key.
template <typename Validate>
void expectEachRefusedNamingItsKey(const test::TempDir& dir, const std::string& section,
                                   std::initializer_list<const char*> bad, Validate validate) {
  for (const char* line : bad) {
    AgentOptions out_of_range;
    ASSERT_TRUE(loadAgentConfig(writeConfig(dir, section + ":\n  " + line + "\n"), out_of_range).ok()) << line;
    const Status status = validate(out_of_range);
    ASSERT_FALSE(status.ok()) << line;
    const std::string key = std::string(line).substr(0, std::string(line).find(':'));
    EXPECT_NE(status.error().message().find(key), std::string::npos) << status.error().message();
  }
}

TEST(AgentConfig, ReadsThreadSchedulesAndNamesBadOnes) {
  test::TempDir dir;
  const auto write = [&](const std::string& text) { return writeConfig(dir, text); };
  AgentOptions o;
  ASSERT_TRUE(loadAgentConfig(write("threads:\n  mapping_nice: 15\n  tracking_realtime_priority: 0\n"
                                    "  tracking_cpus: \"0\"\ntracking:\n  max_pending_keyframes: 3\n"),
                              o)
                  .ok());
  EXPECT_EQ(o.threads.mapping.nice, 15);
  EXPECT_EQ(o.threads.tracking.realtime_priority, 0);
  EXPECT_EQ(o.threads.tracking.cpus, std::vector<int>{0});
  EXPECT_EQ(o.tracking.lag.max_pending_keyframes, 3);

  auto bad_list = loadAgentConfig(write("threads:\n  mapping_cpus: \"1-\"\n"), o);
  ASSERT_FALSE(bad_list.ok());
  EXPECT_NE(bad_list.error().message().find("threads.mapping_cpus"), std::string::npos) << bad_list.error().message();
  auto bad_nice = loadAgentConfig(write("threads:\n  link_nice: 30\n"), o);
  ASSERT_FALSE(bad_nice.ok());
  EXPECT_NE(bad_nice.error().message().find("threads.link: nice = 30"), std::string::npos)
      << bad_nice.error().message();
  auto no_cpu = loadAgentConfig(write("threads:\n  loader_cpus: \"4096\"\n"), o);
  ASSERT_FALSE(no_cpu.ok());
  EXPECT_NE(no_cpu.error().message().find("threads.loader"), std::string::npos) << no_cpu.error().message();
  AgentOptions fresh;
  auto bad_backlog = loadAgentConfig(write("tracking:\n  max_pending_keyframes: 0\n"), fresh);
  ASSERT_TRUE(bad_backlog.ok()) << bad_backlog.error().toString();
  EXPECT_NE(fresh.tracking.validate().error().message().find("max_pending_keyframes = 0"), std::string::npos);

  // The shipped file holds every key with its default.
  AgentOptions shipped;
  ASSERT_TRUE(loadAgentConfig(CVISLAM_SOURCE_DIR "/deploy/agent_config.yaml", shipped).ok());
  const AgentOptions defaults;
  EXPECT_EQ(shipped.tracking.search.max_distance, defaults.tracking.search.max_distance);
  EXPECT_FLOAT_EQ(shipped.tracking.search.ratio, defaults.tracking.search.ratio);
  EXPECT_DOUBLE_EQ(shipped.tracking.keyframe.max_interval_s, defaults.tracking.keyframe.max_interval_s);
  EXPECT_EQ(shipped.tracking.initialisation_max_frames_between, defaults.tracking.initialisation_max_frames_between);
  EXPECT_EQ(shipped.threads.tracking.realtime_priority, defaults.threads.tracking.realtime_priority);
  EXPECT_EQ(shipped.threads.mapping.nice, defaults.threads.mapping.nice);
  EXPECT_EQ(shipped.tracking.lag.min_tracked_points_when_busy, defaults.tracking.lag.min_tracked_points_when_busy);
  EXPECT_EQ(shipped.threads.lower_others_with_realtime, defaults.threads.lower_others_with_realtime);
  EXPECT_EQ(shipped.mapping.imu_init_min_keyframes, defaults.mapping.imu_init_min_keyframes);
  EXPECT_DOUBLE_EQ(shipped.mapping.imu_init_scale_agreement, defaults.mapping.imu_init_scale_agreement);
  EXPECT_EQ(shipped.mapping.return_full_window_keyframes, defaults.mapping.return_full_window_keyframes);
}

TEST(AgentConfig, ReadsTrackingsMatchingAndKeyframeThresholdsAndNamesBadOnes) {
  test::TempDir dir;
  const auto write = [&](const std::string& text) { return writeConfig(dir, text); };
  AgentOptions matching;
  ASSERT_TRUE(loadAgentConfig(write("tracking:\n  max_descriptor_distance: 70\n  match_ratio: 0.8\n"
                                    "  max_keyframe_interval_s: 0.25\n  init_max_frames_between_keyframes: 5\n"),
                              matching)
                  .ok());
  EXPECT_EQ(matching.tracking.search.max_distance, 70);
  EXPECT_EQ(matching.tracking.initialisation_max_frames_between, 5);
  EXPECT_FLOAT_EQ(matching.tracking.search.ratio, 0.8F);
  EXPECT_DOUBLE_EQ(matching.tracking.keyframe.max_interval_s, 0.25);
  expectEachRefusedNamingItsKey(dir, "tracking",
                                {"max_descriptor_distance: 300", "match_ratio: 0", "max_keyframe_interval_s: -1",
                                 "init_max_frames_between_keyframes: 0"},
                                [](const AgentOptions& o) { return o.tracking.validate(); });
}

// Without a server the local map keeps older keyframes for their places; with one, the server's covisible map is
// that memory, and the plan keeps the newest keyframes only.
TEST(AgentPlan, OlderKeyframesAreKeptForTheirPlacesOnlyWithoutAServer) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  test::TempDir dir;
  AgentOptions alone;
  alone.dataset = excerpt;
  alone.output = dir.path() / "alone";
  AgentOptions with_server = alone;
  with_server.link.server = "127.0.0.1:50051";
  ASSERT_TRUE(planRun(alone).ok());
  ASSERT_TRUE(planRun(with_server).ok());
  EXPECT_EQ(alone.mapping.retention.place_keyframes, MapperOptions{}.retention.place_keyframes);
  EXPECT_GT(alone.mapping.retention.place_keyframes, 0);
  EXPECT_EQ(with_server.mapping.retention.place_keyframes, 0);
}

TEST(AgentConfig, ReadsThePlaceKeyframesAndNamesBadOnes) {
  test::TempDir dir;
  const auto write = [&](const std::string& text) { return writeConfig(dir, text); };
  AgentOptions places;
  ASSERT_TRUE(loadAgentConfig(write("mapping:\n  place_keyframes: 12\n  place_angle_weight_m: 0.5\n"
                                    "  return_full_window_keyframes: 5\n"),
                              places)
                  .ok());
  EXPECT_EQ(places.mapping.retention.place_keyframes, 12);
  EXPECT_EQ(places.mapping.return_full_window_keyframes, 5);
  EXPECT_DOUBLE_EQ(places.mapping.retention.angle_weight_m, 0.5);
  EXPECT_TRUE(places.mapping.validate().ok());
  // More own keyframes than the pool holds beside the anchors: the message names the keys and the capacity.
  AgentOptions too_many;
  ASSERT_TRUE(
      loadAgentConfig(write("mapping:\n  place_keyframes: " + std::to_string(kMaxKeyframes) + "\n"), too_many).ok());
  const Status status = too_many.mapping.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message().find("place_keyframes"), std::string::npos) << status.error().message();
  EXPECT_NE(status.error().message().find("CVISLAM_MAX_KEYFRAMES"), std::string::npos) << status.error().message();
  expectEachRefusedNamingItsKey(dir, "mapping",
                                {"place_keyframes: -1", "place_angle_weight_m: -2", "return_full_window_keyframes: -1"},
                                [](const AgentOptions& o) { return o.mapping.validate(); });
}

TEST(AgentConfig, ReadsTheEarlyImuInitialisationAndNamesBadValues) {
  test::TempDir dir;
  AgentOptions early;
  ASSERT_TRUE(
      loadAgentConfig(writeConfig(dir, "imu:\n  init_min_keyframes: 12\n  init_scale_agreement: 0.002\n"), early).ok());
  EXPECT_EQ(early.mapping.imu_init_min_keyframes, 12);
  EXPECT_DOUBLE_EQ(early.mapping.imu_init_scale_agreement, 0.002);
  EXPECT_TRUE(early.mapping.validate().ok());
  expectEachRefusedNamingItsKey(dir, "imu", {"init_min_keyframes: 3", "init_scale_agreement: -0.1"},
                                [](const AgentOptions& o) { return o.mapping.validate(); });
}

TEST(ThreadSchedule, OthersDropTheirNiceOnlyWhenTrackingRunsWithoutRealTimePriority) {
  ThreadScheduleOptions o;
  o.mapping.cpus = {0};
  const ThreadScheduleOptions with_fifo = o.resolved(true, 1);
  EXPECT_EQ(with_fifo.mapping.nice, 1);
  EXPECT_EQ(with_fifo.loader.nice, 1);
  EXPECT_EQ(with_fifo.link.nice, 1);
  EXPECT_EQ(with_fifo.mapping.cpus, std::vector<int>{0});
  EXPECT_EQ(with_fifo.tracking.realtime_priority, 10);
  const ThreadScheduleOptions without = o.resolved(false, 1);
  EXPECT_EQ(without.mapping.nice, 10);
  EXPECT_EQ(without.loader.nice, 2);
  EXPECT_EQ(without.link.nice, 5);
  o.lower_others_with_realtime = true;
  EXPECT_EQ(o.resolved(true, 1).mapping.nice, 10);
  o.lower_others_with_realtime = false;
  o.tracking.realtime_priority = 0;  // tracking asked for no real-time priority: the others make room
  EXPECT_EQ(o.resolved(true, 1).mapping.nice, 10);

  // The probe leaves the calling thread as it was, whatever it answers.
  int policy_before = -1;
  int policy_after = -1;
  sched_param param{};
  bool may = false;
  ScheduleOutcome taken;
  std::thread worker([&] {
    (void)pthread_getschedparam(pthread_self(), &policy_before, &param);
    may = mayTakeRealtimePriority(10);
    (void)pthread_getschedparam(pthread_self(), &policy_after, &param);
    taken = applyToThisThread(ThreadSchedule{0, 10, {}});  // and it answers what applying would do
  });
  worker.join();
  EXPECT_EQ(policy_after, policy_before);
  EXPECT_EQ(taken.applied, may) << taken.note;
  EXPECT_FALSE(mayTakeRealtimePriority(0));
}

TEST(ThreadSchedule, ParsesCpuListsAndLowersTheCallingThreadOnly) {
  EXPECT_EQ(*parseCpuList("0,2-3"), (std::vector<int>{0, 2, 3}));
  EXPECT_EQ(*parseCpuList(""), std::vector<int>{});
  for (const char* bad : {"a", "1,", "3-1", "1--2", ",1"}) EXPECT_FALSE(parseCpuList(bad).ok()) << bad;

  // A higher nice value needs no privilege; it applies to the thread that asked, not to the process.
  const int before = getpriority(PRIO_PROCESS, 0);
  int inside = -100;
  ScheduleOutcome outcome;
  std::thread worker([&] {
    outcome = applyToThisThread(ThreadSchedule{before + 3 > 19 ? 19 : before + 3, 0, {}});
    inside = getpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)));
  });
  worker.join();
  EXPECT_TRUE(outcome.applied) << outcome.note;
  EXPECT_EQ(inside, before + 3 > 19 ? 19 : before + 3);
  EXPECT_EQ(getpriority(PRIO_PROCESS, 0), before);
}

TEST(AgentConfig, NamesUnknownKeysAndBadValues) {
  test::TempDir dir;
  const auto write = [&](const std::string& text) { return writeConfig(dir, text); };
  AgentOptions o;
  EXPECT_TRUE(loadAgentConfig(write("orb:\n  max_features: 400\nmapping:\n  max_keyframes: 16\n"), o).ok());
  EXPECT_EQ(o.tracking.orb.max_features, 400);
  EXPECT_EQ(o.mapping.max_keyframes, 16);

  // An unknown key, a value of the wrong type, a bad choice, an unknown section: each named.
  const std::pair<const char*, const char*> refused[] = {
      {"tracking:\n  serch_radius_px: 9\n", "tracking.serch_radius_px"},
      {"orb:\n  max_features: many\n", "orb.max_features"},
      {"runtime:\n  pace: slow\n", "slow"},
      {"trackin:\n  x: 1\n", "trackin"}};
  for (const auto& [text, named] : refused) {
    auto loaded = loadAgentConfig(write(text), o);
    ASSERT_FALSE(loaded.ok()) << text;
    EXPECT_NE(loaded.error().message().find(named), std::string::npos) << loaded.error().message();
  }

  // Values the file can hold but the agent cannot use are named when the options are validated.
  AgentOptions window;
  window.dataset = "seq";
  window.output = "out";
  ASSERT_TRUE(loadAgentConfig(write("tracking:\n  motion_ba_keyframes: 0\n"), window).ok());
  const Status too_small = window.validate();
  ASSERT_FALSE(too_small.ok());
  EXPECT_NE(too_small.error().message().find("motion_ba_keyframes = 0"), std::string::npos);
  EXPECT_NE(too_small.error().message().find("CVISLAM_MAX_MOTION_BA_KEYFRAMES"), std::string::npos);

  AgentOptions leverage;
  leverage.dataset = "seq";
  leverage.output = "out";
  ASSERT_TRUE(loadAgentConfig(write("tracking:\n  max_pose_leverage: 0.8\n"), leverage).ok());
  EXPECT_DOUBLE_EQ(leverage.tracking.pose.max_leverage, 0.8);
  EXPECT_TRUE(leverage.validate().ok());
  ASSERT_TRUE(loadAgentConfig(write("tracking:\n  max_pose_leverage: 0.2\n"), leverage).ok());
  const Status low = leverage.validate();
  ASSERT_FALSE(low.ok());
  EXPECT_NE(low.error().message().find("max_leverage must be in [0.5, 1]"), std::string::npos)
      << low.error().toString();
}

}  // namespace
}  // namespace cvislam::agent
