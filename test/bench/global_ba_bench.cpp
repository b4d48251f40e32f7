// bench_global_ba: how the server's global BA (server_cloud/backend/global_ba, Eq. 11) scales with the number of
// keyframes. SYNTHETIC scenes, not a dataset: a mono-inertial agent flies one lap of a circle (1 m/s, a keyframe
// every 0.5 s, so the circle grows with the keyframe count) looking outward at a cylindrical wall 4 m away that
// carries 40 points per metre; every keyframe observes the points in its view (at most 300), with 0.5 px pixel
// noise; the IMU (1 kHz) comes from the trajectory. The solve starts from the truth perturbed by 2 cm / 0.2 deg per
// keyframe and 3 cm per point, with the server's default options (or those given) on 2 threads, and is timed end
// to end (problem building and both steps; stderr has each run's time by part and its cost). Each size is solved
// `--repetitions` times with different perturbation seeds; the JSON gives p50 and p99 (with 3 repetitions p99 is
// the slowest run). Pixel noise and a long lap put the optimum away from the truth, so convergence is judged by the
// distance from the optimum that the same solve reaches from the truth (solved once more per size, untimed), and
// by the final cost. Each run also times what a merge's correction solves on that lap: a BA of 11 keyframes with
// the rest held, and the fit of one 4-DoF change to their moves; with --free-fraction, also a GBA of the newest
// keyframes with the rest held at the optimum (timeWindow). --laps N flies the lap N times on a smaller circle, so that
// the keyframes of all laps see the same points: dense covisibility, as with many agents over one place.
//
//   bench_global_ba [--keyframes 250,500,1000,2000] [--laps 1] [--free-fraction F] [--repetitions 3] [--threads 2]
//                   [--json OUT] [--structure-iterations N] [--full-iterations N] [--function-tolerance F]
//                   [--solver schur|ceres|both]
// --solver both (the default) solves every size with the server's own Schur solver and with Ceres, side by side.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/backend/merge_correction.hpp"
#include "test/bench/percentiles.hpp"

namespace {

using cvislam::geometry::SE3d;
using cvislam::geometry::SO3d;
using Eigen::Vector3d;
namespace backend = cvislam::server::backend;

constexpr double kSpeed_mps = 1.0;
constexpr double kKeyframeInterval_s = 0.5;
constexpr double kImuRate_hz = 1000.0;
constexpr double kWallDistance_m = 4.0;
constexpr double kPointsPerMetre = 40.0;
constexpr int kMaxObservationsPerKeyframe = 300;
constexpr double kPixelSigma = 0.5;
// A merge's correction solves a BA of the query keyframe and its 10 most covisible keyframes of its own map.
constexpr int kCorrectionWindow = 11;
const cvislam::factors::PinholeIntrinsics kCamera{458.0, 457.0, 367.0, 248.0};
constexpr double kWidth = 752.0;
constexpr double kHeight = 480.0;

// The flight: a circle of radius `radius`, the body's x axis (and so roughly the camera, whose EuRoC extrinsics
// look along body x) pointing outward, with a gentle height and heading wobble.
struct Circle {
  double radius = 10.0;
  SE3d T_w_s(double t) const {
    const double theta = kSpeed_mps * t / radius;
    const Vector3d p(radius * std::cos(theta), radius * std::sin(theta), 1.5 + 0.2 * std::sin(1.3 * t));
    const double yaw = theta + 0.15 * std::sin(0.7 * t);
    const double pitch = 0.05 * std::sin(1.1 * t);
    // Body: x outward (forward), z up before the EuRoC camera rotation is applied by T_s_c.
    const SO3d R = SO3d::exp(Vector3d(0.0, 0.0, yaw)) * SO3d::exp(Vector3d(0.0, pitch, 0.0));
    return SE3d(R, p);
  }
};

// The camera that looks along body +x: EuRoC's body is x forward with the camera looking along it.
SE3d cameraInBody() {
  Eigen::Matrix3d R_s_c;
  R_s_c.col(0) = -Vector3d::UnitY();  // image x to body -y
  R_s_c.col(1) = -Vector3d::UnitZ();  // image y to body -z
  R_s_c.col(2) = Vector3d::UnitX();   // optical axis along body x
  return SE3d(SO3d(R_s_c), Vector3d(0.0, -0.05, 0.0));
}

// IMU readings by central differences of the analytic trajectory (step 1e-4 s): accurate to well under the noise.
cvislam::dataset::ImuSample imuAt(const Circle& c, double t) {
  constexpr double h = 1e-4;
  const SE3d a = c.T_w_s(t - h);
  const SE3d b = c.T_w_s(t);
  const SE3d d = c.T_w_s(t + h);
  cvislam::dataset::ImuSample s;
  s.t_ns = std::llround(t * 1e9);
  s.gyro_s = (a.so3().inverse() * d.so3()).log() / (2.0 * h);
  const Vector3d accel_w = (d.translation() - 2.0 * b.translation() + a.translation()) / (h * h);
  s.accel_s = b.so3().inverse() * (accel_w - cvislam::imu::kGravityW);
  return s;
}

struct Scene {
  backend::GbaSnapshot snapshot;  // the truth
  std::vector<SE3d> truth;
};

// `laps` > 1 flies the same flight on a smaller circle several times, so that keyframes of every lap see the same
// wall points: a dense covisibility like several agents in one hall, where the lap of one keeps it banded.
Scene makeScene(int keyframes, int laps, std::uint64_t seed) {
  Scene scene;
  const double length_m = kSpeed_mps * kKeyframeInterval_s * keyframes;
  Circle circle;
  circle.radius = std::max(6.0, length_m / (2.0 * M_PI * laps));
  const double wall_radius = circle.radius + kWallDistance_m;
  std::mt19937_64 rng(seed);

  // Points on the wall over the whole lap.
  const int points = static_cast<int>(2.0 * M_PI * wall_radius * kPointsPerMetre);
  std::uniform_real_distribution<double> angle(0.0, 2.0 * M_PI);
  std::uniform_real_distribution<double> height(0.0, 3.5);
  std::vector<Vector3d> p_w(static_cast<std::size_t>(points));
  for (Vector3d& p : p_w) {
    const double a = angle(rng);
    p = Vector3d(wall_radius * std::cos(a), wall_radius * std::sin(a), height(rng));
  }

  backend::GbaAgent agent;
  agent.cam0 = kCamera;
  agent.T_c0_s = cameraInBody().inverse();
  agent.uses_imu = true;
  scene.snapshot.agents.emplace(0, agent);

  std::normal_distribution<double> pixel_noise(0.0, kPixelSigma);
  std::vector<int> observers(p_w.size(), 0);
  std::vector<cvislam::dataset::ImuSample> imu;
  for (int k = 0; k < keyframes; ++k) {
    const double t = k * kKeyframeInterval_s;
    backend::GbaKeyframe kf;
    kf.id = cvislam::KeyframeId{0, static_cast<std::uint32_t>(k)};
    kf.t_ns = std::llround(t * 1e9);
    kf.T_w_s = circle.T_w_s(t);
    kf.T_w_s_before = kf.T_w_s;
    kf.v_w = (circle.T_w_s(t + 1e-4).translation() - circle.T_w_s(t - 1e-4).translation()) / 2e-4;
    if (k > 0) {
      imu.clear();
      const double t0 = (k - 1) * kKeyframeInterval_s;
      const auto first = std::llround(t0 * kImuRate_hz);
      const auto last = std::llround(t * kImuRate_hz);
      for (auto i = first; i <= last; ++i) imu.push_back(imuAt(circle, static_cast<double>(i) / kImuRate_hz));
      cvislam::imu::Preintegration pre(cvislam::imu::ImuBias{}, cvislam::imu::ImuNoise{});
      if (!pre.integrateInterval(imu, scene.snapshot.keyframes.back().t_ns, kf.t_ns).ok()) std::abort();
      kf.imu_from = k - 1;
      kf.preintegration = pre;
    }
    const SE3d T_c_w = (kf.T_w_s * cameraInBody()).inverse();
    for (std::size_t p = 0; p < p_w.size() && kf.observations.size() < kMaxObservationsPerKeyframe; ++p) {
      const Vector3d p_c = T_c_w * p_w[p];
      if (p_c.z() < 0.5 || p_c.z() > 12.0) continue;
      const double u = kCamera.fx * p_c.x() / p_c.z() + kCamera.cx;
      const double v = kCamera.fy * p_c.y() / p_c.z() + kCamera.cy;
      if (u < 0.0 || u >= kWidth || v < 0.0 || v >= kHeight) continue;
      backend::GbaObservation o;
      o.point = static_cast<std::uint32_t>(p);
      o.px_undistorted = Eigen::Vector2d(u + pixel_noise(rng), v + pixel_noise(rng));
      kf.observations.push_back(o);
      ++observers[p];
    }
    scene.truth.push_back(kf.T_w_s);
    scene.snapshot.keyframes.push_back(std::move(kf));
  }
  // Points seen by two keyframes or more, reindexed.
  std::vector<std::int64_t> index(p_w.size(), -1);
  for (std::size_t p = 0; p < p_w.size(); ++p) {
    if (observers[p] < 2) continue;
    index[p] = static_cast<std::int64_t>(scene.snapshot.points.size());
    backend::GbaPoint point;
    point.id = cvislam::MapPointId{0, static_cast<std::uint32_t>(p)};
    point.p_w = p_w[p];
    point.p_w_before = p_w[p];
    scene.snapshot.points.push_back(point);
  }
  for (backend::GbaKeyframe& kf : scene.snapshot.keyframes) {
    std::erase_if(kf.observations, [&](const backend::GbaObservation& o) { return index[o.point] < 0; });
    for (backend::GbaObservation& o : kf.observations) o.point = static_cast<std::uint32_t>(index[o.point]);
  }
  return scene;
}

void perturb(backend::GbaSnapshot& snapshot, std::uint64_t seed, double scale) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n(0.0, 1.0);
  const auto vec = [&](double sigma) {
    return Vector3d(scale * sigma * n(rng), scale * sigma * n(rng), scale * sigma * n(rng));
  };
  for (std::size_t i = 1; i < snapshot.keyframes.size(); ++i) {  // the oldest holds the gauge
    backend::GbaKeyframe& kf = snapshot.keyframes[i];
    kf.T_w_s = SE3d(SO3d::exp(vec(0.2 * M_PI / 180.0)) * kf.T_w_s.so3(), kf.T_w_s.translation() + vec(0.02));
    kf.T_w_s_before = kf.T_w_s;
    kf.v_w += vec(0.05);
  }
  for (backend::GbaPoint& p : snapshot.points) {
    p.p_w += vec(0.03);
    p.p_w_before = p.p_w;
  }
}

double rmsPositionError(const backend::GbaSnapshot& snapshot, const std::vector<SE3d>& reference) {
  double sum = 0.0;
  for (std::size_t i = 0; i < reference.size(); ++i) {
    sum += (snapshot.keyframes[i].T_w_s.translation() - reference[i].translation()).squaredNorm();
  }
  return std::sqrt(sum / static_cast<double>(reference.size()));
}

std::vector<SE3d> posesOf(const backend::GbaSnapshot& snapshot) {
  std::vector<SE3d> poses;
  for (const backend::GbaKeyframe& kf : snapshot.keyframes) poses.push_back(kf.T_w_s);
  return poses;
}

// Keyframes [first, last) of `perturbed` free, with the points they see and the other keyframes that see those
// points (or are IMU-linked to the window) held, as makeGbaSnapshot(window) copies them. `keyframe_index` maps
// each keyframe of `perturbed` to its index in the result (-1: left out).
backend::GbaSnapshot windowOf(const backend::GbaSnapshot& perturbed, std::size_t first, std::size_t last,
                              std::vector<int>& keyframe_index) {
  const std::size_t n = perturbed.keyframes.size();
  std::vector<std::uint8_t> seen(perturbed.points.size(), 0);
  for (std::size_t i = first; i < last; ++i) {
    for (const backend::GbaObservation& o : perturbed.keyframes[i].observations) seen[o.point] = 1;
  }
  backend::GbaSnapshot part;
  part.agents = perturbed.agents;
  std::vector<std::int64_t> point_index(perturbed.points.size(), -1);
  for (std::size_t p = 0; p < perturbed.points.size(); ++p) {
    if (seen[p] == 0) continue;
    point_index[p] = static_cast<std::int64_t>(part.points.size());
    part.points.push_back(perturbed.points[p]);
  }
  keyframe_index.assign(n, -1);
  for (std::size_t i = 0; i < n; ++i) {
    backend::GbaKeyframe kf = perturbed.keyframes[i];
    kf.held = i < first || i >= last;
    std::erase_if(kf.observations, [&](const backend::GbaObservation& o) { return point_index[o.point] < 0; });
    const bool imu_neighbour = i + 1 == first || i == last;
    if (kf.held && kf.observations.empty() && !imu_neighbour) continue;
    for (backend::GbaObservation& o : kf.observations) o.point = static_cast<std::uint32_t>(point_index[o.point]);
    kf.imu_from = kf.imu_from >= 0 ? keyframe_index[static_cast<std::size_t>(kf.imu_from)] : -1;
    if (kf.imu_from < 0) kf.preintegration.reset();
    keyframe_index[i] = static_cast<int>(part.keyframes.size());
    part.keyframes.push_back(std::move(kf));
  }
  return part;
}

// The merge's correction on a lap of this size: a windowed BA of `window` keyframes from the lap's middle, the rest
// held where they see its points, then the 4-DoF change fitted to the window's moves. Returns the whole time in
// seconds.
double timeCorrection(const backend::GbaSnapshot& perturbed, int window, backend::GlobalBaOptions::Solver solver) {
  const std::size_t n = perturbed.keyframes.size();
  const std::size_t first = n / 2 - static_cast<std::size_t>(window) / 2;
  const std::size_t last = std::min(n, first + static_cast<std::size_t>(window));
  std::vector<int> keyframe_index;
  backend::GbaSnapshot part = windowOf(perturbed, first, last, keyframe_index);
  backend::GlobalBaOptions options = backend::BackendOptions{}.merge_correction_ba;
  options.solver = solver;
  const auto start = std::chrono::steady_clock::now();
  if (!backend::runGlobalBa(part, options)) std::abort();
  std::vector<SE3d> before;
  std::vector<SE3d> after;
  for (const backend::GbaKeyframe& kf : part.keyframes) {
    if (kf.held) continue;
    before.push_back(kf.T_w_s_before);
    after.push_back(kf.T_w_s);
  }
  const SE3d change = backend::fitFourDofChange(before, after);
  if (!change.matrix().allFinite()) std::abort();
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// The GBA after a merge with a window (backend.gba_window_above_keyframes): the newest `free` keyframes of a map
// otherwise at its optimum (the whole map's solve from the truth) start perturbed with their points, as the map a
// merge moved would; the rest keep the optimum and are held where they see those points. Returns the solve's time
// in seconds and the free keyframes' RMS position to the optimum in metres.
std::pair<double, double> timeWindow(const backend::GbaSnapshot& at_optimum, std::size_t free, std::uint64_t seed,
                                     double scale, const backend::GlobalBaOptions& options) {
  const std::size_t n = at_optimum.keyframes.size();
  const std::size_t first = n - std::min(free, n - 1);
  backend::GbaSnapshot start = at_optimum;
  perturb(start, seed, scale);
  std::vector<std::uint8_t> moved(start.points.size(), 0);
  for (std::size_t i = first; i < n; ++i) {
    for (const backend::GbaObservation& o : start.keyframes[i].observations) moved[o.point] = 1;
  }
  for (std::size_t i = 0; i < first; ++i) start.keyframes[i] = at_optimum.keyframes[i];
  for (std::size_t p = 0; p < start.points.size(); ++p) {
    if (moved[p] == 0) start.points[p] = at_optimum.points[p];
  }
  for (backend::GbaKeyframe& kf : start.keyframes) kf.T_w_s_before = kf.T_w_s;
  for (backend::GbaPoint& p : start.points) p.p_w_before = p.p_w;
  std::vector<int> keyframe_index;
  backend::GbaSnapshot part = windowOf(start, first, n, keyframe_index);
  const auto t0 = std::chrono::steady_clock::now();
  if (!backend::runGlobalBa(part, options)) std::abort();
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  double sum = 0.0;
  for (std::size_t i = first; i < n; ++i) {
    const SE3d& solved = part.keyframes[static_cast<std::size_t>(keyframe_index[i])].T_w_s;
    sum += (solved.translation() - at_optimum.keyframes[i].T_w_s.translation()).squaredNorm();
  }
  return {seconds, std::sqrt(sum / static_cast<double>(n - first))};
}

std::vector<int> parseSizes(const std::string& text) {
  std::vector<int> sizes;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) {
    const int n = std::stoi(item);
    if (n < 2) throw std::invalid_argument("every keyframe count must be at least 2, not " + item);
    sizes.push_back(n);
  }
  return sizes;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "bench_global_ba: the server's global BA time against the keyframe count (synthetic mono-inertial "
      "scenes; see the file's header)"};
  std::string sizes_text = "250,500,1000,2000";
  int repetitions = 3;
  int threads = 2;
  std::string json_path;
  double perturbation = 1.0;
  int laps = 1;
  app.add_option("--keyframes", sizes_text, "Comma-separated keyframe counts [250,500,1000,2000]");
  app.add_option("--repetitions", repetitions, "Solves per size, each from another perturbation [3]")
      ->check(CLI::PositiveNumber);
  app.add_option("--threads", threads, "Solver threads [2]")->check(CLI::PositiveNumber);
  app.add_option("--json", json_path, "Write the results here as JSON");
  app.add_option("--laps", laps, "Laps of one flight (a smaller circle each time): >1 makes covisibility dense [1]")
      ->check(CLI::PositiveNumber);
  double free_fraction = 0.0;
  app.add_option("--free-fraction", free_fraction,
                 "Also time a GBA of the newest fraction of the keyframes, the rest at the optimum and held [off]")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--perturbation", perturbation, "Scale of the start's perturbation; 0 starts at the truth [1]")
      ->check(CLI::NonNegativeNumber);
  backend::GlobalBaOptions options;
  app.add_option("--structure-iterations", options.structure_iterations, "Step 1 (poses held) iterations [server's]")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--full-iterations", options.full_iterations, "Step 2 iterations at most [server's]")
      ->check(CLI::PositiveNumber);
  std::string solver_text = "both";
  app.add_option("--solver", solver_text, "schur (the server's own), ceres, or both, side by side in this run [both]")
      ->check(CLI::IsMember({"schur", "ceres", "both"}));
  app.add_flag("--iterative-schur", options.iterative_schur,
               "With Ceres: ITERATIVE_SCHUR (SCHUR_JACOBI) in place of SPARSE_SCHUR");
  app.add_option("--function-tolerance", options.function_tolerance,
                 "A step stops when an iteration lowers the cost by less than this fraction [server's]");
  CLI11_PARSE(app, argc, argv);
  std::vector<int> sizes;
  try {
    sizes = parseSizes(sizes_text);
  } catch (const std::exception& e) {
    std::cerr << "bench_global_ba: --keyframes: " << e.what() << "\n";
    return 2;
  }

  options.threads = threads;
  std::vector<backend::GlobalBaOptions::Solver> solvers;
  if (solver_text != "ceres") solvers.push_back(backend::GlobalBaOptions::Solver::kSchur);
  if (solver_text != "schur") solvers.push_back(backend::GlobalBaOptions::Solver::kCeres);
  nlohmann::json results = nlohmann::json::array();
  std::printf("SYNTHETIC mono-inertial scenes (%d lap(s), 1 m/s, a keyframe per 0.5 s, <= 300 observations each)\n",
              laps);
  std::printf(
      "RMS keyframe position differences [cm]: start and result to the truth; result to the optimum reached "
      "from the truth; that optimum to the truth\n");
  std::printf("%9s %6s %7s %9s %6s %10s %10s %10s %8s %8s %10s %10s %12s\n", "keyframes", "solver", "points", "reproj",
              "iters", "solve p50", "solve p99", "s/KF p50", "start", "result", "to optimum", "optimum", "final cost");
  for (const int n : sizes) {
    const Scene scene = makeScene(n, laps, 1);
    for (const backend::GlobalBaOptions::Solver solver : solvers) {
      options.solver = solver;
      const char* solver_name = backend::toString(solver);
      // The optimum as the solve finds it from the truth: with pixel noise it is not the truth, and over a long lap
      // it drifts from it, so convergence is judged against this.
      backend::GbaSnapshot from_truth = scene.snapshot;
      if (auto s = backend::runGlobalBa(from_truth, options); !s) {
        std::cerr << "bench_global_ba: " << s.error().toString() << "\n";
        return 1;
      }
      const std::vector<SE3d> optimum = posesOf(from_truth);
      const double optimum_to_truth_m = rmsPositionError(from_truth, scene.truth);
      std::vector<double> to_optimum_m;
      std::vector<double> seconds;
      std::vector<double> before_m;
      std::vector<double> after_m;
      std::vector<double> correction_s;
      std::vector<double> window_s;
      std::vector<double> window_to_optimum_m;
      const auto free_keyframes = static_cast<std::size_t>(std::lround(free_fraction * n));
      std::vector<double> final_cost;
      backend::GlobalBaSummary last;
      for (int r = 0; r < repetitions; ++r) {
        backend::GbaSnapshot snapshot = scene.snapshot;
        perturb(snapshot, 100 + static_cast<std::uint64_t>(r), perturbation);
        before_m.push_back(rmsPositionError(snapshot, scene.truth));
        correction_s.push_back(timeCorrection(snapshot, kCorrectionWindow, solver));
        if (free_keyframes > 0) {
          const auto [seconds_w, rms_m] =
              timeWindow(from_truth, free_keyframes, 100 + static_cast<std::uint64_t>(r), perturbation, options);
          window_s.push_back(seconds_w);
          window_to_optimum_m.push_back(rms_m);
        }
        const auto start = std::chrono::steady_clock::now();
        auto summary = backend::runGlobalBa(snapshot, options);
        seconds.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
        if (!summary) {
          std::cerr << "bench_global_ba: " << summary.error().toString() << "\n";
          return 1;
        }
        last = *summary;
        final_cost.push_back(summary->final_cost);
        after_m.push_back(rmsPositionError(snapshot, scene.truth));
        to_optimum_m.push_back(rmsPositionError(snapshot, optimum));
        const backend::GlobalBaProfile& pr = summary->profile;
        std::fprintf(
            stderr,
            "  %d keyframes, %s, run %d/%d: %.2f s (build %.2f, preprocess %.2f, residuals %.2f, jacobians %.2f, "
            "linear solver %.2f, other %.2f; iterations %d + %d; cost %.6g -> %.6g)\n",
            n, solver_name, r + 1, repetitions, seconds.back(), pr.build_s, pr.preprocess_s, pr.residuals_s,
            pr.jacobians_s, pr.linear_solver_s, pr.other_s, summary->structure_iterations, summary->full_iterations,
            summary->initial_cost, summary->final_cost);
      }
      const auto pct = [](const std::vector<double>& v, double p) { return cvislam::bench::percentile(v, p); };
      std::printf("%9d %6s %7d %9d %6d %9.2fs %9.2fs %8.1fms %8.2f %8.2f %10.3f %10.2f %12.6g\n", n, solver_name,
                  last.points, last.reprojection_factors, last.structure_iterations + last.full_iterations,
                  pct(seconds, 0.5), pct(seconds, 0.99), 1000.0 * pct(seconds, 0.5) / n, 100.0 * pct(before_m, 0.5),
                  100.0 * pct(after_m, 0.5), 100.0 * pct(to_optimum_m, 0.99), 100.0 * optimum_to_truth_m,
                  pct(final_cost, 0.5));
      std::printf("%9s merge correction: BA of %d keyframes and the fit, p50 %.0f ms, p99 %.0f ms\n", "",
                  kCorrectionWindow, 1000.0 * pct(correction_s, 0.5), 1000.0 * pct(correction_s, 0.99));
      if (free_keyframes > 0) {
        std::printf("%9s GBA of the newest %zu keyframes, the rest held: p50 %.2f s, p99 %.2f s; to optimum %.3f cm\n",
                    "", free_keyframes, pct(window_s, 0.5), pct(window_s, 0.99),
                    100.0 * pct(window_to_optimum_m, 0.99));
      }
      std::fflush(stdout);
      results.push_back({{"keyframes", n},
                         {"solver", solver_name},
                         {"correction",
                          {{"window_keyframes", kCorrectionWindow},
                           {"solve_s", {{"p50", pct(correction_s, 0.5)}, {"p99", pct(correction_s, 0.99)}}}}},
                         {"window",
                          {{"free_keyframes", free_keyframes},
                           {"solve_s", {{"p50", pct(window_s, 0.5)}, {"p99", pct(window_s, 0.99)}}},
                           {"free_to_optimum_m_p99", pct(window_to_optimum_m, 0.99)}}},
                         {"points", last.points},
                         {"reprojection_factors", last.reprojection_factors},
                         {"imu_factors", last.imu_factors},
                         {"iterations", last.structure_iterations + last.full_iterations},
                         {"repetitions", repetitions},
                         {"solve_s", {{"p50", pct(seconds, 0.5)}, {"p99", pct(seconds, 0.99)}, {"all", seconds}}},
                         {"final_cost", final_cost},
                         {"rms_position_m",
                          {{"start_to_truth_p50", pct(before_m, 0.5)},
                           {"result_to_truth_p50", pct(after_m, 0.5)},
                           {"result_to_optimum_p99", pct(to_optimum_m, 0.99)},
                           {"optimum_to_truth", optimum_to_truth_m}}}});
    }
  }
  if (!json_path.empty()) {
    std::ofstream out(json_path);
    if (!out) {
      std::cerr << "bench_global_ba: cannot write " << json_path << "\n";
      return 1;
    }
    out << nlohmann::json{{"benchmark", "global_ba"},
                          {"synthetic", true},
                          {"threads", threads},
                          {"laps", laps},
                          {"results", results}}
               .dump(2)
        << "\n";
  }
  return 0;
}
