// What the options and the sensor input decide before any of the agent's threads starts: the recording (or a live
// stream's or the embedding program's rig, from its calibration files), stereo or mono, the IMU noise, tracking and
// mapping made for those sensors, the frames to run, and the feed that hands them to tracking.
#pragma once

#include <atomic>
#include <functional>
#include <memory>
#include <vector>

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/runtime/agent.hpp"
#include "agent_rt/runtime/frame_feed.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "agent_rt/sources/recording.hpp"
#include "agent_rt/tracking/tracker.hpp"

namespace cvislam::agent {

// What the sensor input and the options decide before any thread starts.
struct RunPlan {
  std::unique_ptr<Recording> recording;  // none for a live stream
  SensorRig rig;
  bool stereo;
  double imu_noise_inflation;
  SensorSetup setup;
  std::unique_ptr<Tracker> tracker;
  std::unique_ptr<Mapper> mapper;
  std::vector<dataset::RigFrame> frames;
};

// Opens the sensor input, chooses the mode and the IMU noise, and makes tracking and mapping for its sensors. Fills
// what `options` takes from the sensors.
Result<RunPlan> planRun(AgentOptions& options);

// The frames for tracking: the recording's, read ahead by a loader thread (which first calls `on_loader_start`), or
// the driver's live topics.
Result<std::unique_ptr<FrameFeed>> openFeed(const AgentOptions& options, RunPlan& plan, const std::atomic<bool>& stop,
                                            const std::function<void()>& on_loader_start);

}  // namespace cvislam::agent
