// The keyframe rule in time, on the real Tracker and Mapper (test/support/inline_agent) over a rendered stereo loop
// (fixed seed): with the IMU, once it is initialised, keyframes are at most max_interval_s (0.5 s) apart; with the
// cap off, or without the IMU, only the frame count spaces them, and this sequence then leaves longer gaps. So it is
// the cap that keeps the keyframes close, and the tracker applies it only with the IMU.
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/runtime/sensor_setup.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/rendered_mission.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::agent {
namespace {

struct KeyframeGaps {
  int keyframes = 0;       // made after the IMU initialisation (all of them without the IMU)
  int by_interval = 0;     // of those, made for the time since the last keyframe
  double longest_s = 0.0;  // the longest time between two of them
  int tracked_frames = 0;
};

KeyframeGaps gapsOver(const std::filesystem::path& mission, const TrackerOptions& options) {
  KeyframeGaps gaps;
  auto seq = dataset::EurocSequence::open(mission / "agent0");
  EXPECT_TRUE(seq.ok()) << seq.error().toString();
  if (!seq.ok()) return gaps;
  MapperOptions mapper_options;
  mapper_options.use_imu = options.use_imu;
  auto created = test::InlineAgent::create(*seq, /*stereo=*/true, options, mapper_options);
  EXPECT_TRUE(created.ok()) << created.error().toString();
  if (!created.ok()) return gaps;
  test::InlineAgent& agent = **created;
  const std::vector<dataset::RigFrame> frames = framesToRun(*seq, /*stereo=*/true);
  std::int64_t last_keyframe_ns = -1;
  for (std::size_t i = 0; i < agent.frameCount(); ++i) {
    const Status loaded = agent.load(i);
    EXPECT_TRUE(loaded.ok()) << loaded.error().toString();
    if (!loaded.ok()) return gaps;
    const FrameResult r = agent.track([] {}, [] {});
    gaps.tracked_frames += r.tracked ? 1 : 0;
    if (!r.keyframe || (options.use_imu && !r.imu_initialised)) continue;
    const std::int64_t t_ns = frames[i].t_ns;
    if (last_keyframe_ns >= 0)
      gaps.longest_s = std::max(gaps.longest_s, static_cast<double>(t_ns - last_keyframe_ns) * 1e-9);
    last_keyframe_ns = t_ns;
    ++gaps.keyframes;
    gaps.by_interval += r.keyframe_reason == KeyframeReason::kInterval ? 1 : 0;
  }
  std::printf("IMU %s, cap %.2f s: %d keyframes (%d for the time), longest gap %.2f s, %d frames tracked\n",
              options.use_imu ? "on" : "off", options.keyframe.max_interval_s, gaps.keyframes, gaps.by_interval,
              gaps.longest_s, gaps.tracked_frames);
  return gaps;
}

// The rendered loop, once per process; shared with the other tests of the CTest run, so read-only.
std::filesystem::path loopMission() {
  static const test::TempDir dir;
  static const Result<std::filesystem::path> rendered =
      test::renderedMission({"loop", 5, 20.0, /*stereo=*/true}, dir.path());
  EXPECT_TRUE(rendered.ok()) << rendered.error().toString();
  return rendered.ok() ? *rendered : std::filesystem::path();
}

// One frame (50 ms) of slack: the rule is checked on frames, so a keyframe comes on the first frame at or past
// the cap.
constexpr double kFrameS = 0.05;

TEST(KeyframeInterval, WithTheImuKeyframesAreAtMostHalfASecondApart) {
  const KeyframeGaps capped = gapsOver(loopMission(), TrackerOptions{});
  ASSERT_GE(capped.keyframes, 10);
  EXPECT_GT(capped.by_interval, 0);
  EXPECT_LE(capped.longest_s, 0.5 + kFrameS);

  TrackerOptions uncapped;
  uncapped.keyframe.max_interval_s = 0.0;
  const KeyframeGaps spaced = gapsOver(loopMission(), uncapped);
  EXPECT_EQ(spaced.by_interval, 0);
  EXPECT_GT(spaced.longest_s, 0.5 + kFrameS);  // else this sequence could not show the cap at work
  EXPECT_LT(spaced.keyframes, capped.keyframes);
}

TEST(KeyframeInterval, WithoutTheImuOnlyTheFrameCountSpacesKeyframes) {
  TrackerOptions options;
  options.use_imu = false;
  const KeyframeGaps gaps = gapsOver(loopMission(), options);
  ASSERT_GE(gaps.keyframes, 10);
  EXPECT_EQ(gaps.by_interval, 0);
  EXPECT_GT(gaps.longest_s, 0.5 + kFrameS);
}

}  // namespace
}  // namespace cvislam::agent
