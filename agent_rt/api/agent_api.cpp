// The embedding API (cvislam/agent.hpp) over the agent's runtime: a PushFeed takes the program's frames and IMU, and
// runAgent runs on a thread of its own, which becomes the agent's tracking thread.
#include <future>
#include <thread>

#include "agent_rt/runtime/agent.hpp"
#include "agent_rt/runtime/push_feed.hpp"
#include "agent_rt/runtime/pushed_propagation.hpp"
#include "agent_rt/sources/kalibr_rig.hpp"
#include "common/core/steady_clock.hpp"
#include "cvislam/agent.hpp"

namespace cvislam {
namespace {

AgentState toApi(const agent::live::AgentStateMessage& m) {
  namespace live = agent::live;
  AgentState s;
  s.kind = m.kind == live::StateKind::kFrame ? AgentState::Kind::kFrame : AgentState::Kind::kImuPropagated;
  switch (m.status) {
    case live::StateStatus::kWaitingForMap:
      s.tracking = AgentState::Tracking::kWaitingForMap;
      break;
    case live::StateStatus::kTracking:
      s.tracking = AgentState::Tracking::kTracking;
      break;
    case live::StateStatus::kRelocalising:
      s.tracking = AgentState::Tracking::kRelocalising;
      break;
  }
  s.tracked = (m.flags & live::kTracked) != 0U;
  s.keyframe = (m.flags & live::kKeyframe) != 0U;
  s.metric = (m.flags & live::kMetric) != 0U;
  s.map_id = m.map_id;
  s.t_ns = m.t_ns;
  for (int k = 0; k < 4; ++k) s.q_w_b[static_cast<std::size_t>(k)] = m.q_w_s[k];
  for (std::size_t k = 0; k < 3; ++k) {
    s.p_w_b[k] = m.p_w_s[k];
    s.v_w[k] = m.v_w[k];
    s.gyro_bias[k] = m.gyro_bias[k];
    s.accel_bias[k] = m.accel_bias[k];
  }
  s.latency_ms = static_cast<double>(m.published_steady_ns - m.captured_steady_ns) * 1e-6;
  return s;
}

// The runtime's options from the API's.
Result<agent::AgentOptions> optionsOf(const AgentConfig& config, bool stereo) {
  agent::AgentOptions o;
  if (!config.config_file.empty()) {
    if (Status s = agent::loadAgentConfig(config.config_file, o); !s.ok()) return s.error();
  }
  o.embedded_input = true;
  o.calibration = config.calibration;
  o.imu_calibration = config.imu_calibration;
  o.use_imu = !config.imu_calibration.empty();
  o.output = config.output;
  o.mode = stereo ? agent::AgentMode::kStereo : agent::AgentMode::kMono;
  o.agent = config.agent_id;
  if (!config.server.empty()) o.link.server = config.server;
  if (!config.mission.empty()) o.link.mission = config.mission;
  o.link.token = config.token;
  o.roudi = config.external_roudi ? agent::RouDiMode::kExternal : agent::RouDiMode::kEmbedded;
  o.pace = config.replay ? agent::Pace::kSync : agent::Pace::kRealtime;
  o.quiet = config.quiet;
  if (Status s = o.validate(); !s.ok()) return s.error();
  return o;
}

}  // namespace

// The program's callback, for the states made between frames.
struct UserCallback final : agent::StateListener {
  explicit UserCallback(const AgentConfig& c) : config(c) {}
  void onState(const agent::live::AgentStateMessage& state) override {
    if (config.on_state) config.on_state(toApi(state));
  }
  const AgentConfig& config;
};

struct Agent::Impl final : agent::StateListener {
  // Every frame's state, on tracking's thread: to the IMU-rate propagation and to the program.
  void onState(const agent::live::AgentStateMessage& state) override {
    if (propagation) propagation->onFrameState(state);
    if (config.on_state) config.on_state(toApi(state));
  }

  AgentSummary finish() {
    if (!finished) {
      finished = true;
      feed->finish();
      if (runner.joinable()) runner.join();
      propagation.reset();
    }
    AgentSummary out;
    if (!result.ok()) {
      out.error = result.error().toString();
      return out;
    }
    const agent::AgentRunSummary& r = *result;
    out.ok = true;
    out.frames = r.frames;
    out.tracked_frames = r.tracked_frames;
    out.keyframes = r.keyframes;
    out.frames_dropped = r.live_faults.frames_lost;
    out.imu_dropped = r.live_faults.imu_lost;
    out.imu_initialised_at_s = r.imu_initialised_at_s;
    out.tracking_initialised_at_s = r.tracking_initialised_at_s;
    out.time_offset_ms = r.time_offset_ms;
    out.trajectory = r.trajectory.string();
    out.summary_json = (options.output / "summary.json").string();
    return out;
  }

  AgentConfig config;
  agent::AgentOptions options;
  agent::SensorRig rig;
  bool stereo = false;
  std::unique_ptr<agent::PushFeed> feed;
  std::unique_ptr<UserCallback> between_frames;
  std::unique_ptr<agent::PushedPropagation> propagation;  // with the IMU: its states between frames
  std::atomic<bool> stop{false};
  Result<agent::AgentRunSummary> result = Error{ErrorCode::kInternal, "the agent has not run"};
  std::thread runner;
  bool finished = false;
};

std::unique_ptr<Agent> Agent::create(const AgentConfig& config, std::string* error) {
  const auto fail = [&](const std::string& why) {
    if (error != nullptr) *error = why;
    return nullptr;
  };
  auto impl = std::make_unique<Impl>();
  impl->config = config;
  auto rig = agent::rigFromKalibrFiles(config.calibration, config.imu_calibration);
  if (!rig) return fail(rig.error().toString());
  impl->rig = *rig;
  impl->stereo = config.stereo && rig->cam1.has_value();
  auto options = optionsOf(config, impl->stereo);
  if (!options) return fail(options.error().toString());
  impl->options = *options;
  agent::PushFeedOptions feed;
  feed.width = rig->cam0.width;
  feed.height = rig->cam0.height;
  feed.stereo = impl->stereo;
  feed.use_imu = impl->options.use_imu;
  feed.timeshift_cam_imu_ns = rig->timeshift_cam_imu_ns;
  feed.imu_wait_s = impl->options.live_imu_wait_s;
  feed.wait_when_full = config.replay;
  impl->feed = std::make_unique<agent::PushFeed>(feed);
  if (impl->options.use_imu) {
    impl->between_frames = std::make_unique<UserCallback>(impl->config);
    impl->propagation = std::make_unique<agent::PushedPropagation>(*impl->between_frames);
  }

  // The runner says true once the agent runs, false when it could not start (its result says why).
  std::promise<bool> running;
  std::future<bool> started = running.get_future();
  Impl* d = impl.get();
  d->runner = std::thread([d, &running] {
    bool told = false;
    agent::AgentHooks hooks;
    hooks.listener = d;
    hooks.feed = d->feed.get();
    hooks.on_running = [&] {
      told = true;
      running.set_value(true);
    };
    auto result = agent::runAgent(d->options, d->stop, hooks);
    d->result = std::move(result);
    if (!told) running.set_value(false);
  });
  if (!started.get()) {
    d->runner.join();
    return fail(d->result.error().toString());
  }
  return std::unique_ptr<Agent>(new Agent(std::move(impl)));
}

Agent::Agent(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

Agent::~Agent() {
  if (impl_) (void)impl_->finish();
}

bool Agent::pushFrame(std::int64_t t_ns, const std::uint8_t* left, const std::uint8_t* right) {
  return impl_->feed->pushFrame(t_ns, left, right);
}

bool Agent::pushImu(const ImuMeasurement& m) {
  dataset::ImuSample s;
  s.t_ns = m.t_ns;
  s.gyro_s = {m.gyro[0], m.gyro[1], m.gyro[2]};
  s.accel_s = {m.accel[0], m.accel[1], m.accel[2]};
  if (impl_->propagation) impl_->propagation->pushImu(s, steadyNowNs());
  return impl_->feed->pushImu(s);
}

int Agent::width() const {
  return impl_->rig.cam0.width;
}
int Agent::height() const {
  return impl_->rig.cam0.height;
}
bool Agent::stereo() const {
  return impl_->stereo;
}

AgentSummary Agent::finish() {
  return impl_->finish();
}

}  // namespace cvislam
