// The agent's live state, for a flight controller or planner in another process: plain structs (no iceoryx here) on
// iceoryx topics of service "cvislam_state", instance "agent<ID>" (the agent's id, as --agent-id gives it):
//
//   event "frames": one AgentStateMessage per camera frame, once it is tracked (kind kFrame);
//   event "imu":    with --live, one per IMU sample between frames: the newest tracked state carried forward by the
//                   IMU (kind kPropagated), once the IMU is initialised.
//   event "health": once a second, AgentHealthMessage: how the agent is doing (tracking, frame rate, backlog, the
//                   link, CPU per thread), for a robot's supervisor.
//
// A reader subscribes with a queue of 1 to read the newest state, or deeper to see every one; nothing waits for it.
// Frames: the state is of the IMU (body) frame s in the agent's world frame w, which is gravity-aligned (z up) and
// metric once kMetric is set; before that (monocular start) it is up to scale. Times: t_ns is the sensor time the
// state is at (the IMU's clock); the steady times are CLOCK_MONOTONIC, the capture of the frame or sample the state
// came from and the moment it was published, so latency = published - captured.
#pragma once

#include <cstdint>

namespace cvislam::agent::live {

inline constexpr const char* kStateServiceName = "cvislam_state";
inline constexpr const char* kStateFramesEvent = "frames";
inline constexpr const char* kStateImuEvent = "imu";
inline constexpr const char* kStateHealthEvent = "health";

inline constexpr std::uint32_t kStateMagic = 0x54535643;  // "CVST"
inline constexpr std::uint32_t kStateVersion = 1;

enum class StateKind : std::uint32_t { kFrame = 0, kPropagated = 1 };
// As tracking sees itself: waiting for a map (start, or a new map after a loss), tracking, relocalising.
enum class StateStatus : std::uint32_t { kWaitingForMap = 0, kTracking = 1, kRelocalising = 2 };
enum StateFlags : std::uint32_t {
  kTracked = 1U << 0,   // this frame's pose comes from matches against the map (else: predicted)
  kKeyframe = 1U << 1,  // this frame became a keyframe
  kMetric = 1U << 2,    // the IMU is initialised: metric scale, gravity along -z
};

struct AgentStateMessage {
  std::uint32_t magic = kStateMagic;
  std::uint32_t version = kStateVersion;
  std::uint64_t sequence = 0;  // per topic, from 0
  std::int64_t t_ns = 0;
  std::int64_t captured_steady_ns = 0;
  std::int64_t published_steady_ns = 0;
  StateKind kind = StateKind::kFrame;
  StateStatus status = StateStatus::kWaitingForMap;
  std::uint32_t flags = 0;
  std::uint32_t agent = 0;
  std::uint32_t map_id = 0;
  std::uint32_t map_epoch = 0;             // +1 each time the world frame moves (IMU initialisation)
  double q_w_s[4] = {0.0, 0.0, 0.0, 1.0};  // orientation x, y, z, w
  double p_w_s[3] = {0.0, 0.0, 0.0};       // position [m]
  double v_w[3] = {0.0, 0.0, 0.0};         // velocity [m/s]
  double gyro_bias[3] = {0.0, 0.0, 0.0};   // [rad/s]
  double accel_bias[3] = {0.0, 0.0, 0.0};  // [m/s^2]
};

// The agent's threads, in the order of AgentHealthMessage::cpu_percent.
inline constexpr const char* kHealthThreads[] = {"tracking", "mapping", "link", "loader", "propagation"};
inline constexpr std::uint32_t kHealthThreadCount = 5;

enum HealthFlags : std::uint32_t {
  kImuInitialised = 1U << 0,
  kLinkEnabled = 1U << 1,    // the agent streams to a server
  kLinkConnected = 1U << 2,  // and its stream is up
};

struct AgentHealthMessage {
  std::uint32_t magic = kStateMagic;
  std::uint32_t version = kStateVersion;
  std::uint64_t sequence = 0;  // from 0
  std::int64_t published_steady_ns = 0;
  std::uint32_t agent = 0;
  StateStatus status = StateStatus::kWaitingForMap;  // of the newest frame
  std::uint32_t flags = 0;
  std::uint32_t map_id = 0;
  double interval_s = 0.0;     // what the rates and CPU figures are over: since the previous message
  double frame_rate_hz = 0.0;  // frames tracked (or tried) per second over the interval
  std::uint64_t frames = 0;    // since start
  std::uint64_t tracked_frames = 0;
  std::uint64_t lost_frames = 0;
  std::uint64_t keyframes = 0;
  std::int32_t pending_keyframes = 0;  // keyframes mapping has not answered yet: its backlog
  std::uint32_t reserved = 0;
  // The link (zero without a server): the newest batch the server acknowledged, and the keyframes not yet
  // sent or acknowledged.
  std::uint64_t link_acked_batches = 0;
  std::uint64_t link_keyframes_waiting = 0;
  // Each thread's CPU over the interval, in percent of one core (-1: the thread does not run in this agent).
  double cpu_percent[kHealthThreadCount] = {-1.0, -1.0, -1.0, -1.0, -1.0};
};

}  // namespace cvislam::agent::live
