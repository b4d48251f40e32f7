// Missions as a whole: readable EuRoC output, determinism, path properties, and the command line.
#include <sys/wait.h>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <map>
#include <numbers>
#include <string>

#include <gtest/gtest.h>

#include "common/dataset/euroc.hpp"
#include "common/dataset/trajectory_io.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::sim {
namespace {

struct CommandResult {
  int exit_code = -1;
  std::string output;
};

CommandResult runSim(const std::string& arguments, const std::string& env = "") {
  const std::string command = env + " " + CVISLAM_SIM_BINARY + " " + arguments + " 2>&1";
  CommandResult result;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return result;
  std::array<char, 4096> buffer{};
  while (std::fgets(buffer.data(), static_cast<int>(buffer.size()), pipe) != nullptr) result.output += buffer.data();
  const int status = pclose(pipe);
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return result;
}

std::string fileBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Relative path -> bytes of every file below root.
std::map<std::string, std::string> treeBytes(const std::filesystem::path& root) {
  std::map<std::string, std::string> out;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(root)) {
    if (entry.is_regular_file()) out[std::filesystem::relative(entry.path(), root).string()] = fileBytes(entry.path());
  }
  return out;
}

TEST(CvislamSim, WritesReadableEurocDatasetsOnePerAgent) {
  const test::TempDir dir;
  const CommandResult r = runSim("--preset overlap2 --duration 1 --seed 4 --stereo -q --out " + (dir / "m").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  for (const char* agent : {"agent0", "agent1"}) {
    auto seq = dataset::EurocSequence::open(dir / "m" / agent);
    ASSERT_TRUE(seq.ok()) << seq.error().toString();
    EXPECT_TRUE(seq->diagnostics().empty());
    EXPECT_EQ(seq->cam0().frames.size(), 21U);  // 1 s at 20 Hz, both ends included
    ASSERT_NE(seq->cam1(), nullptr);
    EXPECT_EQ(seq->stereoPairCount(), 21U);
    EXPECT_EQ(seq->imu().size(), 201U);
    EXPECT_EQ(seq->groundTruth().size(), 201U);
    EXPECT_EQ(seq->cam0().calibration.width, 752);
  }
  EXPECT_TRUE(std::filesystem::exists(dir / "m" / "mission.yaml"));
  EXPECT_FALSE(std::filesystem::exists(dir / "m" / "agent2"));
}

TEST(CvislamSim, SamePresetAndSeedGiveByteIdenticalFilesAndAnotherSeedDoesNot) {
  const test::TempDir dir;
  const std::string common = " --preset loop --duration 0.5 --pixel-noise 2 --exposure 0.2 -q --out ";
  ASSERT_EQ(runSim("--seed 8" + common + (dir / "a").string()).exit_code, 0);
  ASSERT_EQ(runSim("--seed 8" + common + (dir / "b").string()).exit_code, 0);
  ASSERT_EQ(runSim("--seed 9" + common + (dir / "c").string()).exit_code, 0);
  const auto a = treeBytes(dir / "a"), b = treeBytes(dir / "b"), c = treeBytes(dir / "c");
  EXPECT_GT(a.size(), 10U);
  EXPECT_TRUE(a == b);
  const std::string image = "agent0/mav0/cam0/data/1600000000000000000.png";
  ASSERT_TRUE(a.count(image) == 1 && c.count(image) == 1);
  EXPECT_NE(a.at(image), c.at(image));
}

TEST(CvislamSim, TheFingerprintFollowsThePlanAndWritesNothing) {
  const auto fingerprint = [](const std::string& arguments) {
    const CommandResult r = runSim(arguments + " --fingerprint");
    EXPECT_EQ(r.exit_code, 0) << r.output;
    EXPECT_EQ(r.output.size(), 17U) << "16 hex digits and a newline: " << r.output;
    return r.output;
  };
  const std::string hall = fingerprint("--preset hall4 --seed 1 --duration 30");
  EXPECT_EQ(fingerprint("--preset hall4 --seed 1 --duration 30"), hall);
  EXPECT_NE(fingerprint("--preset hall4 --seed 2 --duration 30"), hall) << "another seed, another layout";
  EXPECT_NE(fingerprint("--preset hall4 --seed 1 --duration 20"), hall);
  EXPECT_NE(fingerprint("--preset hall8 --seed 1 --duration 30"), hall);
  const CommandResult no_out = runSim("--preset loop --duration 1");
  EXPECT_EQ(no_out.exit_code, 2);
  EXPECT_NE(no_out.output.find("--out"), std::string::npos) << no_out.output;
}

TEST(CvislamSim, RenderingAgentsOnSeveralThreadsWritesTheSameFilesAsOne) {
  const test::TempDir dir;
  const std::string common = " --preset overlap2 --duration 0.3 --seed 3 --pixel-noise 2 -q --out ";
  ASSERT_EQ(runSim("--threads 1" + common + (dir / "one").string()).exit_code, 0);
  ASSERT_EQ(runSim("--threads 2" + common + (dir / "two").string()).exit_code, 0);
  const auto one = treeBytes(dir / "one");
  EXPECT_GT(one.size(), 10U);
  EXPECT_TRUE(one == treeBytes(dir / "two"));
}

TEST(CvislamSim, RefusesExistingOutputUnlessOverwriteAndThenLeavesNoStaleImages) {
  const test::TempDir dir;
  const std::string out = " -q --out " + (dir / "m").string();
  ASSERT_EQ(runSim("--preset loop --duration 0.5" + out).exit_code, 0);
  const CommandResult again = runSim("--preset loop --duration 0.2" + out);
  EXPECT_EQ(again.exit_code, 1);
  EXPECT_NE(again.output.find("--overwrite"), std::string::npos) << again.output;
  ASSERT_EQ(runSim("--preset loop --duration 0.2 --overwrite" + out).exit_code, 0);
  auto seq = dataset::EurocSequence::open(dir / "m" / "agent0");
  ASSERT_TRUE(seq.ok());
  const auto images = std::distance(std::filesystem::directory_iterator(dir / "m/agent0/mav0/cam0/data"),
                                    std::filesystem::directory_iterator{});
  EXPECT_EQ(images, 5);  // 0.2 s at 20 Hz, both ends
  EXPECT_EQ(seq->cam0().frames.size(), 5U);
}

TEST(CvislamSim, ReplayFollowsTheGivenFlight) {
  // A flight to replay, written as a TUM file: 4 s of the aggressive preset at 200 Hz.
  const test::TempDir dir;
  MissionPlanOptions plan_options;
  plan_options.preset = "aggressive";
  plan_options.duration_s = 4.0;
  auto source = planMission(plan_options);
  ASSERT_TRUE(source.ok());
  constexpr std::int64_t kStartNs = 1'403'636'580'838'555'000;
  dataset::Trajectory flight;
  for (int k = 0; k <= 800; ++k) {
    flight.push_back({kStartNs + std::int64_t{5'000'000} * k, source->agents[0].trajectory.state(k / 200.0).T_w_b});
  }
  ASSERT_TRUE(dataset::writeTrajectory(dir / "flight.txt", flight, dataset::TrajectoryFormat::kTum).ok());

  const CommandResult r = runSim("--replay " + (dir / "flight.txt").string() +
                                 " --duration 3 --no-imu-noise -q --out " + (dir / "m").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  auto seq = dataset::EurocSequence::open(dir / "m" / "agent0");
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  ASSERT_EQ(seq->groundTruth().size(), 601U);
  double worst_m = 0.0, worst_rad = 0.0;
  for (std::size_t k = 0; k < seq->groundTruth().size(); ++k) {
    const geometry::SE3d& replayed = seq->groundTruth()[k].T_w_b;
    worst_m = std::max(worst_m, (replayed.translation() - flight[k].T_w_b.translation()).norm());
    worst_rad = std::max(worst_rad, (flight[k].T_w_b.so3().inverse() * replayed.so3()).log().norm());
  }
  // The replay smooths (knots every 0.1 s), so it follows the flight closely but not exactly.
  EXPECT_LT(worst_m, 0.01);
  EXPECT_LT(worst_rad, 0.5 * std::numbers::pi / 180.0);
}

TEST(CvislamSim, BadCommandLinesExitWith2) {
  EXPECT_EQ(runSim("--preset nosuchpreset --out /tmp/x").exit_code, 2);
  EXPECT_EQ(runSim("--preset loop").exit_code, 2);                              // no --out
  EXPECT_EQ(runSim("--out /tmp/x").exit_code, 2);                               // neither preset nor replay
  EXPECT_EQ(runSim("--preset loop --replay a.txt --out /tmp/x").exit_code, 2);  // both
  EXPECT_EQ(runSim("--preset loop --duration -1 --out /tmp/x").exit_code, 2);
}

TEST(CvislamSim, EurocMhWithoutDataNamesTheMissingFile) {
  const test::TempDir dir;
  const CommandResult r = runSim("--preset euroc-mh --duration 1 -q --out " + (dir / "m").string(),
                                 "CVISLAM_DATA_DIR=" + dir.path().string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.output.find("MH_01_easy.txt"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("CVISLAM_DATA_DIR"), std::string::npos) << r.output;
  const CommandResult replay =
      runSim("--replay " + (dir / "nope.txt").string() + " --duration 1 -q --out " + (dir / "r").string());
  EXPECT_EQ(replay.exit_code, 1);
  EXPECT_NE(replay.output.find("nope.txt"), std::string::npos) << replay.output;
}

TEST(MissionWriter, PixelNoiseHasTheRequestedSigmaAndExposureChangesBrightnessSmoothly) {
  const test::TempDir dir;
  MissionPlanOptions plan_options;
  plan_options.preset = "loop";
  plan_options.duration_s = 0.5;
  auto plan = planMission(plan_options);
  ASSERT_TRUE(plan.ok());
  constexpr double kSigma = 3.0;
  constexpr double kExposure = 0.3;
  for (const char* variant : {"clean", "noisy", "exposure"}) {
    MissionWriterOptions options = defaultWriterOptions();
    options.out_dir = dir / variant;
    options.texture.texel_size_m = 0.02;
    options.pixel_noise_sigma = std::string(variant) == "noisy" ? kSigma : 0.0;
    options.exposure_amplitude = std::string(variant) == "exposure" ? kExposure : 0.0;
    ASSERT_TRUE(writeMission(*plan, options).ok()) << variant;
  }
  auto clean = dataset::EurocSequence::open(dir / "clean" / "agent0");
  auto noisy = dataset::EurocSequence::open(dir / "noisy" / "agent0");
  auto exposed = dataset::EurocSequence::open(dir / "exposure" / "agent0");
  ASSERT_TRUE(clean.ok() && noisy.ok() && exposed.ok());
  double sum = 0.0, sum_sq = 0.0, count = 0.0;
  std::vector<double> gain;
  for (std::size_t f = 0; f < clean->cam0().frames.size(); ++f) {
    auto a = clean->loadImage(0, f);
    auto b = noisy->loadImage(0, f);
    auto c = exposed->loadImage(0, f);
    ASSERT_TRUE(a.ok() && b.ok() && c.ok());
    double mean_a = 0.0, mean_c = 0.0;
    for (std::size_t i = 0; i < a->pixels.size(); ++i) {
      if (a->pixels[i] > 10 && a->pixels[i] < 245) {  // away from clipping
        const double d = static_cast<double>(b->pixels[i]) - static_cast<double>(a->pixels[i]);
        sum += d;
        sum_sq += d * d;
        count += 1.0;
      }
      mean_a += a->pixels[i];
      mean_c += c->pixels[i];
    }
    gain.push_back(mean_c / mean_a);
  }
  const double mean = sum / count;
  EXPECT_NEAR(mean, 0.0, 0.05);
  EXPECT_NEAR(std::sqrt(sum_sq / count - mean * mean), kSigma, 0.1 * kSigma);
  for (std::size_t f = 0; f < gain.size(); ++f) {
    EXPECT_GT(gain[f], 1.0 - kExposure - 0.05);
    EXPECT_LT(gain[f], 1.0 + kExposure + 0.05);
    if (f > 0) {
      EXPECT_LT(std::abs(gain[f] - gain[f - 1]), 0.05) << "exposure jumps at frame " << f;
    }
  }
  EXPECT_GT(std::abs(gain.front() - 1.0) + std::abs(gain.back() - 1.0), 0.01);  // it does change brightness
}

// ---------------------------------------------------------------------------------------- path properties

double distanceToBox(const Box& b, const Eigen::Vector3d& p) {
  return (b.min_w - p).cwiseMax(p - b.max_w).cwiseMax(0.0).norm();
}

void expectUavLikePaths(const MissionPlan& plan, double max_speed_mps) {
  for (const AgentPlan& agent : plan.agents) {
    double path_m = 0.0, max_speed = 0.0;
    Eigen::Vector3d previous = agent.trajectory.state(0.0).T_w_b.translation();
    for (double t = 0.0; t <= plan.duration_s; t += 0.05) {
      const KinematicState s = agent.trajectory.state(t);
      const Eigen::Vector3d p = s.T_w_b.translation();
      path_m += (p - previous).norm();
      previous = p;
      max_speed = std::max(max_speed, s.v_w.norm());
      ASSERT_TRUE((p.array() > plan.layout.hall.min_w.array() + 0.5).all() &&
                  (p.array() < plan.layout.hall.max_w.array() - 0.5).all())
          << agent.name << " leaves the hall at t=" << t;
      for (const Box& b : plan.layout.obstacles) ASSERT_GT(distanceToBox(b, p), 0.5) << agent.name << " t=" << t;
    }
    // Like a UAV with a forward camera, it mostly looks where it flies (camera axis = body z).
    int fast = 0, forward = 0;
    for (double t = 0.0; t <= plan.duration_s; t += 0.1) {
      const KinematicState s = agent.trajectory.state(t);
      const Eigen::Vector2d v = s.v_w.head<2>();
      if (v.norm() < 0.5) continue;
      ++fast;
      const Eigen::Vector2d look = s.T_w_b.rotationMatrix().col(2).head<2>();
      if (look.normalized().dot(v.normalized()) > std::cos(75.0 * std::numbers::pi / 180.0)) ++forward;
    }
    EXPECT_GT(forward, 0.8 * fast) << plan.preset << " " << agent.name << " flies sideways or backwards";
    const double mean_speed = path_m / plan.duration_s;
    EXPECT_GE(mean_speed, 0.5) << plan.preset << " " << agent.name;
    EXPECT_LE(mean_speed, 2.0) << plan.preset << " " << agent.name;
    EXPECT_LE(max_speed, max_speed_mps) << plan.preset << " " << agent.name;
    // Motion-rich start: the first 3 s rotate about every axis.
    Eigen::Vector3d peak_rate = Eigen::Vector3d::Zero();
    for (double t = 0.0; t <= 3.0; t += 0.05)
      peak_rate = peak_rate.cwiseMax(agent.trajectory.state(t).omega_b.cwiseAbs());
    EXPECT_GT(peak_rate.minCoeff(), 0.2) << plan.preset << " " << agent.name;
  }
}

TEST(MissionPlans, EveryPresetFliesLikeAUavInsideTheHallAndClearOfObstacles) {
  for (const std::string preset : {"loop", "overlap2", "hall4", "hall8", "aggressive"}) {
    MissionPlanOptions options;
    options.preset = preset;
    options.seed = 2;
    auto plan = planMission(options);
    ASSERT_TRUE(plan.ok()) << plan.error().toString();
    EXPECT_EQ(plan->agents.size(), preset == "hall8" ? 8U : preset == "hall4" ? 4U : preset == "overlap2" ? 2U : 1U);
    expectUavLikePaths(*plan, preset == "aggressive" ? 2.8 : 2.0);
    EXPECT_GT(plan->layout.obstacles.size(), 30U) << preset;
  }
}

TEST(MissionPlans, HallAgentsFlyBothWaysRoundTheRingSoThatEveryPlaceIsSeenInBothDirections) {
  MissionPlanOptions options;
  options.preset = "hall8";
  options.seed = 1;
  auto plan = planMission(options);
  ASSERT_TRUE(plan.ok()) << plan.error().toString();
  // The sense of travel round the hall's centre (+1 counter-clockwise) from the angular momentum about z.
  const auto sense = [](const AgentPlan& agent, double t) {
    const KinematicState s = agent.trajectory.state(t);
    const Eigen::Vector3d p = s.T_w_b.translation();
    return p.x() * s.v_w.y() - p.y() * s.v_w.x() > 0.0 ? 1 : -1;
  };
  for (std::size_t i = 0; i < plan->agents.size(); ++i) {
    const AgentPlan& agent = plan->agents[i];
    const double turn_s = 24.0 + 2.0 * static_cast<double>(i);
    const int before = sense(agent, turn_s - 4.0), after = sense(agent, turn_s + 9.0);
    EXPECT_EQ(before, i % 2 == 0 ? 1 : -1) << agent.name;
    EXPECT_EQ(after, -before) << agent.name << " turns round after " << turn_s << " s";
  }
}

TEST(MissionPlans, LoopRevisitsItsStartAndOverlap2SharesAboutAThird) {
  MissionPlanOptions options;
  options.preset = "loop";
  auto loop = planMission(options);
  ASSERT_TRUE(loop.ok());
  const Eigen::Vector3d start = loop->agents[0].trajectory.state(0.0).T_w_b.translation();
  double closest_later = 1e9;
  for (double t = 20.0; t <= 60.0; t += 0.05) {
    closest_later = std::min(closest_later, (loop->agents[0].trajectory.state(t).T_w_b.translation() - start).norm());
  }
  EXPECT_LT(closest_later, 1.0);

  options.preset = "overlap2";
  auto two = planMission(options);
  ASSERT_TRUE(two.ok());
  std::array<std::vector<Eigen::Vector3d>, 2> paths;
  for (std::size_t a = 0; a < 2; ++a) {
    for (double t = 0.0; t <= 60.0; t += 0.1)
      paths[a].push_back(two->agents[a].trajectory.state(t).T_w_b.translation());
  }
  std::size_t shared = 0;
  for (const Eigen::Vector3d& p : paths[0]) {
    for (const Eigen::Vector3d& q : paths[1]) {
      if ((p - q).head<2>().norm() < 1.0) {
        ++shared;
        break;
      }
    }
  }
  const double fraction = static_cast<double>(shared) / static_cast<double>(paths[0].size());
  EXPECT_GT(fraction, 0.25);
  EXPECT_LT(fraction, 0.45);
  RecordProperty("overlap2_shared_fraction", std::to_string(fraction));
}

TEST(MissionPlans, EurocMhReplaysTheFiveFlightsInsideAHallAroundThem) {
  CVISLAM_REQUIRE_DATA(gt_dir, "euroc-groundtruth");
  MissionPlanOptions options;
  options.preset = "euroc-mh";
  options.duration_s = 30.0;
  options.data_dir = test::dataRoot();
  auto plan = planMission(options);
  ASSERT_TRUE(plan.ok()) << plan.error().toString();
  ASSERT_EQ(plan->agents.size(), 5U);
  EXPECT_EQ(plan->agents[0].source, "MH_01_easy.txt");
  // The replayed spline follows the real flight closely.
  Diagnostics diagnostics;
  auto real = dataset::readTrajectory(gt_dir / "MH_03_medium.txt", {}, diagnostics);
  ASSERT_TRUE(real.ok());
  double worst_m = 0.0, worst_rad = 0.0;
  for (std::size_t i = 0; i < real->size(); i += 20) {
    const double t = static_cast<double>((*real)[i].t_ns - real->front().t_ns) * 1e-9;
    if (t > options.duration_s) break;
    const geometry::SE3d replayed = plan->agents[2].trajectory.state(t).T_w_b;
    worst_m = std::max(worst_m, ((*real)[i].T_w_b.translation() - replayed.translation()).norm());
    worst_rad = std::max(worst_rad, ((*real)[i].T_w_b.so3().inverse() * replayed.so3()).log().norm());
  }
  EXPECT_LT(worst_m, 0.05);
  EXPECT_LT(worst_rad, 2.0 * std::numbers::pi / 180.0);
  RecordProperty("replay_worst_error", std::to_string(worst_m) + " m, " + std::to_string(worst_rad) + " rad");
  for (const AgentPlan& agent : plan->agents) {
    for (double t = 0.0; t <= options.duration_s; t += 0.1) {
      const Eigen::Vector3d p = agent.trajectory.state(t).T_w_b.translation();
      for (const Box& b : plan->layout.obstacles) ASSERT_GT(distanceToBox(b, p), 0.5) << agent.name << " t=" << t;
    }
  }
}

}  // namespace
}  // namespace cvislam::sim
