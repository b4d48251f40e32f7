// cvislam's agent inside your own program: create it from options, push your camera frames and IMU samples with
// their sensor timestamps, get its state back through a callback, finish. Standard C++ only: no iceoryx, gRPC,
// Eigen or OpenCV comes in with this header. Link cvislam::agent_api.
//
//   cvislam::AgentConfig config;
//   config.calibration = "camchain-imucam.yaml";  // Kalibr
//   config.imu_calibration = "imu.yaml";
//   config.output = "run1";
//   config.on_state = [](const cvislam::AgentState& s) { /* hand s to the controller */ };
//   std::string error;
//   auto agent = cvislam::Agent::create(config, &error);
//   // IMU thread:    agent->pushImu({t_ns, {wx, wy, wz}, {ax, ay, az}});
//   // camera thread: agent->pushFrame(t_ns, left_pixels, right_pixels);
//   cvislam::AgentSummary summary = agent->finish();
//
// Threads: the agent runs its own (tracking, mapping, and with a server the link); pushImu and pushFrame may be
// called from one thread or each from its own, and neither allocates nor waits (unless wait_when_full): a full
// queue drops what is pushed and says so in the return value and the summary. on_state is called on the agent's
// tracking thread for every frame, and with the IMU on its propagation thread for every IMU sample once the IMU is
// initialised (the newest frame's state carried forward by the samples since): return quickly from it. Call
// finish() after the last push. The process runs iceoryx's RouDi inside unless external_roudi is set (one RouDi per
// machine: with several agents on one machine, start iox-roudi and set it).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

namespace cvislam {

// One state of the IMU (body) frame in the agent's world frame (gravity along -z once `metric`).
struct AgentState {
  enum class Kind : std::uint8_t { kFrame, kImuPropagated };
  enum class Tracking : std::uint8_t { kWaitingForMap, kTracking, kRelocalising };
  Kind kind = Kind::kFrame;
  Tracking tracking = Tracking::kWaitingForMap;
  bool tracked = false;   // kFrame: the pose comes from matches against the map, not a prediction
  bool keyframe = false;  // kFrame: the frame became a keyframe
  bool metric = false;    // the IMU is initialised: metric scale and gravity; before, a monocular pose is up to scale
  std::uint32_t map_id = 0;
  std::int64_t t_ns = 0;                            // sensor time (the IMU's clock)
  std::array<double, 4> q_w_b{0.0, 0.0, 0.0, 1.0};  // x, y, z, w
  std::array<double, 3> p_w_b{0.0, 0.0, 0.0};       // [m]
  std::array<double, 3> v_w{0.0, 0.0, 0.0};         // [m/s]
  std::array<double, 3> gyro_bias{0.0, 0.0, 0.0};   // [rad/s]
  std::array<double, 3> accel_bias{0.0, 0.0, 0.0};  // [m/s^2]
  double latency_ms = 0.0;                          // from the frame's or sample's push to this state
};

struct ImuMeasurement {
  std::int64_t t_ns = 0;                       // the IMU's clock [ns]
  std::array<double, 3> gyro{0.0, 0.0, 0.0};   // angular rate in the IMU frame [rad/s]
  std::array<double, 3> accel{0.0, 0.0, 0.0};  // specific force in the IMU frame [m/s^2]
};

struct AgentConfig {
  std::string calibration;      // Kalibr camchain-imucam.yaml (cam0; cam1 for stereo); required
  std::string imu_calibration;  // Kalibr imu.yaml; empty: vision only
  std::string output;           // folder for the trajectories, latency profile and summary written by finish()
  std::string config_file;      // optional agent YAML (deploy/agent_config.yaml); the fields below win
  bool stereo = true;           // use cam1 when the calibration has it
  std::uint16_t agent_id = 0;
  std::string server;   // host:port of a cvislam_server; empty: the agent alone
  std::string mission;  // on the server [default]
  std::string token;    // the mission's token, when the server wants one
  bool external_roudi = false;
  // Replaying a recording: pushFrame waits for room, and tracking waits for mapping after each keyframe, so that a
  // run repeats exactly. Leave false for a live robot.
  bool replay = false;
  bool quiet = true;  // no progress lines on stderr
  std::function<void(const AgentState&)> on_state;
};

struct AgentSummary {
  bool ok = false;
  std::string error;  // when not ok
  std::uint64_t frames = 0;
  std::uint64_t tracked_frames = 0;
  std::uint64_t keyframes = 0;
  std::uint64_t frames_dropped = 0;  // pushed into a full ring
  std::uint64_t imu_dropped = 0;     // pushed into a full queue
  double imu_initialised_at_s = -1.0;
  // The first frame tracked in a final world frame (metric, gravity-aligned); -1 never. Earlier poses are marked
  // in the trajectory files ("# before_init" rows) and their states carry no kMetric flag.
  double tracking_initialised_at_s = -1.0;
  // The camera-IMU time offset at the end (t_imu = t_cam + offset): the calibration's, or the estimate when the
  // config file says imu.estimate_time_offset.
  double time_offset_ms = 0.0;
  std::string trajectory;  // the files written
  std::string summary_json;
};

class Agent {
 public:
  // Reads the calibration, starts the agent's threads; nullptr with `error` set when it cannot.
  static std::unique_ptr<Agent> create(const AgentConfig& config, std::string* error);
  ~Agent();  // finishes, if finish() was not called
  Agent(const Agent&) = delete;
  Agent& operator=(const Agent&) = delete;

  // cam0's (and in stereo cam1's) image: 8-bit grey, width x height of the calibration, rows without padding.
  bool pushFrame(std::int64_t t_ns, const std::uint8_t* left, const std::uint8_t* right = nullptr);
  bool pushImu(const ImuMeasurement& sample);
  // The image size the calibration asks for.
  [[nodiscard]] int width() const;
  [[nodiscard]] int height() const;
  [[nodiscard]] bool stereo() const;

  // Ends the stream: the frames pushed are tracked, the outputs written, the threads stopped.
  AgentSummary finish();

 private:
  struct Impl;
  explicit Agent(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam
