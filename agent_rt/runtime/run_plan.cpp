#include "agent_rt/runtime/run_plan.hpp"

#include <cstdio>
#include <iostream>
#include <string>

#include "agent_rt/runtime/live_feed.hpp"
#include "agent_rt/runtime/recording_feed.hpp"
#include "agent_rt/sources/kalibr_rig.hpp"

namespace cvislam::agent {
namespace {

// The recording and its rig; a live stream has only its rig (from the calibration files).
struct OpenedSource {
  std::unique_ptr<Recording> recording;
  SensorRig rig;
  std::string source;
  bool simulated = false;
};

Result<OpenedSource> openSource(const AgentOptions& options) {
  if (!options.live.empty() || options.embedded_input) {
    auto rig = rigFromKalibrFiles(options.calibration, options.imu_calibration);
    if (!rig) return rig.error();
    std::string source = options.embedded_input ? "the embedding program" : "live stream '" + options.live + "'";
    return OpenedSource{nullptr, std::move(rig).value(), std::move(source), false};
  }
  RecordingOptions recording;
  recording.dataset = options.dataset;
  recording.mcap = options.mcap;
  recording.topics = options.topics;
  recording.calibration = options.calibration;
  recording.imu_calibration = options.imu_calibration;
  recording.require_imu = options.use_imu;
  auto opened = openRecording(recording);
  if (!opened) return opened.error();
  Recording& rec = **opened;
  if (!rec.diagnostics().empty() && !options.quiet) {
    std::fprintf(stderr, "[agent] the recording has %zu finding(s); the agent goes on without the bad rows:\n",
                 rec.diagnostics().findings().size());
    rec.diagnostics().print(std::cerr, 10);
  }
  SensorRig rig = rec.rig();
  std::string source = rec.describe();
  const bool simulated = rec.simulated();
  return OpenedSource{std::move(opened).value(), std::move(rig), std::move(source), simulated};
}

}  // namespace

Result<RunPlan> planRun(AgentOptions& options) {
  auto opened = openSource(options);
  if (!opened) return opened.error();
  const SensorRig& rig = opened->rig;
  const std::string& describe = opened->source;
  const bool has_cam1 = rig.cam1.has_value();
  if (options.mode == AgentMode::kStereo && !has_cam1) {
    return Error{ErrorCode::kInvalidArgument,
                 "stereo mode needs a second camera (cam1), which " + describe + " does not have: use --mode mono"};
  }
  const bool stereo = options.mode == AgentMode::kStereo || (options.mode == AgentMode::kAuto && has_cam1);
  // The frame ring holds both images of a pair at one size; a cam1 of another size would fail every frame.
  if (stereo && (rig.cam1->width != rig.cam0.width || rig.cam1->height != rig.cam0.height)) {
    return Error{ErrorCode::kInvalidArgument,
                 describe + ": cam1 is " + std::to_string(rig.cam1->width) + "x" + std::to_string(rig.cam1->height) +
                     " but cam0 is " + std::to_string(rig.cam0.width) + "x" + std::to_string(rig.cam0.height) +
                     "; stereo needs both at one resolution (or use --mode mono)"};
  }
  if (options.use_imu && !rig.imu) {
    return Error{ErrorCode::kInvalidArgument, describe +
                                                  " has no IMU calibration (imu0/sensor.yaml or --imu-calibration); "
                                                  "run with use_imu: false"};
  }
  double inflation = options.imu_noise_inflation;
  if (inflation == 0.0) inflation = opened->simulated ? 1.0 : 10.0;
  auto setup = makeSensorSetup(rig, stereo, inflation);
  if (!setup) return setup.error();
  options.tracking.agent = options.agent;
  options.tracking.use_imu = options.use_imu;
  options.mapping.agent = options.agent;
  options.mapping.use_imu = options.use_imu;
  applySensorSetup(*setup, options.tracking, options.mapping);
  // With a server, its covisible map is the agent's memory of the places it has been, in the states of the
  // server's global BA. Own older keyframes kept beside it carry the drift the server takes out: on eight simulated
  // agents they made every agent's onboard ATE worse. They are kept only without a server.
  if (!options.link.server.empty()) options.mapping.retention.place_keyframes = 0;
  const camera::CameraModel* right = setup->right ? &*setup->right : nullptr;
  auto tracker = Tracker::create(options.tracking, setup->left, right, setup->T_s_c);
  if (!tracker) return tracker.error();
  auto mapper = Mapper::create(options.mapping, setup->left, right, setup->T_s_c, setup->T_c0_c1);
  if (!mapper) return mapper.error();

  std::vector<dataset::RigFrame> frames;
  if (opened->recording) {
    frames = framesToRun(opened->recording->rigFrames(), stereo);
    if (options.max_frames > 0 && frames.size() > options.max_frames) frames.resize(options.max_frames);
    if (frames.empty()) return Error{ErrorCode::kDataError, describe + " has no usable camera frames"};
  }
  return RunPlan{
      std::move(opened->recording), std::move(opened->rig),    stereo,           inflation, std::move(setup).value(),
      std::move(tracker).value(),   std::move(mapper).value(), std::move(frames)};
}

Result<std::unique_ptr<FrameFeed>> openFeed(const AgentOptions& options, RunPlan& plan, const std::atomic<bool>& stop,
                                            const std::function<void()>& on_loader_start) {
  if (plan.recording) {
    RecordingFeedOptions feed;
    feed.stereo = plan.stereo;
    feed.use_imu = options.use_imu;
    feed.realtime = options.pace == Pace::kRealtime;
    feed.rate = options.rate;
    feed.ring_size = options.frame_ring_size;
    return std::unique_ptr<FrameFeed>(
        std::make_unique<RecordingFeed>(*plan.recording, plan.frames, feed, on_loader_start));
  }
  LiveFeedOptions feed;
  feed.stream = options.live;
  feed.width = plan.rig.cam0.width;
  feed.height = plan.rig.cam0.height;
  feed.stereo = plan.stereo;
  feed.use_imu = options.use_imu;
  feed.timeshift_cam_imu_ns = plan.rig.timeshift_cam_imu_ns;
  feed.imu_wait_s = options.live_imu_wait_s;
  feed.quiet = options.quiet;
  feed.stop = &stop;
  return openLiveFeed(feed);
}

}  // namespace cvislam::agent
