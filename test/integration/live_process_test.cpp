// The agent on live topics as a robot runs it: iox-roudi, a driver process (cvislam_sensor_publisher playing the real
// EuRoC V1_01 excerpt at sensor pace), cvislam_agent --live and a cvislam_server, all separate processes. The live
// run must track as well as the same recording read from its folder at the same pace, reach the server, and end when
// the driver ends the stream; an agent left without a driver stops on SIGINT with its outputs written.
#include <signal.h>

#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include "common/core/diagnostics.hpp"
#include "common/dataset/calibration.hpp"
#include "common/dataset/trajectory_io.hpp"
#include "common/eval/trajectory_eval.hpp"
#include "test/support/child_process.hpp"
#include "test/support/kalibr_files.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam {
namespace {

namespace fs = std::filesystem;
using std::chrono::milliseconds;
using test::ChildProcess;

std::string readFile(const fs::path& path) {
  std::ifstream in(path);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

nlohmann::json readJson(const fs::path& path) {
  std::ifstream in(path);
  return nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
}

// ATE (SE3 alignment, RMSE) of a trajectory against the sequence's ground truth.
double ateM(const fs::path& trajectory, const fs::path& sequence) {
  Diagnostics diagnostics;
  auto estimate = dataset::readTrajectory(trajectory, {}, diagnostics);
  auto truth = dataset::readTrajectory(sequence, {}, diagnostics);
  if (!estimate.ok() || !truth.ok()) return 1e9;
  auto evaluation = eval::evaluate(*estimate, *truth, {});
  if (!evaluation.ok()) return 1e9;
  const eval::AbsoluteError* se3 = evaluation->find(eval::Alignment::kSE3);
  return se3 != nullptr ? se3->translation_m.rmse : 1e9;
}

class LiveProcesses : public ::testing::Test {
 protected:
  void TearDown() override {
    if (roudi_) {
      roudi_->signal(SIGTERM);
      (void)roudi_->wait(milliseconds(5000));
      // A process that cannot register or publish is often explained only on RouDi's side.
      if (HasFailure()) std::printf("iox-roudi's log:\n%s\n", readFile(roudi_->log()).c_str());
    }
  }

  void startRouDi() {
    roudi_ = std::make_unique<ChildProcess>(
        std::vector<std::string>{"/usr/bin/iox-roudi", "-m", "off", "-c", CVISLAM_ROUDI_CONFIG},
        dir_.path() / "roudi.log");
    ASSERT_TRUE(test::waitFor([&] { return readFile(roudi_->log()).find("RouDi is ready") != std::string::npos; },
                              milliseconds(10000)))
        << readFile(roudi_->log());
  }

  // Kalibr files equal to the sequence's sensor.yaml files: a live stream carries no calibration.
  void writeCalibration(const fs::path& sequence) {
    const Status written = test::writeKalibrFilesOf(sequence, camchain_, imu_yaml_);
    ASSERT_TRUE(written.ok()) << written.error().toString();
  }

  [[nodiscard]] std::vector<std::string> agentArgs(const std::string& name) const {
    return {CVISLAM_AGENT_BINARY,
            "--output",
            (dir_.path() / name).string(),
            "--calibration",
            camchain_.string(),
            "--imu-calibration",
            imu_yaml_.string(),
            "--mode",
            "stereo",
            "--quiet"};
  }

  static void expectCleanExit(ChildProcess& process, milliseconds timeout = milliseconds(120000)) {
    const auto status = process.wait(timeout);
    ASSERT_TRUE(status.has_value()) << "did not finish; its log:\n" << readFile(process.log());
    EXPECT_EQ(*status, 0) << readFile(process.log());
  }

  test::TempDir dir_;
  fs::path camchain_ = dir_.path() / "kalibr" / "camchain-imucam.yaml";
  fs::path imu_yaml_ = dir_.path() / "kalibr" / "imu.yaml";
  std::unique_ptr<ChildProcess> roudi_;
};

TEST_F(LiveProcesses, ADriverProcessFeedsTheAgentWhichTracksAsFromTheFolderAndReachesTheServer) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  writeCalibration(excerpt);
  startRouDi();

  // The reference: the same recording from its folder, at the same (sensor) pace.
  std::vector<std::string> folder_args = agentArgs("folder");
  folder_args.insert(folder_args.end(), {"--dataset", excerpt.string(), "--roudi", "external"});
  ChildProcess folder(folder_args, dir_.path() / "folder.log");
  expectCleanExit(folder);

  const fs::path port_file = dir_.path() / "server_port";
  ChildProcess server({CVISLAM_SERVER_BINARY, "--listen", "127.0.0.1:0", "--output", (dir_.path() / "server").string(),
                       "--port-file", port_file.string(), "--quiet"},
                      dir_.path() / "server.log");
  ASSERT_TRUE(test::waitFor([&] { return fs::exists(port_file) || !server.running(); }, milliseconds(10000)));
  ASSERT_TRUE(server.running()) << readFile(server.log());

  std::vector<std::string> live_args = agentArgs("live");
  live_args.insert(live_args.end(),
                   {"--live", "v101", "--server", "127.0.0.1:" + readFile(port_file), "--mission", "live"});
  // The agent's states read by another program (a flight controller's place), through the same RouDi.
  ChildProcess monitor({CVISLAM_MONITOR_BINARY, "--quiet"}, dir_.path() / "monitor.log");
  ChildProcess agent(live_args, dir_.path() / "live.log");
  ChildProcess driver({CVISLAM_PUBLISHER_BINARY, "--dataset", excerpt.string(), "--name", "v101", "--quiet"},
                      dir_.path() / "driver.log");
  expectCleanExit(driver);
  expectCleanExit(agent);  // ended by the driver's end of stream
  monitor.signal(SIGINT);
  expectCleanExit(monitor, milliseconds(10000));
  server.signal(SIGTERM);
  ASSERT_TRUE(server.wait(milliseconds(20000)).has_value()) << readFile(server.log());

  const nlohmann::json live = readJson(dir_.path() / "live" / "summary.json");
  const nlohmann::json from_folder = readJson(dir_.path() / "folder" / "summary.json");
  ASSERT_TRUE(live.is_object() && from_folder.is_object()) << readFile(agent.log());
  EXPECT_EQ(live["frames"], from_folder["frames"]) << live.dump(1);
  EXPECT_FALSE(live["interrupted"].get<bool>());
  EXPECT_EQ(live["live"]["frames_lost"], 0) << live.dump(1);
  EXPECT_EQ(live["live"]["imu_wait_timeouts"], 0) << live.dump(1);
  EXPECT_GE(live["tracked_frames"].get<int>(), from_folder["tracked_frames"].get<int>() - 2);
  EXPECT_TRUE(live["link"]["flushed"].get<bool>()) << live.dump(1);
  EXPECT_EQ(live["link"]["keyframes_unacknowledged"], 0) << live.dump(1);

  // Every frame's state reached the reader; the IMU-rate states came between them once the IMU was initialised.
  unsigned long long frames = 0, metric = 0, gaps = 0, propagated = 0;
  const std::string counts = readFile(monitor.log());
  const std::size_t at = counts.find("states: frames");
  ASSERT_NE(at, std::string::npos) << counts;
  ASSERT_EQ(std::sscanf(counts.c_str() + at, "states: frames %llu (metric %llu, sequence gaps %llu), propagated %llu",
                        &frames, &metric, &gaps, &propagated),
            4)
      << counts;
  EXPECT_EQ(frames, live["frames"].get<unsigned long long>()) << counts;
  EXPECT_EQ(gaps, 0U) << counts;
  EXPECT_GT(metric, 0U) << counts;
  EXPECT_GE(propagated, 9 * (metric - 1)) << counts;
  // And the health topic, once a second while the agent ran (4.7 s of frames at sensor pace).
  unsigned long long health = 0, health_frames = 0;
  const std::size_t health_at = counts.find("health: ");
  ASSERT_NE(health_at, std::string::npos) << counts;
  ASSERT_EQ(std::sscanf(counts.c_str() + health_at, "health: %llu messages, the last at frames %llu", &health,
                        &health_frames),
            2)
      << counts;
  EXPECT_GE(health, 2U) << counts;
  EXPECT_GT(health_frames, 0U) << counts;
  EXPECT_LE(health_frames, live["frames"].get<unsigned long long>()) << counts;
  const double ate_folder_m = ateM(dir_.path() / "folder" / "trajectory.txt", excerpt);
  const double ate_live_m = ateM(dir_.path() / "live" / "trajectory.txt", excerpt);
  std::printf("ATE (SE3, refined trajectory, realtime): folder %.3f mm, live %.3f mm\n", ate_folder_m * 1e3,
              ate_live_m * 1e3);
  EXPECT_LT(ate_folder_m, 0.005);
  EXPECT_LE(ate_live_m, 1.1 * ate_folder_m);
}

// A driver process killed mid-stream (SIGKILL: no end-of-stream) and started again from the beginning of its
// recording, its clock back where it began: the agent says the camera stopped, follows the new driver and ends with
// it. The restarted stream's first frame is searched for around the last pose and, not found there (the hand-held
// camera was elsewhere at the start of the recording), starts a new map at once instead of relocalising for 20
// frames against a prediction from the old clock. REAL EuRoC MH_01 (mono), whose rig the publisher writes as Kalibr
// files.
TEST_F(LiveProcesses, ADriverKilledAndStartedAgainIsFollowedToTheEnd) {
  CVISLAM_REQUIRE_DATA(mh01, "euroc-mh01-30s-mono");
  const fs::path kalibr = dir_.path() / "mh01_kalibr";
  ChildProcess write({CVISLAM_PUBLISHER_BINARY, "--dataset", mh01.string(), "--write-calibration", kalibr.string()},
                     dir_.path() / "write.log");
  expectCleanExit(write, milliseconds(20000));
  startRouDi();
  ChildProcess agent({CVISLAM_AGENT_BINARY, "--live", "restart", "--output", (dir_.path() / "restarted").string(),
                      "--calibration", (kalibr / "camchain-imucam.yaml").string(), "--imu-calibration",
                      (kalibr / "imu.yaml").string(), "--mode", "mono"},
                     dir_.path() / "restarted.log");
  {
    // Killed 6 s in: past the IMU's initialisation, 2 m into the hand-held path. The driver kills itself between two
    // publishes; a SIGKILL from outside may land inside one and leave an iceoryx lock held, which blocks RouDi.
    ChildProcess first({CVISLAM_PUBLISHER_BINARY, "--dataset", mh01.string(), "--name", "restart", "--quiet",
                        "--crash-after-frames", "120"},
                       dir_.path() / "driver1.log");
    const auto status = first.wait(milliseconds(60000));
    ASSERT_TRUE(status.has_value()) << readFile(first.log());
    EXPECT_EQ(*status, 128 + SIGKILL) << readFile(first.log());
  }
  ASSERT_TRUE(test::waitFor([&] { return readFile(agent.log()).find("no frame for") != std::string::npos; },
                            milliseconds(10000)))
      << readFile(agent.log());
  ChildProcess second(
      {CVISLAM_PUBLISHER_BINARY, "--dataset", mh01.string(), "--name", "restart", "--quiet", "--max-frames", "60"},
      dir_.path() / "driver2.log");
  expectCleanExit(second);
  expectCleanExit(agent);
  const std::string log = readFile(agent.log());
  EXPECT_NE(log.find("frames again after"), std::string::npos) << log;
  const std::size_t restart = log.find("the driver started again");
  ASSERT_NE(restart, std::string::npos) << log;
  EXPECT_EQ(log.find("pose refused", restart), std::string::npos) << log.substr(restart);
  const nlohmann::json summary = readJson(dir_.path() / "restarted" / "summary.json");
  ASSERT_TRUE(summary.is_object()) << log;
  EXPECT_EQ(summary["live"]["stalls"], 1) << summary.dump(1);
  EXPECT_EQ(summary["live"]["driver_restarts"], 1) << summary.dump(1);
  EXPECT_EQ(summary["new_maps"], 2) << summary.dump(1);
  EXPECT_FALSE(summary["interrupted"].get<bool>());
}

TEST_F(LiveProcesses, AnAgentWaitingForADriverStopsOnSigintWithItsOutputs) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  writeCalibration(excerpt);
  startRouDi();
  std::vector<std::string> args = agentArgs("waiting");
  args.erase(args.end() - 1);  // not quiet: the waiting is said
  args.insert(args.end(), {"--live", "nobody"});
  ChildProcess agent(args, dir_.path() / "waiting.log");
  ASSERT_TRUE(test::waitFor([&] { return readFile(agent.log()).find("waiting for a driver") != std::string::npos; },
                            milliseconds(20000)))
      << readFile(agent.log());
  agent.signal(SIGINT);
  expectCleanExit(agent, milliseconds(20000));
  const nlohmann::json summary = readJson(dir_.path() / "waiting" / "summary.json");
  ASSERT_TRUE(summary.is_object()) << readFile(agent.log());
  EXPECT_TRUE(summary["interrupted"].get<bool>());
  EXPECT_EQ(summary["frames"], 0);
}

TEST_F(LiveProcesses, ALiveAgentSaysWhatItLacks) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  writeCalibration(excerpt);
  // No calibration.
  ChildProcess bare({CVISLAM_AGENT_BINARY, "--live", "cam", "--output", (dir_.path() / "bare").string()},
                    dir_.path() / "bare.log");
  EXPECT_EQ(bare.wait(milliseconds(20000)), 1);
  EXPECT_NE(readFile(bare.log()).find("--calibration"), std::string::npos) << readFile(bare.log());
  // No iox-roudi to meet the driver at.
  std::vector<std::string> args = agentArgs("no_roudi");
  args.insert(args.end(), {"--live", "cam"});
  ChildProcess alone(args, dir_.path() / "alone.log");
  EXPECT_EQ(alone.wait(milliseconds(20000)), 1);
  EXPECT_NE(readFile(alone.log()).find("iox-roudi"), std::string::npos) << readFile(alone.log());
}

}  // namespace
}  // namespace cvislam
