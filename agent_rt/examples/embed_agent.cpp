// An example of the embedding API (cvislam/agent.hpp): a program that owns its sensors runs the agent inside itself.
// Here a EuRoC folder stands in for the robot's camera and IMU drivers: its IMU samples and images are pushed in
// time order, at the sensor's pace (or as fast as the agent takes them with --replay), and the newest state is
// printed once a second from the agent's callback.
//
//   cvislam_embed_example SEQ_DIR CAMCHAIN.yaml IMU.yaml OUT_DIR [--replay]
//
// SEQ_DIR holds mav0 (EuRoC/ASL); the two YAML files are Kalibr's, describing that rig.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "common/dataset/euroc.hpp"
#include "cvislam/agent.hpp"

namespace {

// The newest state, handed from the agent's threads to this program's main thread. The callback only copies: it
// runs on the agent's tracking and propagation threads and must return quickly.
class NewestState {
 public:
  void set(const cvislam::AgentState& state) {
    std::lock_guard lock(mutex_);
    state_ = state;
    ++count_;
  }
  bool get(cvislam::AgentState& out, long& count) {
    std::lock_guard lock(mutex_);
    out = state_;
    count = count_;
    return count_ > 0;
  }

 private:
  std::mutex mutex_;
  cvislam::AgentState state_;
  long count_ = 0;
};

// Latencies the callback saw, one log per kind of state: each kind comes from one agent thread, and the log is read
// once the agent has finished. The room is reserved up front, so the callback never allocates.
class LatencyLog {
 public:
  explicit LatencyLog(std::size_t capacity) : ms_(capacity) {}
  void add(double ms) {
    if (count_ < ms_.size()) ms_[count_++] = ms;
  }
  // p50 and p99 (nearest rank), after the agent finished.
  std::pair<double, double> percentiles() {
    if (count_ == 0) return {0.0, 0.0};
    std::sort(ms_.begin(), ms_.begin() + static_cast<std::ptrdiff_t>(count_));
    const auto at = [&](double q) {
      return ms_[std::min(count_ - 1, static_cast<std::size_t>(q * static_cast<double>(count_)))];
    };
    return {at(0.50), at(0.99)};
  }
  [[nodiscard]] std::size_t count() const { return count_; }

 private:
  std::vector<double> ms_;
  std::size_t count_ = 0;
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 5) {
    std::fprintf(stderr, "usage: %s SEQ_DIR CAMCHAIN.yaml IMU.yaml OUT_DIR [--replay]\n", argv[0]);
    return 2;
  }
  const bool replay = argc > 5 && std::strcmp(argv[5], "--replay") == 0;
  auto sequence = cvislam::dataset::EurocSequence::open(argv[1]);
  if (!sequence) {
    std::fprintf(stderr, "%s\n", sequence.error().toString().c_str());
    return 1;
  }

  NewestState newest;
  LatencyLog frame_latency(1 << 16);
  LatencyLog imu_latency(1 << 20);
  cvislam::AgentConfig config;
  config.calibration = argv[2];
  config.imu_calibration = argv[3];
  config.output = argv[4];
  config.replay = replay;
  config.on_state = [&](const cvislam::AgentState& state) {
    newest.set(state);
    (state.kind == cvislam::AgentState::Kind::kFrame ? frame_latency : imu_latency).add(state.latency_ms);
  };
  std::string error;
  auto agent = cvislam::Agent::create(config, &error);
  if (!agent) {
    std::fprintf(stderr, "cannot start the agent: %s\n", error.c_str());
    return 1;
  }

  // The "drivers": IMU samples up to each frame's time, then the frame.
  const auto imu = sequence->imu();
  const auto& frames = sequence->rigFrames();
  const std::size_t pixels = static_cast<std::size_t>(agent->width()) * static_cast<std::size_t>(agent->height());
  std::vector<std::uint8_t> left(pixels);
  std::vector<std::uint8_t> right(pixels);
  std::size_t next_imu = 0;
  const auto start = std::chrono::steady_clock::now();
  auto next_print = start;
  for (const auto& frame : frames) {
    if (agent->stereo() && !frame.cam1) continue;
    for (; next_imu < imu.size() && imu[next_imu].t_ns <= frame.t_ns; ++next_imu) {
      const auto& s = imu[next_imu];
      agent->pushImu(
          {s.t_ns, {s.gyro_s.x(), s.gyro_s.y(), s.gyro_s.z()}, {s.accel_s.x(), s.accel_s.y(), s.accel_s.z()}});
    }
    if (next_imu < imu.size()) {  // the sample after the frame closes its interval
      const auto& s = imu[next_imu++];
      agent->pushImu(
          {s.t_ns, {s.gyro_s.x(), s.gyro_s.y(), s.gyro_s.z()}, {s.accel_s.x(), s.accel_s.y(), s.accel_s.z()}});
    }
    if (!sequence->loadImageInto(0, frame.cam0, left).ok()) continue;
    if (agent->stereo() && !sequence->loadImageInto(1, *frame.cam1, right).ok()) continue;
    if (!replay) {  // a camera delivers at its own pace
      std::this_thread::sleep_until(start + std::chrono::nanoseconds(frame.t_ns - frames.front().t_ns));
    }
    agent->pushFrame(frame.t_ns, left.data(), agent->stereo() ? right.data() : nullptr);

    cvislam::AgentState state;
    long count = 0;
    if (std::chrono::steady_clock::now() >= next_print && newest.get(state, count)) {
      std::printf("t=%.2f s  %s  p=(%.3f, %.3f, %.3f) m  latency %.2f ms  (%ld states)\n",
                  static_cast<double>(state.t_ns - frames.front().t_ns) * 1e-9, state.metric ? "metric" : "up to scale",
                  state.p_w_b[0], state.p_w_b[1], state.p_w_b[2], state.latency_ms, count);
      next_print = std::chrono::steady_clock::now() + std::chrono::seconds(1);
    }
  }
  const cvislam::AgentSummary summary = agent->finish();
  if (!summary.ok) {
    std::fprintf(stderr, "the agent failed: %s\n", summary.error.c_str());
    return 1;
  }
  const auto [frame_p50, frame_p99] = frame_latency.percentiles();
  const auto [imu_p50, imu_p99] = imu_latency.percentiles();
  std::printf("push to state, p50 / p99: frames %.3f / %.3f ms (%zu), IMU samples %.3f / %.3f ms (%zu)\n", frame_p50,
              frame_p99, frame_latency.count(), imu_p50, imu_p99, imu_latency.count());
  std::printf("frames %llu, tracked %llu, keyframes %llu, dropped %llu; trajectory %s\n",
              static_cast<unsigned long long>(summary.frames), static_cast<unsigned long long>(summary.tracked_frames),
              static_cast<unsigned long long>(summary.keyframes),
              static_cast<unsigned long long>(summary.frames_dropped), summary.trajectory.c_str());
  return 0;
}
