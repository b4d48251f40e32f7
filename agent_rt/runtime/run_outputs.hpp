// What the agent writes when a run ends: the trajectories, latency.json and summary.json (the link writes its own
// report), and the summary printed on stdout.
#pragma once

#include "agent_rt/runtime/agent.hpp"
#include "agent_rt/runtime/mapping_thread.hpp"
#include "agent_rt/runtime/trajectory_recorder.hpp"

namespace cvislam::agent {

// What the run decided at start that the outputs report.
struct RunSetup {
  bool stereo = false;
  double imu_noise_inflation = 1.0;
};

// Fills the summary's output paths and writes the files into options.output.
Status writeRunOutputs(const AgentOptions& options, const TrajectoryRecorder& recorder,
                       const MappingStats& mapping_stats, const RunSetup& setup, AgentRunSummary& summary);

}  // namespace cvislam::agent
