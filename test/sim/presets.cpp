#include "test/sim/presets.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <numbers>

#include "common/dataset/trajectory_io.hpp"
#include "test/sim/random.hpp"

#ifndef CVISLAM_SIM_DEFAULT_DATA_DIR
#define CVISLAM_SIM_DEFAULT_DATA_DIR "../shared/data"
#endif

namespace cvislam::sim {

namespace {

constexpr double kPi = std::numbers::pi;
constexpr std::uint64_t kLayoutStream = 0x1A70;
constexpr std::uint64_t kPathStream = 0xA7E4;

// Synthetic hall: 20 x 15 x 6 m centred on the origin; agents fly around an elliptic ring between the central
// island of shelves and crates and the walls.
constexpr double kHallHalfX = 10.0, kHallHalfY = 7.5, kHallHeight = 6.0;
constexpr double kRingA = 6.6, kRingB = 4.8;

Box makeBox(double x0, double y0, double z0, double x1, double y1, double z1, const char* kind) {
  Box b;
  b.min_w = Eigen::Vector3d(std::min(x0, x1), std::min(y0, y1), std::min(z0, z1));
  b.max_w = Eigen::Vector3d(std::max(x0, x1), std::max(y0, y1), std::max(z0, z1));
  b.kind = kind;
  return b;
}

// How an agent moves around the ring.
struct RingMotion {
  double start_angle = 0.0;  // [rad] on the ring
  double direction = 1.0;    // +1 counter-clockwise
  double speed_mps = 1.0;    // mean speed along the ring
  bool sweep = false;        // back and forth over [centre - half_range, centre + half_range] instead of laps
  double sweep_half_range = 0.0;
  double lane_offset_m = 0.0;  // shifts the ring outwards (+) or inwards (-)
  double lane_amp_m = 0.4;
  double z_mean_m = 1.6;
  double z_amp_m = 0.5;
  double yaw_amp_rad = 0.35;   // looking around, on top of the flight direction
  double tilt_amp_rad = 0.06;  // roll and pitch oscillation
  double wiggle_hz = 0.12;     // base frequency of the oscillations
  double init_s = 4.0;         // motion-rich start (IMU initialisation) before leaving along the ring
  // Laps only: at this time [s] (negative: never) the vehicle slows down, turns round through a sideways look
  // within `turn_s`, and flies on the other way, so that it sees the ring's places from both directions.
  double turn_at_s = -1.0;
  double turn_s = 5.0;
};

double smoothstep(double x) {
  x = std::clamp(x, 0.0, 1.0);
  return x * x * x * (x * (6.0 * x - 15.0) + 10.0);  // C2
}

std::vector<PathSample> sampleRingPath(const RingMotion& m, double duration_s, std::uint64_t seed) {
  Rng rng(seed);
  double phase[8];
  for (double& p : phase) p = rng.uniform(0.0, 2.0 * kPi);
  const double f = m.wiggle_hz;
  constexpr double kRateHz = 50.0;
  const auto n = static_cast<std::size_t>(std::ceil((duration_s + 1.0) * kRateHz)) + 1;
  std::vector<PathSample> out;
  out.reserve(n);
  double progress_s = 0.0;         // time spent moving along the ring, ramped in after the start manoeuvre
  double turned_progress_s = 0.0;  // the same, signed by the direction of travel (a vehicle that turns round)
  const double perimeter = 2.0 * kPi * std::sqrt(0.5 * (kRingA * kRingA + kRingB * kRingB));
  const double angular_rate = 2.0 * kPi * m.speed_mps / perimeter;
  for (std::size_t k = 0; k < n; ++k) {
    const double t = static_cast<double>(k) / kRateHz;
    const double turn = m.turn_at_s < 0.0 ? 0.0 : smoothstep((t - m.turn_at_s) / m.turn_s);  // 0 before, 1 after
    if (k > 0) {
      const double step = smoothstep((t - 1.0) / (m.init_s - 1.0)) / kRateHz;
      progress_s += step;
      turned_progress_s += std::cos(kPi * turn) * step;  // slows to rest halfway through the turn, then back
    }
    double theta = 0.0;
    double heading_offset = 0.0;
    if (m.sweep) {
      // theta swings sinusoidally; the vehicle turns to face its direction of motion through a sideways look.
      const double omega = angular_rate * kPi / (2.0 * m.sweep_half_range);  // mean speed over a half swing
      const double s = omega * progress_s - 0.5 * kPi;                       // start at the end of the arc, at rest
      theta = m.start_angle + m.direction * m.sweep_half_range * std::sin(s);
      // Moving along direction * (+theta) while cos(s) > 0: face that way, and turn through a sideways look
      // to face back when the sweep reverses.
      heading_offset = (m.direction > 0.0 ? 0.0 : kPi) + 0.5 * kPi * (1.0 - std::cos(s)) * m.direction;
    } else if (m.turn_at_s >= 0.0) {
      theta = m.start_angle + m.direction * angular_rate * turned_progress_s;
      heading_offset = (m.direction > 0.0 ? 0.0 : kPi) + kPi * turn;
    } else {
      theta = m.start_angle + m.direction * angular_rate * progress_s;
      heading_offset = m.direction > 0.0 ? 0.0 : kPi;
    }
    const double lane = m.lane_offset_m + m.lane_amp_m * (0.7 * std::sin(2.0 * kPi * 0.9 * f * t + phase[0]) +
                                                          0.3 * std::sin(2.0 * kPi * 2.3 * f * t + phase[1]));
    const double a = kRingA + lane, b = kRingB + lane;
    PathSample s;
    s.t_s = t;
    s.p_w = Eigen::Vector3d(a * std::cos(theta), b * std::sin(theta),
                            m.z_mean_m + m.z_amp_m * (0.7 * std::sin(2.0 * kPi * 0.7 * f * t + phase[2]) +
                                                      0.3 * std::sin(2.0 * kPi * 1.9 * f * t + phase[3])));
    // Tangent of the ring in the +theta direction.
    const double tangent_yaw = std::atan2(b * std::cos(theta), -a * std::sin(theta));
    s.yaw = tangent_yaw + heading_offset + m.yaw_amp_rad * std::sin(2.0 * kPi * 1.1 * f * t + phase[4]);
    s.pitch = m.tilt_amp_rad * std::sin(2.0 * kPi * 3.1 * f * t + phase[5]);
    s.roll = m.tilt_amp_rad * std::sin(2.0 * kPi * 3.7 * f * t + phase[6]);
    // Motion-rich start: translation and rotation excitation on all axes, faded in and out.
    if (t < m.init_s) {
      const double w = std::pow(std::sin(kPi * t / m.init_s), 2);
      s.p_w += w * Eigen::Vector3d(0.12 * std::sin(2.0 * kPi * 0.8 * t + phase[7]), 0.1 * std::sin(2.0 * kPi * 1.1 * t),
                                   0.08 * std::sin(2.0 * kPi * 1.3 * t + 1.0));
      s.yaw += w * 0.3 * std::sin(2.0 * kPi * 0.6 * t);
      s.pitch += w * 0.15 * std::sin(2.0 * kPi * 0.9 * t + 0.5);
      s.roll += w * 0.15 * std::sin(2.0 * kPi * 0.7 * t + 2.0);
    }
    out.push_back(s);
  }
  return out;
}

std::vector<RingMotion> presetMotions(const std::string& preset, std::uint64_t seed) {
  Rng rng(deriveSeed(seed, kPathStream));
  std::vector<RingMotion> motions;
  if (preset == "loop") {
    RingMotion m;
    m.start_angle = -0.5 * kPi;
    motions.push_back(m);
  } else if (preset == "overlap2") {
    // Two swept arcs of 200 deg whose centres are 135 deg apart: they share 65 deg at one end of each arc.
    // Each starts at rest at the far end of its arc and sweeps towards the other.
    for (int i = 0; i < 2; ++i) {
      RingMotion m;
      m.sweep = true;
      m.sweep_half_range = 100.0 * kPi / 180.0;
      m.start_angle = i == 0 ? -0.5 * kPi : -0.5 * kPi + 0.75 * kPi;
      m.direction = i == 0 ? 1.0 : -1.0;  // both start by flying towards the shared part
      m.z_mean_m = i == 0 ? 1.5 : 1.9;
      m.lane_offset_m = i == 0 ? 0.25 : -0.25;
      motions.push_back(m);
    }
  } else if (preset == "hall4" || preset == "hall8") {
    // Half the agents start counter-clockwise, half clockwise; each turns round once (agent i after
    // 24 + 2 i s), so that every place is seen from both directions by several agents. Cameras look ahead:
    // without the turn the two groups would never see a place from a similar direction, and could not merge.
    const int n = preset == "hall4" ? 4 : 8;
    for (int i = 0; i < n; ++i) {
      RingMotion m;
      m.start_angle = 2.0 * kPi * i / n;
      m.direction = i % 2 == 0 ? 1.0 : -1.0;
      m.lane_offset_m = (i % 4 < 2 ? 0.4 : -0.4);
      m.z_mean_m = 1.3 + 0.25 * (i % 4);
      m.speed_mps = rng.uniform(0.8, 1.2);
      m.turn_at_s = 24.0 + 2.0 * i;
      motions.push_back(m);
    }
  } else if (preset == "aggressive") {
    RingMotion m;
    m.start_angle = 0.5 * kPi;
    m.speed_mps = 1.5;
    m.lane_amp_m = 0.6;
    m.z_amp_m = 0.8;
    m.yaw_amp_rad = 0.8;
    m.tilt_amp_rad = 0.3;
    m.wiggle_hz = 0.3;
    m.init_s = 3.0;
    motions.push_back(m);
  }
  return motions;
}

WorldLayout syntheticHall(std::uint64_t seed) {
  WorldLayout layout;
  layout.hall = makeBox(-kHallHalfX, -kHallHalfY, 0.0, kHallHalfX, kHallHalfY, kHallHeight, "hall");
  auto& obs = layout.obstacles;
  // Central island: two shelves and crates.
  obs.push_back(makeBox(-3.0, -1.6, 0.0, -0.2, -1.0, 2.2, "shelf"));
  obs.push_back(makeBox(0.4, 0.9, 0.0, 3.2, 1.5, 2.0, "shelf"));
  // Pillars, floor to ceiling, outside and inside the ring.
  for (int k = 0; k < 8; ++k) {
    const double angle = kPi / 8.0 + k * kPi / 4.0;
    const double x = 1.38 * kRingA * std::cos(angle), y = 1.38 * kRingB * std::sin(angle);
    obs.push_back(makeBox(x - 0.25, y - 0.25, 0.0, x + 0.25, y + 0.25, kHallHeight, "pillar"));
  }
  for (int k = 0; k < 4; ++k) {
    const double angle = kPi / 4.0 + k * kPi / 2.0;
    const double x = 0.62 * kRingA * std::cos(angle), y = 0.62 * kRingB * std::sin(angle);
    obs.push_back(makeBox(x - 0.2, y - 0.2, 0.0, x + 0.2, y + 0.2, kHallHeight, "pillar"));
  }
  // Shelves along the walls, with gaps.
  for (double x0 : {-8.0, -2.0, 4.0}) {
    obs.push_back(makeBox(x0, kHallHalfY - 0.5, 0.0, x0 + 4.0, kHallHalfY, 2.4, "shelf"));
    obs.push_back(makeBox(x0 + 0.5, -kHallHalfY, 0.0, x0 + 3.5, -kHallHalfY + 0.5, 1.8, "shelf"));
  }
  for (double y0 : {-5.0, 1.5}) {
    obs.push_back(makeBox(kHallHalfX - 0.5, y0, 0.0, kHallHalfX, y0 + 3.5, 2.2, "shelf"));
    obs.push_back(makeBox(-kHallHalfX, y0 + 0.3, 0.0, -kHallHalfX + 0.5, y0 + 3.0, 2.6, "shelf"));
  }
  // Crates: on the island and scattered; those in the flight corridor are removed later.
  Rng rng(deriveSeed(seed, kLayoutStream));
  for (int k = 0; k < 8; ++k) {
    const double x = rng.uniform(-3.0, 3.0), y = rng.uniform(-0.8, 0.7);
    const double sx = rng.uniform(0.4, 1.0), sy = rng.uniform(0.4, 0.9), sz = rng.uniform(0.4, 1.8);
    obs.push_back(makeBox(x - 0.5 * sx, y - 0.5 * sy, 0.0, x + 0.5 * sx, y + 0.5 * sy, sz, "crate"));
  }
  for (int k = 0; k < 24; ++k) {
    const double x = rng.uniform(-kHallHalfX + 0.5, kHallHalfX - 0.5),
                 y = rng.uniform(-kHallHalfY + 0.5, kHallHalfY - 0.5);
    const double sx = rng.uniform(0.4, 1.2), sy = rng.uniform(0.4, 1.2), sz = rng.uniform(0.3, 1.5);
    obs.push_back(makeBox(x - 0.5 * sx, y - 0.5 * sy, 0.0, x + 0.5 * sx, y + 0.5 * sy, sz, "crate"));
  }
  return layout;
}

// A hall around replayed paths: their bounding box plus margins, with pillars, shelves and crates placed where
// no path passes.
WorldLayout hallAroundPaths(const std::vector<AgentPlan>& agents, double duration_s, std::uint64_t seed) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e9), hi = Eigen::Vector3d::Constant(-1e9);
  for (const AgentPlan& a : agents) {
    for (double t = 0.0; t <= duration_s; t += 0.1) {
      const Eigen::Vector3d p = a.trajectory.state(t).T_w_b.translation();
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
  }
  constexpr double kMarginM = 3.0;
  WorldLayout layout;
  const double floor_z = lo.z() - 0.7;
  const double ceiling_z = std::max(hi.z() + 2.0, floor_z + 5.0);
  layout.hall =
      makeBox(lo.x() - kMarginM, lo.y() - kMarginM, floor_z, hi.x() + kMarginM, hi.y() + kMarginM, ceiling_z, "hall");
  const Eigen::Vector3d hmin = layout.hall.min_w, hmax = layout.hall.max_w;
  Rng rng(deriveSeed(seed, kLayoutStream, 1));
  const double area = (hmax.x() - hmin.x()) * (hmax.y() - hmin.y());
  const int pillars = static_cast<int>(area / 25.0), crates = static_cast<int>(area / 6.0),
            shelves = static_cast<int>(area / 30.0);
  for (int k = 0; k < pillars; ++k) {
    const double x = rng.uniform(hmin.x() + 0.5, hmax.x() - 0.5), y = rng.uniform(hmin.y() + 0.5, hmax.y() - 0.5);
    layout.obstacles.push_back(makeBox(x - 0.25, y - 0.25, floor_z, x + 0.25, y + 0.25, ceiling_z, "pillar"));
  }
  for (int k = 0; k < shelves; ++k) {
    const double x = rng.uniform(hmin.x() + 1.0, hmax.x() - 1.0), y = rng.uniform(hmin.y() + 1.0, hmax.y() - 1.0);
    const double length = rng.uniform(2.0, 4.0), height = rng.uniform(1.6, 2.6);
    const bool along_x = rng.uniform() < 0.5;
    const double hx = along_x ? 0.5 * length : 0.3, hy = along_x ? 0.3 : 0.5 * length;
    layout.obstacles.push_back(makeBox(x - hx, y - hy, floor_z, x + hx, y + hy, floor_z + height, "shelf"));
  }
  for (int k = 0; k < crates; ++k) {
    const double x = rng.uniform(hmin.x() + 0.5, hmax.x() - 0.5), y = rng.uniform(hmin.y() + 0.5, hmax.y() - 0.5);
    const double sx = rng.uniform(0.4, 1.2), sy = rng.uniform(0.4, 1.2), sz = rng.uniform(0.3, 1.5);
    layout.obstacles.push_back(
        makeBox(x - 0.5 * sx, y - 0.5 * sy, floor_z, x + 0.5 * sx, y + 0.5 * sy, floor_z + sz, "crate"));
  }
  return layout;
}

double distanceToBox(const Box& b, const Eigen::Vector3d& p) {
  return (b.min_w - p).cwiseMax(p - b.max_w).cwiseMax(0.0).norm();
}

// Drops obstacles that any agent's camera would come closer to than min_clearance (or fly through).
void clearPaths(WorldLayout& layout, const std::vector<AgentPlan>& agents, double duration_s, double min_clearance) {
  std::vector<Eigen::Vector3d> points;
  for (const AgentPlan& a : agents) {
    for (double t = 0.0; t <= duration_s; t += 0.05) points.push_back(a.trajectory.state(t).T_w_b.translation());
  }
  std::erase_if(layout.obstacles, [&](const Box& b) {
    return std::any_of(points.begin(), points.end(),
                       [&](const Eigen::Vector3d& p) { return distanceToBox(b, p) < min_clearance; });
  });
}

Result<std::vector<AgentPlan>> replayAgents(const std::vector<std::filesystem::path>& files, double duration_s) {
  std::vector<AgentPlan> agents;
  for (std::size_t i = 0; i < files.size(); ++i) {
    const std::filesystem::path& file = files[i];
    std::error_code ec;
    if (!std::filesystem::is_regular_file(file, ec)) {
      return Error{ErrorCode::kNotFound, "ground-truth file " + file.string() +
                                             " not found (set CVISLAM_DATA_DIR to the folder that holds "
                                             "euroc-groundtruth/, or pass existing files to --replay)"};
    }
    Diagnostics diagnostics;
    dataset::TrajectoryReadOptions read_options;
    Result<dataset::Trajectory> poses = dataset::readTrajectory(file, read_options, diagnostics);
    if (!poses) return poses.error().withContext("reading " + file.string());
    const double flight_s = static_cast<double>(poses->back().t_ns - poses->front().t_ns) * 1e-9;
    if (flight_s < duration_s) {
      return Error{ErrorCode::kInvalidArgument,
                   file.string() + " covers only " + std::to_string(flight_s) + " s; ask for a shorter --duration"};
    }
    Result<std::vector<PathSample>> samples = pathSamplesFromPoses(*poses, duration_s);
    if (!samples) return samples.error().withContext(file.string());
    SplineFitOptions fit;
    fit.knot_spacing_s = 0.1;
    fit.smoothing = 1e-2;
    Result<BodyTrajectory> trajectory = fitTrajectory(*samples, duration_s, fit);
    if (!trajectory) return trajectory.error().withContext(file.string());
    agents.push_back({"agent" + std::to_string(i), file.filename().string(), std::move(trajectory).value()});
  }
  return agents;
}

}  // namespace

const std::vector<std::string>& presetNames() {
  static const std::vector<std::string> names = {"loop", "overlap2", "hall4", "hall8", "aggressive", "euroc-mh"};
  return names;
}

std::filesystem::path defaultDataDir() {
  if (const char* env = std::getenv("CVISLAM_DATA_DIR"); env != nullptr && *env != '\0') return env;
  return CVISLAM_SIM_DEFAULT_DATA_DIR;
}

Result<MissionPlan> planMission(const MissionPlanOptions& options) {
  if (!(options.duration_s > 0.0)) return Error{ErrorCode::kInvalidArgument, "duration must be positive"};
  MissionPlan plan;
  plan.preset = options.preset;
  plan.duration_s = options.duration_s;
  std::vector<std::filesystem::path> replay = options.replay;
  if (options.preset == "euroc-mh") {
    const std::filesystem::path dir = options.data_dir.empty() ? defaultDataDir() : options.data_dir;
    for (const char* name :
         {"MH_01_easy.txt", "MH_02_easy.txt", "MH_03_medium.txt", "MH_04_difficult.txt", "MH_05_difficult.txt"}) {
      replay.push_back(dir / "euroc-groundtruth" / name);
    }
  }
  if (!replay.empty()) {
    Result<std::vector<AgentPlan>> agents = replayAgents(replay, options.duration_s);
    if (!agents) return agents.error();
    plan.agents = std::move(agents).value();
    plan.layout = hallAroundPaths(plan.agents, options.duration_s, options.seed);
  } else {
    const std::vector<RingMotion> motions = presetMotions(options.preset, options.seed);
    if (motions.empty()) {
      std::string names;
      for (const std::string& n : presetNames()) names += (names.empty() ? "" : ", ") + n;
      return Error{ErrorCode::kInvalidArgument, "unknown preset '" + options.preset + "' (use one of " + names + ")"};
    }
    SplineFitOptions fit;
    fit.knot_spacing_s = 0.1;
    fit.smoothing = 1e-6;
    for (std::size_t i = 0; i < motions.size(); ++i) {
      const std::vector<PathSample> samples =
          sampleRingPath(motions[i], options.duration_s, deriveSeed(options.seed, kPathStream, i + 1));
      Result<BodyTrajectory> trajectory = fitTrajectory(samples, options.duration_s, fit);
      if (!trajectory) return trajectory.error();
      plan.agents.push_back({"agent" + std::to_string(i), options.preset, std::move(trajectory).value()});
    }
    plan.layout = syntheticHall(options.seed);
  }
  clearPaths(plan.layout, plan.agents, options.duration_s, options.min_clearance_m);
  return plan;
}

Result<MissionPlan> planPreset(const std::string& preset, std::uint64_t seed, double duration_s) {
  MissionPlanOptions options;
  options.preset = preset;
  options.seed = seed;
  options.duration_s = duration_s;
  return planMission(options);
}

}  // namespace cvislam::sim
