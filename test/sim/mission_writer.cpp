#include "test/sim/mission_writer.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <fstream>
#include <mutex>
#include <numbers>
#include <optional>
#include <thread>

#include "common/camera/camera_model.hpp"
#include "common/core/text.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "common/dataset/euroc_writer.hpp"
#include "test/sim/random.hpp"
#include "test/sim/renderer.hpp"

namespace cvislam::sim {

namespace {

constexpr std::uint64_t kImuStream = 0x1111;
constexpr std::uint64_t kPixelNoiseStream = 0x2222;
constexpr std::uint64_t kExposureStream = 0x3333;

void addPixelNoise(dataset::GrayImage& image, double sigma, Rng& rng) {
  for (std::size_t i = 0; i + 1 < image.pixels.size(); i += 2) {
    // Box-Muller, both outputs.
    const double u1 = 1.0 - rng.uniform();
    const double u2 = rng.uniform();
    const double r = sigma * std::sqrt(-2.0 * std::log(u1));
    const double n0 = r * std::cos(2.0 * std::numbers::pi * u2), n1 = r * std::sin(2.0 * std::numbers::pi * u2);
    image.pixels[i] = static_cast<std::uint8_t>(std::clamp(std::lround(image.pixels[i] + n0), 0L, 255L));
    image.pixels[i + 1] = static_cast<std::uint8_t>(std::clamp(std::lround(image.pixels[i + 1] + n1), 0L, 255L));
  }
}

std::string vec(const Eigen::Vector3d& v) {
  return "[" + text::formatDouble(v.x()) + ", " + text::formatDouble(v.y()) + ", " + text::formatDouble(v.z()) + "]";
}

Status writeMissionYaml(const MissionPlan& plan, const MissionWriterOptions& options) {
  const std::filesystem::path path = options.out_dir / "mission.yaml";
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << "# cvislam_sim mission: what was simulated. Ground truth of all agents is in one world frame.\n";
  out << "preset: " << plan.preset << "\nseed: " << options.seed
      << "\nduration_s: " << text::formatDouble(plan.duration_s) << "\nstart_time_ns: " << options.start_time_ns
      << "\ngravity_w: [0, 0, -9.81]\n";
  out << "imu_noise: " << (options.imu_options.noise ? "true" : "false")
      << "\npixel_noise_sigma: " << text::formatDouble(options.pixel_noise_sigma)
      << "\nexposure_amplitude: " << text::formatDouble(options.exposure_amplitude) << "\n";
  if (options.camera_time_shift_ns != 0) {
    out << "camera_time_shift_ns: " << options.camera_time_shift_ns << "  # t_imu = t_cam + shift\n";
  }
  out << "agents:\n";
  for (const AgentPlan& a : plan.agents) {
    const geometry::SE3d T_w_b = a.trajectory.state(0.0).T_w_b;
    const Eigen::Quaterniond& q = T_w_b.quaternion();
    out << "  - {name: " << a.name << ", motion: " << a.source << ", start_p_w: " << vec(T_w_b.translation())
        << ", start_q_w_b_wxyz: [" << text::formatDouble(q.w()) << ", " << text::formatDouble(q.x()) << ", "
        << text::formatDouble(q.y()) << ", " << text::formatDouble(q.z()) << "]}\n";
  }
  out << "hall: {min: " << vec(plan.layout.hall.min_w) << ", max: " << vec(plan.layout.hall.max_w) << "}\nobstacles:\n";
  for (const Box& b : plan.layout.obstacles) {
    out << "  - {kind: " << b.kind << ", min: " << vec(b.min_w) << ", max: " << vec(b.max_w) << "}\n";
  }
  out.close();
  if (!out) return Error{ErrorCode::kIoError, path.string() + ": cannot write"};
  return Status::Ok();
}

}  // namespace

MissionWriterOptions defaultWriterOptions() {
  MissionWriterOptions o;
  o.cam0 = dataset::eurocCam0();
  o.cam1 = dataset::eurocCam1();
  o.imu = dataset::eurocImu();
  return o;
}

Status MissionWriterOptions::validate() const {
  if (out_dir.empty()) return Error{ErrorCode::kInvalidArgument, "no output folder given"};
  if (pixel_noise_sigma < 0.0 || pixel_noise_sigma > 50.0) {
    return Error{ErrorCode::kInvalidArgument, "pixel noise sigma must be in [0, 50] grey levels"};
  }
  if (exposure_amplitude < 0.0 || exposure_amplitude >= 1.0) {
    return Error{ErrorCode::kInvalidArgument, "exposure amplitude must be in [0, 1)"};
  }
  if (camera_time_shift_ns < -1'000'000'000 || camera_time_shift_ns > 1'000'000'000) {
    return Error{ErrorCode::kInvalidArgument, "the camera clock shift must be within 1 s"};
  }
  const double ratio = imu.rate_hz / cam0.rate_hz;
  if (std::abs(ratio - std::round(ratio)) > 1e-9 || ratio < 1.0) {
    return Error{ErrorCode::kInvalidArgument, "the IMU rate must be a whole multiple of the camera rate"};
  }
  return Status::Ok();
}

Status writeMission(const MissionPlan& plan, const MissionWriterOptions& options) {
  if (Status st = options.validate(); !st) return st;
  std::error_code ec;
  std::filesystem::create_directories(options.out_dir, ec);
  if (ec) return Error{ErrorCode::kIoError, options.out_dir.string() + ": cannot create folder: " + ec.message()};

  WorldOptions world_options;
  world_options.seed = options.seed;
  world_options.texture = options.texture;
  const World world(plan.layout, world_options);

  std::vector<Renderer> renderers;
  std::vector<dataset::CameraCalibration> cameras = {options.cam0};
  if (options.stereo) cameras.push_back(options.cam1);
  for (const dataset::CameraCalibration& cal : cameras) {
    Result<camera::CameraModel> model = camera::CameraModel::create(cal);
    if (!model) return model.error();
    renderers.emplace_back(std::move(model).value());
  }
  if (Status st = writeMissionYaml(plan, options); !st) return st;

  const auto imu_per_frame = static_cast<std::int64_t>(std::lround(options.imu.rate_hz / options.cam0.rate_hz));
  const auto imu_period_ns = static_cast<std::int64_t>(std::llround(1e9 / options.imu.rate_hz));
  const auto imu_ticks = static_cast<std::int64_t>(std::floor(plan.duration_s * options.imu.rate_hz + 1e-9)) + 1;
  const auto frames = static_cast<std::size_t>((imu_ticks - 1) / imu_per_frame + 1);

  std::mutex progress_mutex;
  const auto write_agent = [&](std::size_t a, std::vector<Renderer>& agent_renderers) -> Status {
    const AgentPlan& agent = plan.agents[a];
    dataset::EurocWriterOptions writer_options;
    writer_options.cameras = cameras;
    writer_options.imu = options.imu;
    writer_options.overwrite = options.overwrite;
    Result<dataset::EurocWriter> writer = dataset::EurocWriter::create(options.out_dir / agent.name, writer_options);
    if (!writer) return writer.error().withContext(agent.name);
    ImuSimulator imu(options.imu, options.imu_options, deriveSeed(options.seed, kImuStream, a));
    Rng pixel_rng(deriveSeed(options.seed, kPixelNoiseStream, a));
    const double exposure_phase =
        Rng(deriveSeed(options.seed, kExposureStream, a)).uniform(0.0, 2.0 * std::numbers::pi);
    dataset::GrayImage image;
    std::size_t frame = 0;
    for (std::int64_t k = 0; k < imu_ticks; ++k) {
      const double t_s = static_cast<double>(k) / options.imu.rate_hz;
      const std::int64_t t_ns = options.start_time_ns + k * imu_period_ns;
      const KinematicState state = agent.trajectory.state(t_s);
      dataset::ImuSample sample;
      dataset::GroundTruthState gt;
      imu.step(state, t_ns, sample, gt);
      if (Status st = writer->addImu(sample); !st) return st.error().withContext(agent.name);
      if (Status st = writer->addGroundTruth(gt); !st) return st.error().withContext(agent.name);
      if (k % imu_per_frame != 0) continue;
      // Exposure: two slow sinusoids, so the change is smooth and not periodic within a mission.
      const double gain = 1.0 + options.exposure_amplitude *
                                    (0.7 * std::sin(2.0 * std::numbers::pi * t_s / 15.0 + exposure_phase) +
                                     0.3 * std::sin(2.0 * std::numbers::pi * t_s / 6.3 + 2.0 * exposure_phase));
      for (std::size_t c = 0; c < agent_renderers.size(); ++c) {
        const geometry::SE3d T_w_c = state.T_w_b * cameras[c].T_b_c;
        agent_renderers[c].render(world, T_w_c, gain, image);
        if (options.pixel_noise_sigma > 0.0) addPixelNoise(image, options.pixel_noise_sigma, pixel_rng);
        if (Status st = writer->addImage(static_cast<int>(c), t_ns - options.camera_time_shift_ns, image); !st)
          return st.error().withContext(agent.name);
      }
      ++frame;
      if (options.progress) {
        const std::lock_guard lock(progress_mutex);
        options.progress(a, frame, frames);
      }
    }
    if (Status st = writer->close(); !st) return st.error().withContext(agent.name);
    return Status::Ok();
  };

  // Agents are independent (each has its own seeded streams): render them on `threads` threads, each with its
  // own renderers; the first error wins.
  const auto workers = static_cast<std::size_t>(std::clamp<int>(options.threads, 1, 64));
  if (workers == 1 || plan.agents.size() == 1) {
    for (std::size_t a = 0; a < plan.agents.size(); ++a) {
      if (Status st = write_agent(a, renderers); !st) return st;
    }
    return Status::Ok();
  }
  std::atomic<std::size_t> next{0};
  std::mutex error_mutex;
  std::optional<Error> first_error;
  std::vector<std::thread> pool;
  for (std::size_t w = 0; w < std::min(workers, plan.agents.size()); ++w) {
    pool.emplace_back([&] {
      std::vector<Renderer> own = renderers;  // a copy per thread
      for (std::size_t a = next++; a < plan.agents.size(); a = next++) {
        if (Status st = write_agent(a, own); !st) {
          const std::lock_guard lock(error_mutex);
          if (!first_error) first_error = st.error();
          return;
        }
      }
    });
  }
  for (std::thread& t : pool) t.join();
  if (first_error) return *first_error;
  return Status::Ok();
}

Status renderPreset(const std::string& preset, std::uint64_t seed, double duration_s, bool stereo,
                    const std::filesystem::path& out_dir, int threads) {
  MissionPlanOptions plan_options;
  plan_options.preset = preset;
  plan_options.seed = seed;
  plan_options.duration_s = duration_s;
  Result<MissionPlan> plan = planMission(plan_options);
  if (!plan) return plan.error();
  MissionWriterOptions writer = defaultWriterOptions();
  writer.out_dir = out_dir;
  writer.seed = seed;
  writer.stereo = stereo;
  writer.threads = threads;
  return writeMission(*plan, writer);
}

}  // namespace cvislam::sim
