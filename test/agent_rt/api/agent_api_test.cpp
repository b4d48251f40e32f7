// The embedding API as a program uses it: the real V1_01 excerpt pushed frame by frame with its IMU. Replayed, it
// gives the folder run's trajectory byte for byte; pushed faster than tracking takes frames, the ring drops what
// does not fit and says so; every frame's state reaches the callback; bad configurations are named. The agent runs
// its RouDi in this process: tests of this binary hold the CTest resource lock "iceoryx_roudi".
#include "cvislam/agent.hpp"

#include <atomic>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/runtime/agent.hpp"
#include "common/dataset/calibration.hpp"
#include "common/dataset/euroc.hpp"
#include "test/support/kalibr_files.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam {
namespace {

namespace fs = std::filesystem;

class AgentApi : public ::testing::Test {
 protected:
  void writeCalibration(const fs::path& sequence) {
    const Status written = test::writeKalibrFilesOf(sequence, camchain_, imu_yaml_);
    ASSERT_TRUE(written.ok()) << written.error().toString();
  }

  AgentConfig config(const std::string& name) const {
    AgentConfig c;
    c.calibration = camchain_.string();
    c.imu_calibration = imu_yaml_.string();
    c.output = (dir_.path() / name).string();
    return c;
  }

  // Pushes the sequence as drivers would: the IMU up to each frame and the sample after it, then the frame.
  // With `decode_first`, every image is decoded before the first push, so that pushing takes microseconds a
  // frame whatever the machine's load; otherwise each image is decoded just before it is pushed. Returns how many
  // pushFrame calls were refused.
  static int pushAll(Agent& agent, const dataset::EurocSequence& sequence, bool decode_first = false) {
    const auto imu = sequence.imu();
    const auto size = static_cast<std::size_t>(agent.width() * agent.height());
    std::vector<dataset::RigFrame> frames;
    for (const auto& frame : sequence.rigFrames()) {
      if (frame.cam1) frames.push_back(frame);
    }
    std::vector<std::vector<std::uint8_t>> left(decode_first ? frames.size() : 1, std::vector<std::uint8_t>(size));
    std::vector<std::vector<std::uint8_t>> right(left.size(), std::vector<std::uint8_t>(size));
    const auto decode = [&](std::size_t frame, std::size_t into) {
      EXPECT_TRUE(sequence.loadImageInto(0, frames[frame].cam0, left[into]).ok());
      EXPECT_TRUE(sequence.loadImageInto(1, *frames[frame].cam1, right[into]).ok());
    };
    if (decode_first) {
      for (std::size_t i = 0; i < frames.size(); ++i) decode(i, i);
    }
    std::size_t next_imu = 0;
    int refused = 0;
    const auto push = [&](const dataset::ImuSample& s) {
      EXPECT_TRUE(agent.pushImu(
          {s.t_ns, {s.gyro_s.x(), s.gyro_s.y(), s.gyro_s.z()}, {s.accel_s.x(), s.accel_s.y(), s.accel_s.z()}}));
    };
    for (std::size_t i = 0; i < frames.size(); ++i) {
      const std::int64_t t_ns = frames[i].t_ns;
      for (; next_imu < imu.size() && imu[next_imu].t_ns <= t_ns; ++next_imu) push(imu[next_imu]);
      if (next_imu < imu.size()) push(imu[next_imu++]);
      const std::size_t buffer = decode_first ? i : 0;
      if (!decode_first) decode(i, buffer);
      if (!agent.pushFrame(t_ns, left[buffer].data(), right[buffer].data())) ++refused;
    }
    return refused;
  }

  test::TempDir dir_;
  fs::path camchain_ = dir_.path() / "kalibr" / "camchain-imucam.yaml";
  fs::path imu_yaml_ = dir_.path() / "kalibr" / "imu.yaml";
};

TEST_F(AgentApi, AReplayThroughTheApiGivesTheFolderRunsTrajectoryByteForByte) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  writeCalibration(excerpt);
  auto sequence = dataset::EurocSequence::open(excerpt);
  ASSERT_TRUE(sequence.ok());

  AgentConfig c = config("api");
  c.replay = true;
  std::atomic<int> frame_states{0};
  std::atomic<int> tracked_states{0};
  std::atomic<int> propagated_states{0};
  std::atomic<int> propagated_before_metric{0};
  c.on_state = [&](const AgentState& s) {
    if (s.kind == AgentState::Kind::kImuPropagated) {
      ++propagated_states;
      if (!s.metric) ++propagated_before_metric;
      return;
    }
    ++frame_states;
    if (s.tracked) ++tracked_states;
  };
  std::string error;
  auto agent = Agent::create(c, &error);
  ASSERT_NE(agent, nullptr) << error;
  EXPECT_TRUE(agent->stereo());
  EXPECT_EQ(agent->width(), 752);
  EXPECT_EQ(pushAll(*agent, *sequence), 0);
  const AgentSummary summary = agent->finish();
  ASSERT_TRUE(summary.ok) << summary.error;
  EXPECT_EQ(summary.frames, 95U);
  EXPECT_EQ(frame_states.load(), 95);
  EXPECT_EQ(static_cast<std::uint64_t>(tracked_states.load()), summary.tracked_frames);
  EXPECT_GT(summary.imu_initialised_at_s, 0.0);
  // Between frames, once the IMU is initialised (at 1.8 s of 4.7 s, 200 Hz): the IMU-rate states.
  EXPECT_GT(propagated_states.load(), 300);
  EXPECT_EQ(propagated_before_metric.load(), 0);

  // The same recording read from its folder by the agent at --pace sync.
  agent::AgentOptions folder;
  folder.dataset = excerpt;
  folder.output = dir_.path() / "folder";
  folder.mode = agent::AgentMode::kStereo;
  folder.pace = agent::Pace::kSync;
  folder.calibration = camchain_;
  folder.imu_calibration = imu_yaml_;
  folder.quiet = true;
  const std::atomic<bool> stop{false};
  auto reference = agent::runAgent(folder, stop);
  ASSERT_TRUE(reference.ok()) << reference.error().toString();
  for (const char* file : {"trajectory.txt", "trajectory_online.txt", "keyframes.txt"}) {
    const std::string expected = test::readTextFile(folder.output / file);
    EXPECT_FALSE(expected.empty()) << file;
    EXPECT_EQ(test::readTextFile(dir_.path() / "api" / file), expected) << file;
  }
}

TEST_F(AgentApi, FramesPushedFasterThanTrackingTakesThemAreDroppedAndCounted) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  writeCalibration(excerpt);
  auto sequence = dataset::EurocSequence::open(excerpt);
  ASSERT_TRUE(sequence.ok());
  std::string error;
  auto agent = Agent::create(config("burst"), &error);
  ASSERT_NE(agent, nullptr) << error;
  // No pacing at all: the images are decoded beforehand and the 95 frames pushed in the time it takes to copy
  // them, far faster than tracking takes frames from its ring of four.
  const int refused = pushAll(*agent, *sequence, /*decode_first=*/true);
  const AgentSummary summary = agent->finish();
  ASSERT_TRUE(summary.ok) << summary.error;
  EXPECT_GT(refused, 0);
  EXPECT_EQ(summary.frames_dropped, static_cast<std::uint64_t>(refused));
  EXPECT_EQ(summary.frames + summary.frames_dropped, 95U);
}

TEST_F(AgentApi, ABadConfigurationIsNamed) {
  std::string error;
  AgentConfig none;
  none.output = (dir_.path() / "none").string();
  EXPECT_EQ(Agent::create(none, &error), nullptr);
  EXPECT_NE(error.find("camera chain"), std::string::npos) << error;

  AgentConfig missing = none;
  missing.calibration = (dir_.path() / "nowhere.yaml").string();
  EXPECT_EQ(Agent::create(missing, &error), nullptr);
  EXPECT_NE(error.find("nowhere.yaml"), std::string::npos) << error;
}

}  // namespace
}  // namespace cvislam
