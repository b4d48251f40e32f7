// The agent's link to the server (CVI-SLAM IV-D): a thread beside tracking and mapping.
//
//   mapping --MapDeltaMessage (iceoryx)--> link --MapBatch (gRPC, at most 5/s)--> server
//                                          link <--acknowledgements, corrected keyframe states, the covisible
//                                                   map (<= 2/s)-- server
//   mapping <--AnchorMessage (iceoryx)--   link   the covisible map and corrections, checked
//
// It learns what changed in the local map from mapping's delta after each keyframe (a topic of its own: one
// message carries the keyframe in full, the points made, every structural change in order, and the states and
// positions of the whole local map, so structure and states always come from the same world frame). It keeps
// what it must send in a bounded store (link_store.hpp), sends new keyframes and points in full once and
// compact updates afterwards, and resends after a reconnection whatever the server had not stored.
//
// Without a server (or with the server gone) the agent is exactly the VIO it is alone: the link never blocks
// tracking or mapping. It reconnects by itself with backoff. At the end of a run it waits up to
// flush_timeout_s for the server to acknowledge everything, then says goodbye.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "agent_rt/link/link_store.hpp"
#include "agent_rt/link/uplink_pacer.hpp"
#include "agent_rt/messages/messages.hpp"
#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

struct LinkOptions {
  std::string server;  // host:port; empty: no link
  std::string mission = "default";
  std::string token;         // the mission's token (the server's tokens file); empty: none
  std::string tls_ca_pem;    // PEM of the CA that signed the server's TLS certificate; empty: plaintext
  double max_rate_hz = 5.0;  // up messages per second (paper: 5)
  std::size_t max_batch_bytes = 512U << 10U;
  double reconnect_min_s = 0.2;  // backoff after a failed attempt, doubling up to reconnect_max_s
  double reconnect_max_s = 2.0;
  double connect_timeout_s = 1.0;
  double flush_timeout_s = 15.0;  // at the end: how long to wait for the server to acknowledge everything
  int keepalive_ms = 1000;
  // How long a keepalive ping may wait for its answer. It waits behind whatever the agent has on its way up: on a
  // slow radio, seconds (the pacer keeps that near pacer.window_s). Longer: a dead server is noticed later.
  int keepalive_timeout_ms = 5000;
  UplinkPacerOptions pacer;
  // The own keyframes the local map keeps (the mapper's N), told to the server in the Hello so that its
  // covisible map leaves them out; 0: the server's default.
  std::uint32_t local_map_keyframes = 0;
  LinkStoreOptions store;
  // Mapping hands a keyframe to the link as soon as it is in the local map, and its refined state after the local
  // BA: the BA's time (0.1-0.7 s on busy cores) is then not on the keyframe's way to the server. The keyframe says
  // so, and the server stores it at once but fuses it, queries with it and sends it down only once its refined
  // state came. Off: one delta per keyframe, after its BA.
  bool keyframe_before_local_ba = true;

  [[nodiscard]] Status validate() const;
};

// What the Hello says about the agent's sensors.
struct LinkSensors {
  bool stereo = false;
  bool uses_imu = true;
  dataset::CameraCalibration cam0;
  geometry::SE3d T_s_c0;
  std::optional<dataset::CameraCalibration> cam1;
  geometry::SE3d T_s_c1;
  imu::ImuNoise imu_noise;  // as the agent uses it (inflated)
  double imu_rate_hz = 200.0;
};

// Where the link reads mapping's deltas from: iceoryx in the agent, a queue in tests.
class DeltaSource {
 public:
  virtual ~DeltaSource() = default;
  // The next delta, or nullptr when none is waiting. It stays valid until release().
  virtual const MapDeltaMessage* next() = 0;
  virtual void release() = 0;
};

// Where the link writes what the server sent down for mapping (the covisible map and corrections): iceoryx in
// the agent, a queue in tests. The link loans a message, decodes into it, and publishes it, or discards it
// when the server's message was refused.
class AnchorSink {
 public:
  virtual ~AnchorSink() = default;
  // A message to fill, or nullptr when none can be had now (the server's message is then not passed on).
  virtual AnchorMessage* loan() = 0;
  virtual void publish() = 0;
  virtual void discard() = 0;
};

// The agent's newest tracked pose, which each uplink batch carries for the server's live viewers.
struct LivePose {
  std::int64_t t_ns = 0;
  std::uint32_t map_id = 0;  // the agent's map whose world frame w it is in
  geometry::SE3d T_w_s;
  bool metric = false;  // the IMU is initialised (else up to scale)
};

// Where the link reads that pose from: tracking's state topic over iceoryx in the agent, a value in tests.
class PoseSource {
 public:
  virtual ~PoseSource() = default;
  // The newest pose; false when tracking has none yet.
  virtual bool newest(LivePose& out) = 0;
};

// Counters for the progress line and link.json; a copy, safe to read from any thread.
struct LinkStatus {
  bool connected = false;
  std::uint32_t connections = 0;  // streams opened
  std::uint32_t failed_attempts = 0;
  std::string last_error;
  LinkBacklog backlog;
  LinkStoreCounters store;
  std::uint64_t acked_sequence = 0;
  std::uint64_t sent_sequence = 0;
  std::uint64_t up_bytes = 0;
  std::uint64_t down_bytes = 0;
  std::size_t unacked_bytes = 0;       // batches sent and not yet acknowledged
  std::size_t window_bytes = 0;        // what the pacer lets be unacknowledged
  double uplink_rate_bytes_per_s = 0;  // its estimate of the link's rate (0: none yet)
  bool flushed = false;                // at the end: everything acknowledged
  // Covisible maps from the server: checked and decoded, or refused (malformed; the link keeps going).
  std::uint64_t covisible_accepted = 0;
  std::uint64_t covisible_refused = 0;
  std::string covisible_last_refusal;
  std::uint64_t corrections_refused = 0;
  std::uint64_t anchor_messages_published = 0;  // to mapping
  std::uint64_t anchor_messages_dropped = 0;    // no message to loan: mapping is behind
};

// What the agent's health message says of the link; read without allocating.
struct LinkHealth {
  bool connected = false;
  std::uint64_t acked_sequence = 0;
  std::uint64_t keyframes_waiting = 0;  // not sent, or sent and not acknowledged
};

class Link {
 public:
  static Result<std::unique_ptr<Link>> create(const LinkOptions& options, AgentId agent, const LinkSensors& sensors);
  ~Link();
  Link(const Link&) = delete;
  Link& operator=(const Link&) = delete;

  // Runs on the calling thread until `stop` is set and then everything is acknowledged (or flush_timeout_s has
  // passed): reads deltas from `source`, keeps the stream up, sends, reads acknowledgements, and passes the
  // server's covisible maps and corrections on to `anchors` (nullptr: they are checked and counted only). Each
  // batch carries the newest pose of `poses` (nullptr: none).
  void run(DeltaSource& source, const std::atomic<bool>& stop, AnchorSink* anchors = nullptr,
           PoseSource* poses = nullptr);

  // From another thread: ends the current stream at once (a write blocked on a server that stopped reading
  // returns). run() goes on, and reconnects unless it was stopping.
  void abort();

  [[nodiscard]] LinkStatus status() const;
  // One line for the agent's progress output, e.g. "link up, 2 KF waiting" or "link DOWN (retrying), 14 KF waiting".
  [[nodiscard]] std::string progressText() const;
  [[nodiscard]] LinkHealth health() const;
  // link.json (traffic by kind and direction, reconnections, what was dropped) and link_timeline.csv (per second:
  // bytes up and down, connected, keyframes waiting). Call after run() returned.
  Status writeReport(const std::filesystem::path& dir) const;

  struct Impl;

 private:
  explicit Link(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::agent
