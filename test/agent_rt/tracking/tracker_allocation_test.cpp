// The design card's promise: after start-up, the tracking loop makes no heap allocation. This binary
// replaces malloc and its relatives (test/support/malloc_counter), so every allocation counts, OpenCV's and
// Eigen's included. It tracks a simulated stereo sequence (rendered at test time, fixed seed) with the real
// Tracker and Mapper in one thread (test/support/inline_agent), and counts the allocations inside
// Tracker::track() over the steady state: after the IMU is initialised, keyframes included.
#include <cstdio>

#include <gtest/gtest.h>

#include "common/trace/trace.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/malloc_counter.hpp"
#include "test/support/rendered_mission.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::agent {
namespace {

// Tracks the rendered loop and expects no allocation inside track() in the steady state.
void expectSteadyStateAllocatesNothing(const TrackerOptions& options) {
  test::TempDir dir;
  auto mission = test::renderedMission({"loop", 5, 8.0, /*stereo=*/true}, dir.path());
  ASSERT_TRUE(mission.ok()) << mission.error().toString();
  auto seq = dataset::EurocSequence::open(*mission / "agent0");
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  auto agent = test::InlineAgent::create(*seq, true, options);
  ASSERT_TRUE(agent.ok()) << agent.error().toString();

  auto counted = (*agent)->countSteadyAllocations([] { return test::mallocCount(); }, [](std::size_t) {});
  ASSERT_TRUE(counted.ok()) << counted.error().toString();
  const int steady_frames = counted->frames;
  const int steady_tracked = counted->tracked;
  const int steady_keyframes = counted->keyframes;
  const long steady_allocations = counted->allocations;
  std::printf("steady state: %d frames, %d tracked, %d keyframes, %ld allocations\n", steady_frames, steady_tracked,
              steady_keyframes, steady_allocations);
  ASSERT_GE(steady_frames, 100);  // the IMU was initialised early enough to count a real stretch
  EXPECT_GE(steady_tracked, steady_frames - 2);
  EXPECT_GE(steady_keyframes, 3);
  EXPECT_EQ(steady_allocations, 0);
}

TEST(TrackerAllocations, SteadyStateTrackingAllocatesNothing) {
  expectSteadyStateAllocatesNothing(TrackerOptions{});
}

TEST(TrackerAllocations, TheLargestMotionBaWindowAllocatesNothing) {
  TrackerOptions options;
  options.motion_ba_keyframes = static_cast<int>(kMaxMotionBaKeyframes);
  expectSteadyStateAllocatesNothing(options);
}

// With a trace recording every stage (cvislam_agent --trace), the same: a bound thread records into its ring.
TEST(TrackerAllocations, TracingEveryStageAllocatesNothing) {
  trace::SessionOptions trace_options;
  trace_options.process_name = "agent 0";
  trace_options.events_per_thread = std::size_t{1} << 14;
  trace::Session session(trace_options);
  trace::bindThread("tracking");
  expectSteadyStateAllocatesNothing(TrackerOptions{});
  const std::string json = session.chromeJson();
  for (const char* stage :
       {"\"orb\"", "\"matching\"", "\"pose_optimisation\"", "\"motion_ba\"", "\"keyframe_write\""}) {
    EXPECT_NE(json.find(stage), std::string::npos) << stage << " was not traced";
  }
}

}  // namespace
}  // namespace cvislam::agent
