#include "agent_rt/runtime/agent.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>

#include <nlohmann/json.hpp>

#include "agent_rt/ipc/embedded_roudi.hpp"
#include "agent_rt/live/live_service.hpp"
#include "agent_rt/messages/conversions.hpp"
#include "agent_rt/runtime/iceoryx_channels.hpp"
#include "agent_rt/runtime/mapping_thread.hpp"
#include "agent_rt/runtime/propagation_thread.hpp"
#include "agent_rt/runtime/run_outputs.hpp"
#include "agent_rt/runtime/run_plan.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "agent_rt/runtime/state_publisher.hpp"
#include "agent_rt/runtime/thread_cpu.hpp"
#include "agent_rt/runtime/trajectory_recorder.hpp"
#include "common/trace/trace.hpp"
#include "iceoryx_posh/popo/user_trigger.hpp"
#include "iceoryx_posh/popo/wait_set.hpp"

namespace cvislam::agent {

using geometry::SE3d;
using Clock = std::chrono::steady_clock;

Result<AgentMode> parseAgentMode(const std::string& name) {
  if (name == "auto") return AgentMode::kAuto;
  if (name == "mono") return AgentMode::kMono;
  if (name == "stereo") return AgentMode::kStereo;
  return Error{ErrorCode::kInvalidArgument, "mode '" + name + "': use mono, stereo or auto"};
}
Result<RouDiMode> parseRouDiMode(const std::string& name) {
  if (name == "embedded") return RouDiMode::kEmbedded;
  if (name == "external") return RouDiMode::kExternal;
  return Error{ErrorCode::kInvalidArgument, "roudi '" + name + "': use embedded or external"};
}
Result<Pace> parsePace(const std::string& name) {
  if (name == "realtime") return Pace::kRealtime;
  if (name == "fast") return Pace::kFast;
  if (name == "sync") return Pace::kSync;
  return Error{ErrorCode::kInvalidArgument, "pace '" + name + "': use realtime, fast or sync"};
}
const char* toString(AgentMode mode) {
  switch (mode) {
    case AgentMode::kAuto:
      return "auto";
    case AgentMode::kMono:
      return "mono";
    case AgentMode::kStereo:
      return "stereo";
  }
  return "?";
}
const char* toString(Pace pace) {
  switch (pace) {
    case Pace::kRealtime:
      return "realtime";
    case Pace::kFast:
      return "fast";
    case Pace::kSync:
      return "sync";
  }
  return "?";
}

namespace {

trace::SessionOptions traceSessionOptions(const AgentOptions& options) {
  trace::SessionOptions o;
  o.process_name = "agent " + std::to_string(options.agent);
  o.agent = options.agent;
  o.mission = options.link.mission;
  o.events_per_thread = options.trace_events_per_thread;
  return o;
}

}  // namespace

Status AgentOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, what}; };
  const int sources =
      (dataset.empty() ? 0 : 1) + (mcap.empty() ? 0 : 1) + (live.empty() ? 0 : 1) + (embedded_input ? 1 : 0);
  if (sources == 0) {
    return bad(
        "no sensor input given (--dataset SEQ_DIR, the folder that holds mav0; --mcap BAG.mcap; or --live NAME, a "
        "driver's topics)");
  }
  if (sources > 1) return bad("give one of --dataset, --mcap and --live");
  if (embedded_input && calibration.empty()) return bad("the embedded agent needs Kalibr's camera chain (calibration)");
  if (embedded_input && use_imu && imu_calibration.empty()) {
    return bad("the embedded agent needs Kalibr's IMU file (imu_calibration), or runs without the IMU");
  }
  if (!live.empty()) {
    if (roudi != RouDiMode::kExternal) {
      return bad(
          "--live needs --roudi external: the driver and the agent meet at one iox-roudi (iox-roudi -c "
          "deploy/roudi_config.toml)");
    }
    if (pace != Pace::kRealtime) return bad("--live runs at the driver's pace: --pace applies to recordings only");
    if (calibration.empty()) return bad("--live needs the rig's calibration: --calibration camchain-imucam.yaml");
    if (use_imu && imu_calibration.empty()) {
      return bad("--live needs the IMU's calibration: --imu-calibration imu.yaml (or run without the IMU)");
    }
    if (!(live_imu_wait_s >= 0.0 && live_imu_wait_s <= 1.0)) return bad("live_imu_wait_s must be in [0, 1] s");
    if (live_record_frames < 1 || live_record_frames > 10'000'000) {
      return bad("live_record_frames must be in [1, 10000000]");
    }
  }
  if (output.empty()) return bad("no output folder given (--output OUT_DIR)");
  if (imu_noise_inflation < 0.0 || !std::isfinite(imu_noise_inflation)) {
    return bad("imu_noise_inflation must be >= 0 (0 = automatic)");
  }
  if (!(rate > 0.0)) return bad("rate must be > 0");
  if (!(progress_interval_s > 0.0)) return bad("progress_interval_s must be > 0");
  if (frame_ring_size < 2 || frame_ring_size > 64) return bad("frame_ring_size must be in [2, 64]");
  if (Status s = tracking.validate(); !s.ok()) return s;
  if (Status s = link.validate(); !s.ok()) return s;
  if (Status s = threads.validate(); !s.ok()) return s;
  if (!trace_file.empty()) {
    if (Status s = traceSessionOptions(*this).validate(); !s.ok()) return s;
  }
  return mapping.validate();
}

namespace {

// One iceoryx memory pool per message type, sized from its channel's queue (ChannelDepths). Sizes must grow by at
// least a few KiB from pool to pool: near-equal ones share one pool.
std::vector<MemPoolSpec> mempoolsFor(const ChannelDepths& depths, bool with_link) {
  std::vector<MemPoolSpec> pools = {{128, 64},
                                    {static_cast<std::uint32_t>(sizeof(live::AgentStateMessage)), 32},
                                    {static_cast<std::uint32_t>(sizeof(KeyframeMessage)), depths.keyframeChunks()},
                                    {static_cast<std::uint32_t>(sizeof(MapSnapshotMessage)), depths.snapshotChunks()}};
  if (with_link) {
    pools.push_back({static_cast<std::uint32_t>(sizeof(MapDeltaMessage)), depths.deltaChunks()});
    pools.push_back({static_cast<std::uint32_t>(sizeof(AnchorMessage)), depths.anchorChunks()});
  }
  std::sort(pools.begin(), pools.end(),
            [](const MemPoolSpec& a, const MemPoolSpec& b) { return a.chunk_payload_bytes < b.chunk_payload_bytes; });
  std::vector<MemPoolSpec> merged;
  for (const MemPoolSpec& p : pools) {
    if (!merged.empty() && p.chunk_payload_bytes < merged.back().chunk_payload_bytes + 4096) {
      merged.back().chunk_payload_bytes = p.chunk_payload_bytes + 4096;
      merged.back().chunk_count += p.chunk_count;
    } else {
      merged.push_back(p);
    }
  }
  return merged;
}

// RouDi in this process (returned), or an attachment to an external iox-roudi (nullptr).
Result<std::unique_ptr<EmbeddedRouDi>> startIceoryx(const AgentOptions& options, const ChannelDepths& depths) {
  const std::string runtime_name =
      options.runtime_name.empty() ? "cvislam_agent_" + std::to_string(options.agent) : options.runtime_name;
  if (options.roudi == RouDiMode::kExternal) {
    if (Status s = attachToExternalRouDi(runtime_name); !s.ok()) return s.error();
    return std::unique_ptr<EmbeddedRouDi>();
  }
  EmbeddedRouDiOptions roudi_options;
  roudi_options.runtime_name = runtime_name;
  roudi_options.mempools = mempoolsFor(depths, !options.link.server.empty());
  return EmbeddedRouDi::start(roudi_options);
}

// The per-stage latencies of the run, each with room for one sample per frame.
struct StageLatencies {
  explicit StageLatencies(std::size_t frames)
      : orb("orb_extraction", frames),
        matching("matching", frames),
        pose("pose_optimisation", frames),
        motion("motion_ba", frames),
        keyframe("keyframe_write", frames),
        tracking("tracking_total", frames),
        frame_to_state("frame_to_state", frames),
        imu_to_state("imu_to_propagated_state", frames * 10),
        receive("keyframe_publish_to_receive", frames),
        local_ba("local_ba", frames),
        mapping("mapping_total", frames) {}

  void addFrame(const FrameResult& r) {
    orb.add(r.times.orb_ns);
    if (r.times.matching_ns > 0) matching.add(r.times.matching_ns);
    if (r.times.pose_ns > 0) pose.add(r.times.pose_ns);
    if (r.times.motion_ba_ns > 0) motion.add(r.times.motion_ba_ns);
    if (r.keyframe) keyframe.add(r.times.keyframe_ns);
    tracking.add(r.times.total_ns);
  }
  // imu_to_state only when the IMU was carried (a live run).
  [[nodiscard]] std::vector<StageSummary> summarise(bool with_imu_to_state) const {
    std::vector<StageSummary> out;
    for (const LatencyRecorder* r :
         {&orb, &matching, &pose, &motion, &keyframe, &tracking, &frame_to_state, &receive, &local_ba, &mapping})
      out.push_back(cvislam::agent::summarise(*r));
    if (with_imu_to_state) out.push_back(cvislam::agent::summarise(imu_to_state));
    return out;
  }

  // tracking's thread; frame_to_state runs from the frame's capture (FeedFrame::captured_steady_ns) to the
  // publication of its state
  LatencyRecorder orb, matching, pose, motion, keyframe, tracking, frame_to_state;
  LatencyRecorder imu_to_state;  // the propagation thread's: from an IMU sample's capture to its state's publication
  LatencyRecorder receive, local_ba, mapping;  // mapping's thread
};

// Set once by one thread, waited for with a deadline by another.
class Completion {
 public:
  void set() {
    {
      std::lock_guard lock(mutex_);
      done_ = true;
    }
    changed_.notify_all();
  }
  bool waitUntil(std::chrono::steady_clock::time_point deadline) {
    std::unique_lock lock(mutex_);
    return changed_.wait_until(lock, deadline, [&] { return done_; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  bool done_ = false;
};

// The tracking thread's loop over the frames: tracks each one, adopts mapping's snapshots, counts what happened,
// paces the run and reports progress. Its iceoryx ports and its wait on mapping's snapshots are made once, here.
class TrackingLoop {
 public:
  struct Shared {
    const AgentOptions& options;
    const RunPlan& plan;
    FrameFeed& feed;
    StageLatencies& latencies;
    TrajectoryRecorder& recorder;
    YieldRequests& yield_requests;
    StateListener* listener;  // besides the state topic; may be null
    const std::atomic<bool>& stop;
    const Link* link;  // progress text and health only; nullptr without a server
    ThreadCpuClock& cpu;
  };

  TrackingLoop(const Shared& shared, const ChannelDepths& depths)
      : s_(shared),
        tracker_(*shared.plan.tracker),
        keyframe_pub_(service(shared.options.agent, "keyframes"), iox::popo::PublisherOptions{}),
        snapshot_sub_(service(shared.options.agent, "map_snapshot"), snapshotOptions(depths)),
        state_pub_(shared.options.agent, live::kStateFramesEvent),
        health_pub_(shared.options.agent, live::kStateHealthEvent),
        sink_(keyframe_pub_) {
    snapshot_wait_.attachState(snapshot_sub_, iox::popo::SubscriberState::HAS_DATA).or_else([](auto) {
      std::fprintf(stderr, "[agent] cannot wait on mapping's snapshots: iceoryx refused the wait set\n");
    });
  }

  // Both sides must be connected before the first keyframe. RouDi connects publishers and subscribers
  // asynchronously and iceoryx gives no event for it, so this start-up step alone polls, bounded by 10 s.
  void awaitMapping(const std::atomic<bool>& mapping_ready) {
    const auto deadline = Clock::now() + std::chrono::seconds(10);
    while ((!mapping_ready.load() || !keyframe_pub_.hasSubscribers()) && Clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    if (!keyframe_pub_.hasSubscribers())
      std::fprintf(stderr, "[agent] warning: mapping did not subscribe within 10 s\n");
  }

  void run(AgentRunSummary& summary) {
    wall_start_ = Clock::now();
    last_progress_ = wall_start_;
    while (true) {
      if (s_.stop.load()) {
        summary.interrupted = true;
        break;
      }
      s_.feed.setTimeCorrection(tracker_.timeCorrectionForNextFrameNs());
      const FeedFrame* frame = s_.feed.next();
      if (frame == nullptr) {
        summary.interrupted = s_.stop.load();
        break;
      }
      if (first_t_ns_ < 0) first_t_ns_ = frame->t_ns;
      drainSnapshots();
      ++summary.frames;
      if (!frame->ok) {
        ++summary.unreadable_frames;
        if (!s_.options.quiet) {
          std::fprintf(stderr, "[tracking] frame %llu skipped: %s\n", static_cast<unsigned long long>(frame->index),
                       frame->error);
        }
        s_.feed.release();
        continue;
      }
      const FrameInput input = frameInput(*frame);
      const std::int64_t captured_ns = frame->captured_steady_ns;
      if (frame->stream_restarted) {
        tracker_.restartStream(frame->t_ns);
        if (!s_.options.quiet) {
          std::fprintf(stderr,
                       "[tracking] the stream started again: looking for the camera around its last pose, else "
                       "a new map\n");
        }
      }
      trace::Span frame_span("track_frame", {{"frame", static_cast<std::int64_t>(frame->index)}});
      if (frame_span.active()) frame_span.set("since_capture_us", (trace::nowNs() - captured_ns) / 1000);
      const FrameResult r = tracker_.track(input, sink_);
      if (r.keyframe) frame_span.set("keyframe", r.reference.counter);
      s_.feed.release();
      publishState(frameState(r, input.t_ns, captured_ns, s_.options.agent));
      s_.latencies.addFrame(r);
      if (!s_.recorder.addFrame(input.t_ns, input.time_correction_ns, r)) ++summary.frames_not_recorded;
      count(input.t_ns, r, summary);
      waitForMappingIfPaced(r);
      reportProgress(input.t_ns, r, summary);
      publishHealth(r, summary);
    }
    summary.wall_s = std::chrono::duration<double>(Clock::now() - wall_start_).count();
    summary.mean_tracked_points =
        summary.tracked_frames > 0 ? static_cast<double>(tracked_points_sum_) / summary.tracked_frames : 0.0;
  }

  // Takes every snapshot mapping has published; the newest is kept (its chunk held) for tracking.
  void drainSnapshots() {
    while (true) {
      auto taken = snapshot_sub_.take();
      if (taken.has_error()) break;
      if (held_) tsanRelease(held_->get());
      held_.emplace(std::move(taken.value()));
      tsanAcquire(held_->get());
      tracker_.adoptSnapshot(held_->get());
      s_.recorder.addSnapshot(*held_->get());
    }
  }

 private:
  // On the state topic and to the listener; its latency from the frame's capture into the profile.
  void publishState(live::AgentStateMessage state) {
    state_pub_.publish(state);
    s_.latencies.frame_to_state.add(state.published_steady_ns - state.captured_steady_ns);
    if (s_.listener != nullptr) s_.listener->onState(state);
  }

  // Once a second, on the health topic: how the agent is doing, for a supervisor. Reads the link's figures and
  // each thread's /proc entry into fixed buffers: nothing is allocated.
  void publishHealth(const FrameResult& r, const AgentRunSummary& summary) {
    const std::int64_t now_ns = steadyNowNs();
    if (last_health_ns_ < 0) {
      last_health_ns_ = now_ns;
      frames_at_health_ = summary.frames;
      s_.cpu.sample(now_ns, health_.cpu_percent);
      return;
    }
    if (now_ns - last_health_ns_ < kHealthIntervalNs) return;
    live::AgentHealthMessage& h = health_;
    h.agent = s_.options.agent;
    h.status = statusOf(r.status);
    h.map_id = r.map_id;
    h.interval_s = static_cast<double>(now_ns - last_health_ns_) * 1e-9;
    h.frame_rate_hz = static_cast<double>(summary.frames - frames_at_health_) / h.interval_s;
    h.frames = summary.frames;
    h.tracked_frames = summary.tracked_frames;
    h.lost_frames = summary.lost_frames;
    h.keyframes = summary.keyframes;
    h.pending_keyframes = tracker_.pendingKeyframes();
    h.flags = tracker_.imuInitialised() ? live::kImuInitialised : 0U;
    if (s_.link != nullptr) {
      const LinkHealth link = s_.link->health();
      h.flags |= live::kLinkEnabled | (link.connected ? live::kLinkConnected : 0U);
      h.link_acked_batches = link.acked_sequence;
      h.link_keyframes_waiting = link.keyframes_waiting;
    }
    s_.cpu.sample(now_ns, h.cpu_percent);
    health_pub_.publish(h);
    last_health_ns_ = now_ns;
    frames_at_health_ = summary.frames;
  }

  static iox::popo::SubscriberOptions snapshotOptions(const ChannelDepths& depths) {
    iox::popo::SubscriberOptions options;
    options.queueCapacity = depths.snapshots;
    return options;
  }

  [[nodiscard]] FrameInput frameInput(const FeedFrame& frame) const {
    FrameInput input;
    input.t_ns = frame.t_ns;
    input.time_correction_ns = frame.time_correction_ns;
    input.width = s_.plan.rig.cam0.width;
    input.height = s_.plan.rig.cam0.height;
    input.left = frame.left;
    input.right = frame.right;
    input.imu = frame.imu;
    return input;
  }

  void count(std::int64_t t_ns, const FrameResult& r, AgentRunSummary& summary) {
    const bool quiet = s_.options.quiet;
    const double t_s = static_cast<double>(t_ns) * 1e-9;
    if (r.tracked) {
      ++summary.tracked_frames;
      tracked_points_sum_ += static_cast<std::size_t>(r.inliers);
    }
    if (r.keyframe) ++summary.keyframes;
    if (r.issue == FrameIssue::kImuGap) {
      ++summary.imu_gaps;
      if (!quiet) std::fprintf(stderr, "[tracking] t=%.3f s: IMU gap; this frame predicts without it\n", t_s);
    }
    if (r.issue == FrameIssue::kKeyframeDropped) ++summary.dropped_keyframes;
    if (r.keyframe_deferred) ++summary.deferred_keyframes;
    if (r.keyframe_overdue) s_.yield_requests.request();
    if (r.needs_mapping) ++summary.frames_needing_mapping;
    summary.most_pending_keyframes = std::max(summary.most_pending_keyframes, r.pending_keyframes);
    if (!r.tracked && r.status != TrackingStatus::kWaitingForMap) {
      ++summary.lost_frames;
      if (!quiet && r.status == TrackingStatus::kRelocalising) {
        std::fprintf(stderr, "[tracking] t=%.3f s: %s (%d keypoints, %d matches); relocalising\n", t_s,
                     toString(r.issue), r.keypoints, r.matches);
      }
    }
    if (r.status == TrackingStatus::kWaitingForMap && previous_status_ == TrackingStatus::kRelocalising && !quiet) {
      std::fprintf(stderr, "[tracking] t=%.3f s: relocalisation failed for %d frames: starting a new map\n", t_s,
                   s_.options.tracking.max_lost_frames);
    }
    previous_status_ = r.status;
  }

  // At fast pace there is no sensor clock to keep: tracking waits for mapping to answer a pending keyframe rather
  // than run ahead of the map. At sync pace it waits after every keyframe, so runs repeat. Woken by the snapshot
  // itself; the bounded slices only let a stop request in.
  void waitForMappingIfPaced(const FrameResult& r) {
    const Pace pace = s_.options.pace;
    const bool fast_wait = pace == Pace::kFast && r.needs_mapping && r.pending_keyframes > 0;
    const bool sync_wait = pace == Pace::kSync && r.keyframe;
    if (!fast_wait && !sync_wait) return;
    const auto still_waiting = [&] {
      return fast_wait ? tracker_.pendingKeyframes() >= r.pending_keyframes : tracker_.awaitingKeyframe(nullptr);
    };
    const auto deadline = Clock::now() + (fast_wait ? std::chrono::seconds(10) : std::chrono::seconds(30));
    while (still_waiting() && !s_.stop.load()) {
      const auto now = Clock::now();
      if (now >= deadline) break;
      const auto slice = std::min<Clock::duration>(deadline - now, std::chrono::milliseconds(100));
      snapshot_wait_.timedWait(
          iox::units::Duration::fromNanoseconds(std::chrono::duration_cast<std::chrono::nanoseconds>(slice).count()));
      drainSnapshots();
    }
  }

  void reportProgress(std::int64_t t_ns, const FrameResult& r, const AgentRunSummary& summary) {
    const auto now = Clock::now();
    const double since_s = std::chrono::duration<double>(now - last_progress_).count();
    if (s_.options.quiet || since_s < s_.options.progress_interval_s) return;
    const double fps = static_cast<double>(summary.frames - frames_at_progress_) / since_s;
    const MapSnapshotMessage* map = held_ ? held_->get() : nullptr;
    char frames[48];
    if (s_.feed.knownFrames() > 0) {
      std::snprintf(frames, sizeof(frames), "%zu/%zu", summary.frames, s_.feed.knownFrames());
    } else {
      std::snprintf(frames, sizeof(frames), "%zu", summary.frames);
    }
    std::fprintf(stderr, "[agent] frame %s  t=%.1f s  %.1f fps  %-15s  inliers %3d  map %2u KF %5u pts  IMU %s%s%s%s\n",
                 frames, static_cast<double>(t_ns - first_t_ns_) * 1e-9, fps, toString(r.status), r.inliers,
                 map ? map->keyframe_count : 0U, map ? map->point_count : 0U,
                 tracker_.imuInitialised() ? "initialised" : "not yet", liveFaultText(), s_.link ? "  " : "",
                 s_.link ? s_.link->progressText().c_str() : "");
    last_progress_ = now;
    frames_at_progress_ = summary.frames;
  }

  // What went wrong with a live stream so far, for the progress line ("" when nothing did). Only printed every
  // progress interval, so its string does not weigh on the per-frame path.
  const char* liveFaultText() {
    const FeedFaults f = s_.feed.faults();
    fault_text_[0] = '\0';
    if (!f.any()) return fault_text_;
    std::snprintf(
        fault_text_, sizeof(fault_text_), "  live: lost %llu, late %llu, bad %llu, IMU lost %llu late %llu waits %llu",
        static_cast<unsigned long long>(f.frames_lost), static_cast<unsigned long long>(f.frames_out_of_order),
        static_cast<unsigned long long>(f.messages_malformed), static_cast<unsigned long long>(f.imu_lost),
        static_cast<unsigned long long>(f.imu_out_of_order), static_cast<unsigned long long>(f.imu_wait_timeouts));
    return fault_text_;
  }

  Shared s_;
  Tracker& tracker_;
  iox::popo::Publisher<KeyframeMessage> keyframe_pub_;
  iox::popo::Subscriber<MapSnapshotMessage> snapshot_sub_;
  iox::popo::WaitSet<1> snapshot_wait_;
  StatePublisher<> state_pub_;
  StatePublisher<live::AgentHealthMessage> health_pub_;
  static constexpr std::int64_t kHealthIntervalNs = 1'000'000'000;
  live::AgentHealthMessage health_;
  std::int64_t last_health_ns_ = -1;
  std::size_t frames_at_health_ = 0;
  IceoryxKeyframeSink sink_;
  std::optional<iox::popo::Sample<const MapSnapshotMessage>> held_;
  Clock::time_point wall_start_;
  Clock::time_point last_progress_;
  std::size_t frames_at_progress_ = 0;
  char fault_text_[160] = {};

 public:
  // The sensor time of the first frame; -1 before one came.
  [[nodiscard]] std::int64_t firstFrameTns() const { return first_t_ns_; }
  // Frame states that found no free chunk (the listener still got them).
  [[nodiscard]] std::uint64_t statesNotSent() const { return state_pub_.notSent(); }

 private:
  std::int64_t first_t_ns_ = -1;
  std::size_t tracked_points_sum_ = 0;
  TrackingStatus previous_status_ = TrackingStatus::kWaitingForMap;
};

// The link to the server on its own thread, fed by mapping's deltas over iceoryx; it passes the server's anchors
// back to mapping.
class LinkThread {
 public:
  LinkThread(std::unique_ptr<Link> link, const AgentOptions& options, const ChannelDepths& depths,
             const std::function<void()>& schedule)
      : link_(std::move(link)), options_(options) {
    thread_ = std::thread([this, depths, schedule] {
      schedule();
      iox::popo::SubscriberOptions delta_options;
      delta_options.queueCapacity = depths.deltas;
      iox::popo::Subscriber<MapDeltaMessage> subscriber(service(options_.agent, "map_delta"), delta_options);
      IceoryxDeltaSource source(subscriber);
      iox::popo::Publisher<AnchorMessage> anchor_publisher(service(options_.agent, "anchors"),
                                                           iox::popo::PublisherOptions{});
      IceoryxAnchorSink anchor_sink(anchor_publisher);
      iox::popo::Subscriber<live::AgentStateMessage> state_subscriber(
          live::stateService(options_.agent, live::kStateFramesEvent), live::dropOldestQueue(1));
      IceoryxPoseSource poses(state_subscriber);
      link_->run(source, stop_, &anchor_sink, &poses);
      done_.set();
    });
  }
  ~LinkThread() {
    stop_.store(true);
    if (thread_.joinable()) thread_.join();
  }
  LinkThread(const LinkThread&) = delete;
  LinkThread& operator=(const LinkThread&) = delete;

  [[nodiscard]] const Link& link() const { return *link_; }

  // Mapping has published its last delta: the link sends what is left and waits for the acknowledgements. It
  // ends within its flush timeout, unless a write is stuck on a server that stopped reading (it still answers
  // keepalive pings): then its stream is cancelled.
  LinkStatus finish() {
    if (!options_.quiet) std::fprintf(stderr, "[link] end of run: %s; flushing\n", link_->progressText().c_str());
    stop_.store(true);
    const auto give_up = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                            std::chrono::duration<double>(options_.link.flush_timeout_s + 5.0));
    if (!done_.waitUntil(give_up)) {
      std::fprintf(stderr, "[link] the server stopped reading: cancelling the stream\n");
      link_->abort();
    }
    thread_.join();
    LinkStatus status = link_->status();
    if (!options_.quiet) {
      const std::size_t waiting = status.backlog.keyframes_unsent + status.backlog.keyframes_unacked;
      std::fprintf(stderr, "[link] %s: %llu batches acknowledged, %zu keyframes not acknowledged\n",
                   status.flushed ? "flushed" : "NOT flushed (server unreachable or too slow)",
                   static_cast<unsigned long long>(status.acked_sequence), waiting);
    }
    return status;
  }

  [[nodiscard]] Status writeReport(const std::filesystem::path& folder) const { return link_->writeReport(folder); }

 private:
  std::unique_ptr<Link> link_;
  const AgentOptions& options_;
  std::atomic<bool> stop_{false};
  Completion done_;
  std::thread thread_;
};

// The link to the server on its thread; none without a server.
Result<std::unique_ptr<LinkThread>> startLink(const AgentOptions& options, const RunPlan& plan,
                                              const ChannelDepths& depths, const std::function<void()>& schedule) {
  if (options.link.server.empty()) return std::unique_ptr<LinkThread>();
  LinkOptions link_options = options.link;
  link_options.local_map_keyframes = static_cast<std::uint32_t>(options.mapping.max_keyframes);
  auto created =
      Link::create(link_options, options.agent, linkSensors(plan.rig, plan.setup, plan.stereo, options.use_imu));
  if (!created) return created.error();
  if (!options.quiet) {
    std::fprintf(stderr, "[link] server %s, mission '%s', agent %u\n", options.link.server.c_str(),
                 options.link.mission.c_str(), static_cast<unsigned>(options.agent));
  }
  return std::make_unique<LinkThread>(std::move(created.value()), options, depths, schedule);
}

// A live run's IMU-rate state, from the driver's IMU and tracking's states; none otherwise.
std::unique_ptr<PropagationThread> startPropagation(const AgentOptions& options, StateListener* listener,
                                                    LatencyRecorder& imu_to_state,
                                                    const std::function<void()>& schedule) {
  if (options.live.empty() || !options.use_imu) return nullptr;
  PropagationOptions propagation;
  propagation.stream = options.live;
  propagation.agent = options.agent;
  propagation.listener = listener;
  return std::make_unique<PropagationThread>(propagation, imu_to_state, schedule);
}

// What mapping counted, into the run's summary.
void addMappingFigures(const MappingStats& stats, const YieldRequests& yield_requests, std::int64_t first_frame_t_ns,
                       AgentRunSummary& summary) {
  summary.new_maps = stats.new_maps;
  summary.local_ba_skipped = stats.ba_skipped;
  summary.local_ba_stopped_early = stats.ba_stopped_early;
  summary.local_ba_yielded_to_tracking = stats.ba_yielded_to_tracking;
  summary.mapping_yield_requests = yield_requests.requests();
  summary.lost_keyframe_messages = stats.lost_messages;
  if (!stats.time_corrections.empty()) {
    summary.time_offset_ms += static_cast<double>(stats.time_corrections.back().second) * 1e-6;
  }
  summary.imu_initialised_at_s = stats.imu_initialised_at_s < 0 || first_frame_t_ns < 0
                                     ? -1.0
                                     : stats.imu_initialised_at_s - static_cast<double>(first_frame_t_ns) * 1e-9;
}

}  // namespace

Result<AgentRunSummary> runAgent(const AgentOptions& options_in, const std::atomic<bool>& stop,
                                 const AgentHooks& hooks) {
  AgentOptions options = options_in;
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto planned = planRun(options);
  if (!planned) return planned.error();
  RunPlan& plan = *planned;

  std::error_code ec;
  std::filesystem::create_directories(options.output, ec);
  if (ec) {
    return Error{ErrorCode::kIoError,
                 "cannot create the output folder " + options.output.string() + ": " + ec.message()};
  }
  const ChannelDepths depths = ChannelDepths::forLag(options.tracking.lag);
  auto roudi = startIceoryx(options, depths);
  if (!roudi) return roudi.error();
  // Before the first thread starts: each binds to it as it starts (schedule_this_thread).
  std::optional<trace::Session> trace_session;
  if (!options.trace_file.empty()) trace_session.emplace(traceSessionOptions(options));

  // Room for every frame of a recording; a live run keeps the first live_record_frames.
  const std::size_t n_frames = plan.recording ? plan.frames.size() : options.live_record_frames;
  StageLatencies latencies(n_frames);
  MappingStats mapping_stats;
  AgentRunSummary summary;
  TrajectoryRecorder recorder(n_frames, options.use_imu);
  std::atomic<bool> tracking_done{false};
  std::atomic<bool> mapping_ready{false};
  YieldRequests yield_requests;  // tracking -> mapping: cut the local BA short (FrameResult::keyframe_overdue)

  // Each thread takes its own scheduling when it starts (tracking last, once the others are started: threads
  // inherit a real-time policy from the thread that starts them). What the process may not do is said once.
  const bool scheduling = options.threads.enabled && options.pace == Pace::kRealtime;
  const ThreadScheduleOptions threads =
      scheduling
          ? options.threads.resolved(mayTakeRealtimePriority(options.threads.tracking.realtime_priority), currentNice())
          : options.threads;
  ThreadCpuClock thread_cpu;  // for the health topic
  const auto schedule_this_thread = [&](const char* name, const ThreadSchedule& schedule) {
    trace::bindThread(name);  // every thread of the agent starts here
    thread_cpu.registerCurrentThread(name);
    if (!scheduling) return;
    const ScheduleOutcome outcome = applyToThisThread(schedule);
    if (!outcome.applied) std::fprintf(stderr, "[agent] threads.%s: %s\n", name, outcome.note.c_str());
  };

  std::unique_ptr<FrameFeed> owned_feed;
  FrameFeed* feed = hooks.feed;
  if (!options.embedded_input) {
    auto opened = openFeed(options, plan, stop, [&] { schedule_this_thread("loader", threads.loader); });
    if (!opened) return opened.error();
    owned_feed = std::move(opened).value();
    feed = owned_feed.get();
  } else if (feed == nullptr) {
    return Error{ErrorCode::kInvalidArgument, "embedded input without a feed"};
  }
  if (!options.live.empty() && !options.quiet) {
    std::fprintf(stderr, "[agent] live stream '%s': %s %dx%d%s\n", options.live.c_str(),
                 plan.stereo ? "stereo" : "mono", plan.rig.cam0.width, plan.rig.cam0.height,
                 options.use_imu ? " with IMU" : "");
  }

  auto link = startLink(options, plan, depths, [&] { schedule_this_thread("link", threads.link); });
  if (!link) return link.error();

  // Woken when tracking is done, so mapping waits on events alone.
  iox::popo::UserTrigger tracking_done_trigger;
  std::thread mapping([&] {
    schedule_this_thread("mapping", threads.mapping);
    mappingThread(*plan.mapper, options, tracking_done_trigger,
                  {tracking_done, stop, mapping_ready, latencies.receive, latencies.local_ba, latencies.mapping,
                   mapping_stats, yield_requests});
  });

  std::unique_ptr<PropagationThread> propagation =
      startPropagation(options, hooks.listener, latencies.imu_to_state,
                       [&] { schedule_this_thread("propagation", threads.propagation); });
  const bool propagation_started = propagation != nullptr;

  // The calling thread is tracking for the run only: its own scheduling comes back when runAgent returns.
  const ThreadScheduleRestorer restore_caller;
  schedule_this_thread("tracking", threads.tracking);
  std::int64_t first_frame_t_ns = -1;
  {
    TrackingLoop tracking({options, plan, *feed, latencies, recorder, yield_requests, hooks.listener, stop,
                           *link ? &(*link)->link() : nullptr, thread_cpu},
                          depths);
    tracking.awaitMapping(mapping_ready);
    if (hooks.on_running) hooks.on_running();
    tracking.run(summary);
    feed->close();
    summary.live = !options.live.empty() || options.embedded_input;
    summary.live_faults = feed->faults();
    tracking_done.store(true);
    tracking_done_trigger.trigger();
    mapping.join();
    summary.state_messages_not_sent = tracking.statesNotSent();
    if (propagation) {
      propagation->stop();
      summary.state_messages_not_sent += propagation->notSent();
      propagation.reset();
    }
    owned_feed.reset();         // the loader's end, or the live topics' subscriptions
    tracking.drainSnapshots();  // the last refinements
    first_frame_t_ns = tracking.firstFrameTns();
  }
  if (*link) {
    summary.link_enabled = true;
    summary.link = (*link)->finish();
  }
  summary.time_offset_estimated = options.mapping.ba.estimate_time_offset && options.use_imu;
  summary.time_offset_calibrated_ms = static_cast<double>(plan.rig.timeshift_cam_imu_ns) * 1e-6;
  summary.time_offset_ms = summary.time_offset_calibrated_ms;
  addMappingFigures(mapping_stats, yield_requests, first_frame_t_ns, summary);
  if (recorder.firstInitialisedFrameTns() >= 0 && first_frame_t_ns >= 0) {
    summary.tracking_initialised_at_s =
        static_cast<double>(recorder.firstInitialisedFrameTns() - first_frame_t_ns) * 1e-9;
  }
  summary.stages = latencies.summarise(propagation_started);

  // Outputs, on every path that got here (end of data, SIGINT/SIGTERM).
  if (*link) {
    if (Status s = (*link)->writeReport(options.output); !s.ok()) return s.error();
  }
  if (Status s = writeRunOutputs(options, recorder, mapping_stats, {plan.stereo, plan.imu_noise_inflation}, summary);
      !s.ok()) {
    return s.error();
  }
  if (trace_session) {  // every thread has ended
    if (Status s = trace_session->writeChromeJson(options.trace_file); !s.ok()) return s.error();
    const trace::SessionTotals totals = trace_session->totals();
    if (totals.overwritten > 0) {
      std::fprintf(stderr, "[agent] trace: the oldest %llu of %llu events gave way (trace_events_per_thread %zu)\n",
                   static_cast<unsigned long long>(totals.overwritten), static_cast<unsigned long long>(totals.events),
                   options.trace_events_per_thread);
    }
  }
  return summary;
}

}  // namespace cvislam::agent
