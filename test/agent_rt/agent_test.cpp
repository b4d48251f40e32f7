// The whole agent on a simulated sequence rendered at test time (loop preset, fixed seed): real iceoryx
// (in-process RouDi), real threads, real Ceres. Accuracy against the simulator's ground truth, bad input
// (an IMU gap, a missing image, a black frame, an unreadable image), an interrupted run, and options that cannot
// work. The options on their own (config file, thread schedules): agent_options_test.cpp.
#include "agent_rt/runtime/agent.hpp"

#include <atomic>
#include <chrono>
#include <fstream>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include "common/core/diagnostics.hpp"
#include "common/dataset/calibration.hpp"
#include "common/dataset/image.hpp"
#include "common/dataset/image_codecs.hpp"
#include "common/dataset/trajectory_io.hpp"
#include "common/eval/trajectory_eval.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/support/euroc_to_mcap.hpp"
#include "test/support/kalibr_files.hpp"
#include "test/support/rendered_mission.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::agent {
namespace {

namespace fs = std::filesystem;

class AgentTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new test::TempDir();
    auto rendered = test::renderedMission({"loop", 11, 12.0, /*stereo=*/true}, dir_->path() / "sim");
    ASSERT_TRUE(rendered.ok()) << rendered.error().toString();
    mission_ = *rendered;
  }
  static void TearDownTestSuite() {
    delete dir_;
    dir_ = nullptr;
  }

  static fs::path sequence() { return mission_ / "agent0"; }

  static AgentOptions options(const fs::path& dataset, const std::string& name) {
    AgentOptions o;
    o.dataset = dataset;
    o.output = dir_->path() / name;
    o.pace = Pace::kSync;
    o.quiet = true;
    return o;
  }

  // ATE (SE3 alignment, RMSE) and the Sim3 scale error of a trajectory against the sequence's ground truth.
  static std::pair<double, double> evaluate(const fs::path& trajectory, const fs::path& dataset) {
    Diagnostics diagnostics;
    auto estimate = dataset::readTrajectory(trajectory, {}, diagnostics);
    auto truth = dataset::readTrajectory(dataset, {}, diagnostics);
    EXPECT_TRUE(estimate.ok() && truth.ok());
    if (!estimate.ok() || !truth.ok()) return {1e9, 1e9};
    auto evaluation = eval::evaluate(*estimate, *truth, {});
    EXPECT_TRUE(evaluation.ok());
    if (!evaluation.ok()) return {1e9, 1e9};
    const eval::AbsoluteError* se3 = evaluation->find(eval::Alignment::kSE3);
    return {se3 != nullptr ? se3->translation_m.rmse : 1e9, evaluation->scale_error_percent.value_or(1e9)};
  }

  static test::TempDir* dir_;
  static fs::path mission_;  // read-only: shared with the other tests of the CTest run
};

test::TempDir* AgentTest::dir_ = nullptr;
fs::path AgentTest::mission_;

TEST_F(AgentTest, StereoInertialTracksTheSimulatedLoop) {
  const std::atomic<bool> stop{false};
  AgentOptions o = options(sequence(), "stereo");
  o.mode = AgentMode::kStereo;
  auto summary = runAgent(o, stop);
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  std::printf("%s", formatSummary(*summary).c_str());
  EXPECT_EQ(summary->frames, 241u);
  EXPECT_GE(summary->tracked_frames, summary->frames - 2);  // all but the first, which starts the map
  EXPECT_EQ(summary->new_maps, 1u);
  EXPECT_GE(summary->imu_initialised_at_s, 0.0);
  EXPECT_LT(summary->imu_initialised_at_s, 10.0);
  // Tracking works in the final frame from the first frame after mapping's IMU initialisation; the frames before
  // it are marked in both trajectories, and only those.
  EXPECT_GE(summary->tracking_initialised_at_s, summary->imu_initialised_at_s);
  EXPECT_LT(summary->tracking_initialised_at_s, summary->imu_initialised_at_s + 0.5);
  for (const char* file : {"trajectory.txt", "trajectory_online.txt"}) {
    Diagnostics diagnostics;
    auto written = dataset::readTrajectory(o.output / file, {}, diagnostics);
    ASSERT_TRUE(written.ok()) << file;
    const std::int64_t first_t_ns = written->front().t_ns;
    std::size_t marked = 0;
    for (const dataset::StampedPose& pose : *written) {
      const double t_s = static_cast<double>(pose.t_ns - first_t_ns) * 1e-9;
      EXPECT_EQ(pose.before_initialisation, t_s < summary->tracking_initialised_at_s - 1e-6) << file << " " << t_s;
      marked += pose.before_initialisation ? 1 : 0;
    }
    EXPECT_GT(marked, 0u) << file;
  }
  const auto [ate_m, scale_error] = evaluate(summary->trajectory, sequence());
  std::printf("stereo-inertial, 12 s loop: ATE %.3f m, scale error %.2f %%\n", ate_m, scale_error);
  EXPECT_LT(ate_m, 0.05);
  EXPECT_LT(std::abs(scale_error), 2.0);
  for (const char* file :
       {"trajectory.txt", "trajectory_online.txt", "keyframes.txt", "latency.json", "summary.json"}) {
    EXPECT_TRUE(fs::exists(o.output / file)) << file;
  }
  std::ifstream latency(summary->latency_json);
  const std::string json((std::istreambuf_iterator<char>(latency)), std::istreambuf_iterator<char>());
  for (const char* stage :
       {"orb_extraction", "matching", "pose_optimisation", "motion_ba", "keyframe_publish_to_receive", "local_ba"}) {
    EXPECT_NE(json.find(stage), std::string::npos) << stage;
  }
}

// A copy of the sequence (images hard-linked) with an IMU gap, a missing image, a black frame and an
// unreadable image.
// Rewrites imu0/data.csv of a hard-linked copy, keeping the samples for which keep(t - t0) holds, t0 being
// the first sample's time.
void filterImu(const fs::path& mav0, const std::function<bool(std::int64_t)>& keep) {
  const fs::path imu_csv = mav0 / "imu0" / "data.csv";
  std::ifstream in(imu_csv);
  std::vector<std::string> lines;
  std::string line;
  std::int64_t t0 = -1;
  while (std::getline(in, line)) {
    if (!line.empty() && line[0] != '#') {
      const std::int64_t t = std::stoll(line.substr(0, line.find(',')));
      if (t0 < 0) t0 = t;
      if (!keep(t - t0)) continue;
    }
    lines.push_back(line);
  }
  in.close();
  fs::remove(imu_csv);  // a hard link: write a new file instead of through it
  std::ofstream out(imu_csv);
  for (const std::string& l : lines) out << l << "\n";
}

fs::path damagedCopy(const fs::path& source, const fs::path& target) {
  test::linkedCopy(source, target);
  const fs::path mav0 = target / "mav0";
  // IMU: drop 0.3 s of samples at t0 + 6 s.
  filterImu(mav0, [](std::int64_t dt) { return !(dt > 6'000'000'000 && dt < 6'300'000'000); });
  // Images: frame 100 of cam0 missing, frame 120 black (both cameras), frame 140 not a PNG.
  std::vector<fs::path> cam0;
  for (const auto& e : fs::directory_iterator(mav0 / "cam0" / "data")) cam0.push_back(e.path());
  std::sort(cam0.begin(), cam0.end());
  fs::remove(cam0[100]);
  for (const char* cam : {"cam0", "cam1"}) {
    const fs::path black = mav0 / cam / "data" / cam0[120].filename();
    fs::remove(black);
    EXPECT_TRUE(dataset::writeGrayPng(black, dataset::GrayImage(752, 480, 0)).ok());
  }
  const fs::path garbage = mav0 / "cam0" / "data" / cam0[140].filename();
  fs::remove(garbage);
  std::ofstream(garbage) << "this is not a PNG";
  return target;
}

TEST_F(AgentTest, BadInputIsReportedAndTrackingGoesOn) {
  const fs::path damaged = damagedCopy(sequence(), dir_->path() / "damaged" / "agent0");
  const std::atomic<bool> stop{false};
  AgentOptions o = options(damaged, "damaged_out");
  o.mode = AgentMode::kStereo;
  auto summary = runAgent(o, stop);
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  std::printf("%s", formatSummary(*summary).c_str());
  EXPECT_EQ(summary->frames, 240u);  // the missing image's frame is dropped when the dataset is opened
  EXPECT_GE(summary->imu_gaps, 1u);
  EXPECT_EQ(summary->unreadable_frames, 1u);
  // The black frame and the IMU gap cost a frame or two; the rest is tracked on the same map.
  EXPECT_GE(summary->tracked_frames, summary->frames - 6);
  EXPECT_EQ(summary->new_maps, 1u);
  const auto [ate_m, scale_error] = evaluate(summary->trajectory, damaged);
  std::printf("damaged sequence: ATE %.3f m, scale error %.2f %%\n", ate_m, scale_error);
  EXPECT_LT(ate_m, 0.1);
}

// A copy whose IMU starts `skip_s` seconds late: the first frames have no IMU sample at all.
fs::path imuStartsLateCopy(const fs::path& source, const fs::path& target, double skip_s) {
  test::linkedCopy(source, target);
  const auto skip_ns = static_cast<std::int64_t>(skip_s * 1e9);
  filterImu(target / "mav0", [skip_ns](std::int64_t dt) { return dt >= skip_ns; });
  return target;
}

TEST_F(AgentTest, ImuThatStartsAfterTheImagesIsReportedAndTrackingGoesOn) {
  // The first 2 s of frames have no IMU sample at all: each is an IMU gap, and no keyframe may take a
  // preintegration that silently skips them into the IMU initialisation.
  const fs::path cut = imuStartsLateCopy(sequence(), dir_->path() / "imu_cut" / "agent0", 2.0);
  const std::atomic<bool> stop{false};
  AgentOptions o = options(cut, "imu_cut_out");
  o.mode = AgentMode::kStereo;
  auto summary = runAgent(o, stop);
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  std::printf("%s", formatSummary(*summary).c_str());
  EXPECT_GE(summary->imu_gaps, 35u);  // about 40 frames before the IMU starts
  EXPECT_GT(summary->imu_initialised_at_s, 2.0);
  EXPECT_GE(summary->tracked_frames, summary->frames - 6);
  EXPECT_EQ(summary->new_maps, 1u);
  const auto [ate_m, scale_error] = evaluate(summary->trajectory, cut);
  std::printf("IMU from 2 s on: ATE %.3f m, scale error %.2f %%\n", ate_m, scale_error);
  EXPECT_LT(ate_m, 0.1);
}

TEST_F(AgentTest, InterruptedRunStillWritesItsOutputs) {
  std::atomic<bool> stop{false};
  AgentOptions o = options(sequence(), "interrupted");
  o.pace = Pace::kRealtime;
  std::thread stopper([&] {
    std::this_thread::sleep_for(std::chrono::seconds(3));
    stop.store(true);
  });
  int policy_before = -1;
  sched_param param_before{};
  ASSERT_EQ(pthread_getschedparam(pthread_self(), &policy_before, &param_before), 0);
  const int nice_before = getpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)));
  auto summary = runAgent(o, stop);
  stopper.join();
  ASSERT_TRUE(summary.ok()) << summary.error().toString();
  EXPECT_TRUE(summary->interrupted);
  // The calling thread ran tracking (SCHED_FIFO where allowed) for the run only.
  int policy_after = -1;
  sched_param param_after{};
  ASSERT_EQ(pthread_getschedparam(pthread_self(), &policy_after, &param_after), 0);
  EXPECT_EQ(policy_after, policy_before);
  EXPECT_EQ(param_after.sched_priority, param_before.sched_priority);
  EXPECT_EQ(getpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid))), nice_before);
  EXPECT_LT(summary->frames, 241u);
  EXPECT_GT(summary->tracked_frames, 20u);
  Diagnostics diagnostics;
  auto written = dataset::readTrajectory(summary->trajectory, {}, diagnostics);
  ASSERT_TRUE(written.ok()) << written.error().toString();
  // Every tracked frame, and the frame that started the map (its keyframe is the map's origin).
  EXPECT_EQ(written->size(), summary->tracked_frames + summary->new_maps);
}

TEST_F(AgentTest, RefusesWhatCannotWork) {
  const std::atomic<bool> stop{false};
  AgentOptions o = options(dir_->path() / "no-such-sequence", "refused");
  auto missing = runAgent(o, stop);
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.error().message().find("no-such-sequence"), std::string::npos) << missing.error().message();

  // A cam1 calibrated at another resolution than cam0: refused at start, not frame by frame.
  const fs::path other_size = dir_->path() / "cam1_other_size" / "agent0";
  test::linkedCopy(sequence(), other_size);
  const fs::path cam1_yaml = other_size / "mav0" / "cam1" / "sensor.yaml";
  auto cam1 = dataset::readCameraCalibration(cam1_yaml, "cam1");
  ASSERT_TRUE(cam1.ok());
  cam1->width = 640;
  cam1->cx = 320.0;
  fs::remove(cam1_yaml);  // a hard link: write a new file instead of through it
  ASSERT_TRUE(dataset::writeCameraCalibration(cam1_yaml, *cam1).ok());
  AgentOptions stereo = options(other_size, "refused_cam1");
  stereo.mode = AgentMode::kStereo;
  auto mismatched = runAgent(stereo, stop);
  ASSERT_FALSE(mismatched.ok());
  EXPECT_NE(mismatched.error().message().find("cam1 is 640x480 but cam0 is 752x480"), std::string::npos)
      << mismatched.error().message();

  AgentOptions bad = options(sequence(), "refused");
  bad.tracking.orb.max_features = 100000;
  auto refused = runAgent(bad, stop);
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.error().message().find("max_features"), std::string::npos) << refused.error().message();
}

// Pose by pose, the largest position difference between two TUM trajectories of the same frames [m]; +inf when
// they hold different frames.
double largestDifferenceM(const fs::path& a, const fs::path& b) {
  Diagnostics diagnostics;
  auto ta = dataset::readTrajectory(a, {}, diagnostics);
  auto tb = dataset::readTrajectory(b, {}, diagnostics);
  if (!ta.ok() || !tb.ok() || ta->size() != tb->size()) return std::numeric_limits<double>::infinity();
  double largest = 0.0;
  for (std::size_t i = 0; i < ta->size(); ++i) {
    if ((*ta)[i].t_ns != (*tb)[i].t_ns) return std::numeric_limits<double>::infinity();
    largest = std::max(largest, ((*ta)[i].T_w_b.translation() - (*tb)[i].T_w_b.translation()).norm());
  }
  return largest;
}

// Kalibr's camera chain and IMU file, written from the sequence's own sensor.yaml files, describe the same rig:
// the run with them tracks the same trajectory. Not to the bit: Kalibr stores the inverse transform (T_cam_imu),
// and inverting it back rounds in the last bits of the extrinsics; 1 um leaves room for that and catches any
// real difference (a wrong frame convention moves poses by centimetres).
TEST_F(AgentTest, KalibrFilesOfTheSameRigGiveTheSameTrajectory) {
  const fs::path mav0 = sequence() / "mav0";
  auto cam0 = dataset::readCameraCalibration(mav0 / "cam0" / "sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(mav0 / "cam1" / "sensor.yaml", "cam1");
  auto imu = dataset::readImuCalibration(mav0 / "imu0" / "sensor.yaml");
  ASSERT_TRUE(cam0.ok() && cam1.ok() && imu.ok());
  const fs::path camchain = dir_->path() / "kalibr" / "camchain-imucam.yaml";
  const fs::path imu_yaml = dir_->path() / "kalibr" / "imu.yaml";
  test::writeTextFile(camchain, test::kalibrCamchainYaml(*cam0, *cam1));
  test::writeTextFile(imu_yaml, test::kalibrImuYaml(*imu));

  const std::atomic<bool> stop{false};
  AgentOptions own = options(sequence(), "sensor_yaml");
  own.mode = AgentMode::kStereo;
  AgentOptions kalibr = options(sequence(), "kalibr");
  kalibr.mode = AgentMode::kStereo;
  kalibr.calibration = camchain;
  kalibr.imu_calibration = imu_yaml;
  auto a = runAgent(own, stop);
  auto b = runAgent(kalibr, stop);
  ASSERT_TRUE(a.ok()) << a.error().toString();
  ASSERT_TRUE(b.ok()) << b.error().toString();
  EXPECT_EQ(a->tracked_frames, b->tracked_frames);
  EXPECT_EQ(a->keyframes, b->keyframes);
  const double refined_m = largestDifferenceM(a->trajectory, b->trajectory);
  const double live_m =
      largestDifferenceM(own.output / "trajectory_online.txt", kalibr.output / "trajectory_online.txt");
  std::printf("sensor.yaml against Kalibr: largest difference %.3g m refined, %.3g m live\n", refined_m, live_m);
  EXPECT_LT(refined_m, 1e-6);
  EXPECT_LT(live_m, 1e-6);

  // A chain for another camera is refused, naming the file and what differs.
  dataset::CameraCalibration other = *cam0;
  other.width = 640;
  other.cx = 320.0;
  const fs::path wrong = dir_->path() / "kalibr" / "other_camera.yaml";
  test::writeTextFile(wrong, test::kalibrCamchainYaml(other, std::nullopt));
  AgentOptions refused = options(sequence(), "kalibr_refused");
  refused.calibration = wrong;
  auto r = runAgent(refused, stop);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message().find("other_camera.yaml: cam0 is calibrated at 640x480 but the recording's cam0 images "
                                     "are 752x480"),
            std::string::npos)
      << r.error().message();
}

// A 6 s stereo loop rendered twice, once synchronised and once with the camera clock 30 ms behind the IMU's (the
// simulator stamps the same images 30 ms early), with Kalibr files for the synchronised rig and for the shift.
struct ClockShiftedRig {
  fs::path synced;
  fs::path shifted;
  fs::path camchain;          // timeshift_cam_imu 0
  fs::path camchain_shifted;  // timeshift_cam_imu 0.030
  fs::path imu_yaml;
};

ClockShiftedRig renderClockShiftedRig(const fs::path& dir) {
  ClockShiftedRig rig{dir / "clock_synced", dir / "clock_shifted", dir / "clock_kalibr" / "camchain-imucam.yaml",
                      dir / "clock_kalibr" / "camchain-shifted.yaml", dir / "clock_kalibr" / "imu.yaml"};
  if (fs::exists(rig.camchain_shifted)) return rig;  // rendered by an earlier test of this process
  auto plan = sim::planPreset("loop", 4, 6.0);
  EXPECT_TRUE(plan.ok()) << plan.error().toString();
  if (!plan.ok()) return rig;
  for (const auto& [folder, shift_ns] :
       {std::pair{rig.synced, std::int64_t{0}}, std::pair{rig.shifted, std::int64_t{30'000'000}}}) {
    sim::MissionWriterOptions writer = sim::defaultWriterOptions();
    writer.out_dir = folder;
    writer.seed = 4;
    writer.stereo = true;
    writer.camera_time_shift_ns = shift_ns;
    const Status written = sim::writeMission(*plan, writer);
    EXPECT_TRUE(written.ok()) << written.error().toString();
  }
  const Status kalibr = test::writeKalibrFilesOf(rig.synced / "agent0", rig.camchain, rig.imu_yaml);
  EXPECT_TRUE(kalibr.ok()) << kalibr.error().toString();
  const fs::path mav0 = rig.synced / "agent0" / "mav0";
  auto cam0 = dataset::readCameraCalibration(mav0 / "cam0" / "sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(mav0 / "cam1" / "sensor.yaml", "cam1");
  EXPECT_TRUE(cam0.ok() && cam1.ok());
  if (cam0.ok() && cam1.ok()) test::writeTextFile(rig.camchain_shifted, test::kalibrCamchainYaml(*cam0, *cam1, 0.030));
  return rig;
}

// With the shift given as Kalibr's timeshift_cam_imu the agent sees exactly the synchronised recording, and without
// it the trajectory is another, and worse.
TEST_F(AgentTest, AKnownCameraClockShiftGivenAsTimeshiftGivesTheSynchronisedTrajectory) {
  const ClockShiftedRig rig = renderClockShiftedRig(dir_->path());
  const std::atomic<bool> stop{false};
  const auto run = [&](const fs::path& sequence, const fs::path& chain, const std::string& name) {
    AgentOptions o = options(sequence / "agent0", name);
    o.mode = AgentMode::kStereo;
    o.calibration = chain;
    o.imu_calibration = rig.imu_yaml;
    o.imu_noise_inflation = 1.0;  // simulated noise, as the sensor.yaml files say
    auto r = runAgent(o, stop);
    EXPECT_TRUE(r.ok()) << r.error().toString();
    return o.output;
  };
  const fs::path reference = run(rig.synced, rig.camchain, "clock_reference");
  const fs::path corrected = run(rig.shifted, rig.camchain_shifted, "clock_corrected");
  const fs::path ignored = run(rig.shifted, rig.camchain, "clock_ignored");
  const std::string expected = test::readTextFile(reference / "trajectory.txt");
  EXPECT_FALSE(expected.empty());
  EXPECT_EQ(test::readTextFile(corrected / "trajectory.txt"), expected);
  // Ignored, the frames carry their camera stamps: 30 ms early against the IMU and the ground truth.
  const double ate_synced_m = evaluate(reference / "trajectory.txt", rig.synced / "agent0").first;
  const double ate_ignored_m = evaluate(ignored / "trajectory.txt", rig.synced / "agent0").first;
  std::printf("ATE synchronised %.4f m, 30 ms shift ignored %.4f m\n", ate_synced_m, ate_ignored_m);
  EXPECT_GT(ate_ignored_m, 1.5 * ate_synced_m);
}

// The same 30 ms not given but estimated (imu.estimate_time_offset, from 0): the IMU initialisation finds it with
// the gyro bias, re-times the keyframes made before it, and local BA keeps it; the frames then carry it, and the
// run is within 1.2x of the synchronised one (the 2 s tracked before the estimate included).
TEST_F(AgentTest, AnUnknownCameraClockShiftIsEstimatedAndTheFramesCarryIt) {
  const ClockShiftedRig rig = renderClockShiftedRig(dir_->path());
  const std::atomic<bool> stop{false};
  const auto run = [&](const fs::path& sequence, bool estimate, const std::string& name) {
    AgentOptions o = options(sequence / "agent0", name);
    o.mode = AgentMode::kStereo;
    o.calibration = rig.camchain;
    o.imu_calibration = rig.imu_yaml;
    o.imu_noise_inflation = 1.0;
    o.mapping.ba.estimate_time_offset = estimate;
    auto r = runAgent(o, stop);
    EXPECT_TRUE(r.ok()) << r.error().toString();
    return r.ok() ? *r : AgentRunSummary{};
  };
  const AgentRunSummary synced = run(rig.synced, false, "clock_synced_fixed");
  const AgentRunSummary held = run(rig.shifted, false, "clock_held");
  const AgentRunSummary estimated = run(rig.shifted, true, "clock_estimated");
  const AgentRunSummary synced_estimated = run(rig.synced, true, "clock_synced_estimated");
  const double ate_synced_m = evaluate(synced.trajectory, rig.synced / "agent0").first;
  const double ate_held_m = evaluate(held.trajectory, rig.synced / "agent0").first;
  const double ate_estimated_m = evaluate(estimated.trajectory, rig.synced / "agent0").first;
  const double ate_synced_estimated_m = evaluate(synced_estimated.trajectory, rig.synced / "agent0").first;
  std::printf(
      "ATE synchronised %.4f m (estimating %.4f m); 30 ms shift held at 0 %.4f m, estimated %.4f m (estimate %.2f ms; "
      "on the synchronised rig %.2f ms); IMU initialised at %.2f s (synchronised %.2f s)\n",
      ate_synced_m, ate_synced_estimated_m, ate_held_m, ate_estimated_m, estimated.time_offset_ms,
      synced_estimated.time_offset_ms, estimated.imu_initialised_at_s, synced_estimated.imu_initialised_at_s);
  EXPECT_NEAR(estimated.time_offset_ms, 30.0, 1.0);
  EXPECT_NEAR(synced_estimated.time_offset_ms, 0.0, 1.0);
  EXPECT_NEAR(held.time_offset_ms, 0.0, 1e-9);
  EXPECT_LT(ate_estimated_m, 0.5 * ate_held_m);
  EXPECT_LT(ate_estimated_m, 1.2 * ate_synced_m);
  // The first images, stamped 30 ms early, came before the IMU's first sample, and the first frame's interval lacks
  // IMU: estimating, that costs nothing beyond what estimating costs on the synchronised rig. The first keyframe is
  // linked with the first sample held back to it and again once re-timed into the IMU, so the IMU initialisation
  // comes at the same keyframe and the two runs score alike.
  EXPECT_NEAR(estimated.imu_initialised_at_s, synced_estimated.imu_initialised_at_s, 0.05);
  EXPECT_LT(ate_estimated_m, 1.05 * ate_synced_estimated_m);
  // The frames' times carry the estimate: the shifted recording's last frame, stamped 30 ms early by the camera, is
  // written at the synchronised one's time.
  const auto last_t_s = [](const fs::path& trajectory) {
    const std::string text = test::readTextFile(trajectory);
    const std::size_t line = text.rfind('\n', text.size() - 2);
    return std::stod(text.substr(line == std::string::npos ? 0 : line + 1));
  };
  EXPECT_NEAR(last_t_s(estimated.trajectory), last_t_s(synced.trajectory), 0.001);
  EXPECT_TRUE(fs::exists(estimated.trajectory.parent_path() / "time_offset.csv"));

  // So do the keyframes made before the estimate, which the IMU initialisation re-times, and the frames hung from
  // them: every keyframe and frame the run wrote lies within 1.5 ms of a frame time of the synchronised rig. (With
  // a negative offset the first keyframe's image may be older than the first IMU sample and keep its time; this
  // offset is positive.)
  Diagnostics diagnostics;
  auto synced_frames = dataset::readTrajectory(synced.trajectory, {}, diagnostics);
  ASSERT_TRUE(synced_frames.ok()) << synced_frames.error().toString();
  const auto off_the_synced_times = [&](const fs::path& path) {
    auto written = dataset::readTrajectory(path, {}, diagnostics);
    EXPECT_TRUE(written.ok()) << path;
    int off = 0;
    for (const auto& pose : written.ok() ? *written : dataset::Trajectory{}) {
      const auto nearest =
          std::min_element(synced_frames->begin(), synced_frames->end(), [&](const auto& a, const auto& b) {
            return std::llabs(a.t_ns - pose.t_ns) < std::llabs(b.t_ns - pose.t_ns);
          });
      if (std::llabs(nearest->t_ns - pose.t_ns) > 1'500'000) ++off;
    }
    return off;
  };
  EXPECT_LE(off_the_synced_times(estimated.keyframe_trajectory), 0);
  EXPECT_LE(off_the_synced_times(estimated.trajectory), 0);
}

// The real V1_01 excerpt as its EuRoC folder and as a ROS 2 bag in MCAP, both with the same Kalibr files: the same
// input sample for sample, so at --pace sync the same trajectory to the byte.
TEST_F(AgentTest, TheSameRecordingAsAFolderAndAsAnMcapBagGivesTheSameTrajectory) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  const fs::path mav0 = excerpt / "mav0";
  auto cam0 = dataset::readCameraCalibration(mav0 / "cam0" / "sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(mav0 / "cam1" / "sensor.yaml", "cam1");
  auto imu = dataset::readImuCalibration(mav0 / "imu0" / "sensor.yaml");
  ASSERT_TRUE(cam0.ok() && cam1.ok() && imu.ok());
  const fs::path camchain = dir_->path() / "v101_kalibr" / "camchain-imucam.yaml";
  const fs::path imu_yaml = dir_->path() / "v101_kalibr" / "imu.yaml";
  test::writeTextFile(camchain, test::kalibrCamchainYaml(*cam0, *cam1));
  test::writeTextFile(imu_yaml, test::kalibrImuYaml(*imu));
  const fs::path bag = dir_->path() / "v101.mcap";
  const Status written = test::writeEurocAsMcap(excerpt, bag);
  ASSERT_TRUE(written.ok()) << written.error().toString();

  const std::atomic<bool> stop{false};
  AgentOptions folder = options(excerpt, "v101_folder");
  AgentOptions mcap = options(fs::path(), "v101_mcap");
  mcap.mcap = bag;
  for (AgentOptions* o : {&folder, &mcap}) {
    o->mode = AgentMode::kStereo;
    o->calibration = camchain;
    o->imu_calibration = imu_yaml;
  }
  auto a = runAgent(folder, stop);
  auto b = runAgent(mcap, stop);
  ASSERT_TRUE(a.ok()) << a.error().toString();
  ASSERT_TRUE(b.ok()) << b.error().toString();
  EXPECT_GT(a->tracked_frames, 80u);
  for (const char* file : {"trajectory.txt", "trajectory_online.txt", "keyframes.txt"}) {
    const std::string from_folder = test::readTextFile(folder.output / file);
    EXPECT_FALSE(from_folder.empty()) << file;
    EXPECT_EQ(from_folder, test::readTextFile(mcap.output / file)) << file;
  }
}

// At --pace fast with the whole agent on one core, tracking outruns mapping: keyframes are held back, and once one
// is overdue tracking asks mapping to yield, which cuts its local BAs short. The wiring with real threads
// and iceoryx: requests counted on tracking's side, BAs cut short on mapping's, one map throughout. With the request
// delay beyond the sequence's length, tracking never asks.
TEST_F(AgentTest, OnOneCoreAtFastPaceTrackingAsksTheLaggingMapperToYield) {
  cpu_set_t saved;
  ASSERT_EQ(sched_getaffinity(0, sizeof(saved), &saved), 0);
  int cpu = 0;
  while (cpu < CPU_SETSIZE && !CPU_ISSET(cpu, &saved)) ++cpu;
  ASSERT_LT(cpu, CPU_SETSIZE);
  cpu_set_t one;
  CPU_ZERO(&one);
  CPU_SET(cpu, &one);
  // This thread only; the agent's threads, started from it, inherit the one core.
  ASSERT_EQ(sched_setaffinity(0, sizeof(one), &one), 0);
  struct RestoreAffinity {
    cpu_set_t set;
    ~RestoreAffinity() { (void)sched_setaffinity(0, sizeof(set), &set); }
  } const restore{saved};

  const std::atomic<bool> stop{false};
  AgentOptions o = options(sequence(), "fast_one_core");
  o.mode = AgentMode::kStereo;
  o.pace = Pace::kFast;
  auto asked = runAgent(o, stop);
  ASSERT_TRUE(asked.ok()) << asked.error().toString();
  std::printf("asked to yield:\n%s", formatSummary(*asked).c_str());
  EXPECT_EQ(asked->new_maps, 1u);
  // Frames lost once tracking has started (the first few wait for the first map, longer when mapping lags).
  EXPECT_LE(asked->lost_frames * 100, asked->frames) << asked->tracked_frames << " of " << asked->frames << " tracked";
  EXPECT_GT(asked->deferred_keyframes, 0u) << "mapping kept up on one core: the test no longer starves it";
  EXPECT_GT(asked->mapping_yield_requests, 0u);
  EXPECT_LT(asked->mapping_yield_requests, asked->deferred_keyframes) << "asked at once, not after the delay";
  EXPECT_GT(asked->local_ba_yielded_to_tracking, 0u) << "mapping did not see tracking's requests";
  EXPECT_LE(asked->local_ba_yielded_to_tracking, asked->local_ba_stopped_early + asked->local_ba_skipped);
  const auto [ate_m, scale_error] = evaluate(asked->trajectory, sequence());
  std::printf("fast pace on one core, asking mapping to yield: ATE %.3f m, scale error %.2f %%\n", ate_m, scale_error);
  EXPECT_LT(ate_m, 0.05);

  o.output = dir_->path() / "fast_one_core_never_asks";
  o.tracking.lag.yield_request_after_s = 1e6;
  auto never = runAgent(o, stop);
  ASSERT_TRUE(never.ok()) << never.error().toString();
  std::printf("never asked:\n%s", formatSummary(*never).c_str());
  EXPECT_GT(never->deferred_keyframes, 0u);
  EXPECT_EQ(never->mapping_yield_requests, 0u);
  EXPECT_EQ(never->local_ba_yielded_to_tracking, 0u);
}
}  // namespace
}  // namespace cvislam::agent
