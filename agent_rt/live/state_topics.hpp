// The agent's live state, for a flight controller or planner in another process: plain structs (no iceoryx here) on
// iceoryx topics of service "cvislam_state", instance "agent<ID>" (the agent's id, as --agent-id gives it):
//
//   event "frames": one AgentStateMessage per camera frame, once it is tracked (kind kFrame);
//   event "imu":    with --live, one per IMU sample between frames: the newest tracked state carried forward by the
//                   IMU (kind kPropagated), once the IMU is initialised.
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

}  // namespace cvislam::agent::live
