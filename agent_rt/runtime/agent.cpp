#include "agent_rt/runtime/agent.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <optional>
#include <thread>

#include <nlohmann/json.hpp>

#include "agent_rt/ipc/embedded_roudi.hpp"
#include "agent_rt/runtime/iceoryx_channels.hpp"
#include "agent_rt/runtime/mapping_thread.hpp"
#include "agent_rt/runtime/message_conversions.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "agent_rt/runtime/trajectory_recorder.hpp"
#include "common/dataset/euroc.hpp"
#include "common/dataset/png_gray.hpp"
#include "common/dataset/trajectory_io.hpp"

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

Status AgentOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, what}; };
  if (dataset.empty()) return bad("no dataset given (--dataset SEQ_DIR, the folder that holds mav0)");
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
  return mapping.validate();
}

namespace {

// Frames read ahead by the loader thread into buffers allocated at start-up; one producer, one consumer.
class FrameRing {
 public:
  struct Slot {
    std::vector<std::uint8_t> left;
    std::vector<std::uint8_t> right;
    std::int64_t t_ns = 0;
    std::size_t frame = 0;
    bool ok = true;
    std::string error;
  };

  FrameRing(int size, std::size_t pixels, bool stereo) : slots_(static_cast<std::size_t>(size)) {
    for (Slot& s : slots_) {
      s.left.resize(pixels);
      if (stereo) s.right.resize(pixels);
      s.error.reserve(256);
    }
  }

  Slot* producerSlot() {
    const std::size_t head = head_.load(std::memory_order_relaxed);
    if (head - tail_.load(std::memory_order_acquire) >= slots_.size()) return nullptr;
    return &slots_[head % slots_.size()];
  }
  void produced() { head_.fetch_add(1, std::memory_order_release); }
  Slot* consumerSlot() {
    const std::size_t tail = tail_.load(std::memory_order_relaxed);
    if (tail == head_.load(std::memory_order_acquire)) return nullptr;
    return &slots_[tail % slots_.size()];
  }
  void consumed() { tail_.fetch_add(1, std::memory_order_release); }
  void finish() { done_.store(true, std::memory_order_release); }
  [[nodiscard]] bool finished() const { return done_.load(std::memory_order_acquire); }

 private:
  std::vector<Slot> slots_;
  std::atomic<std::size_t> head_{0};
  std::atomic<std::size_t> tail_{0};
  std::atomic<bool> done_{false};
};

}  // namespace

Result<AgentRunSummary> runAgent(const AgentOptions& options_in, const std::atomic<bool>& stop) {
  AgentOptions options = options_in;
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto sequence = dataset::EurocSequence::open(options.dataset);
  if (!sequence) return sequence.error().withContext("dataset " + options.dataset.string());
  const dataset::EurocSequence& seq = *sequence;
  if (!seq.diagnostics().empty() && !options.quiet) {
    std::fprintf(stderr, "[agent] the dataset has %zu finding(s); the agent goes on without the bad rows:\n",
                 seq.diagnostics().findings().size());
    seq.diagnostics().print(std::cerr, 10);
  }
  const bool has_cam1 = seq.cam1() != nullptr;
  if (options.mode == AgentMode::kStereo && !has_cam1) {
    return Error{ErrorCode::kInvalidArgument,
                 "stereo mode needs mav0/cam1, which " + options.dataset.string() + " does not have: use --mode mono"};
  }
  const bool stereo = options.mode == AgentMode::kStereo || (options.mode == AgentMode::kAuto && has_cam1);
  if (options.use_imu && !seq.imuCalibration()) {
    return Error{ErrorCode::kInvalidArgument, "the dataset has no imu0/sensor.yaml; run with use_imu: false"};
  }

  double inflation = options.imu_noise_inflation;
  if (inflation == 0.0) {
    // The simulator writes mission.yaml beside its agents' folders.
    const bool simulated = std::filesystem::exists(options.dataset / "mission.yaml") ||
                           std::filesystem::exists(options.dataset.parent_path() / "mission.yaml");
    inflation = simulated ? 1.0 : 10.0;
  }
  auto setup = makeSensorSetup(seq, stereo, inflation);
  if (!setup) return setup.error();
  options.tracking.agent = options.agent;
  options.tracking.use_imu = options.use_imu;
  options.mapping.agent = options.agent;
  options.mapping.use_imu = options.use_imu;
  applySensorSetup(*setup, options.tracking, options.mapping);
  const camera::CameraModel* right = setup->right ? &*setup->right : nullptr;
  auto tracker = Tracker::create(options.tracking, setup->left, right, setup->T_s_c);
  if (!tracker) return tracker.error();
  auto mapper = Mapper::create(options.mapping, setup->left, right, setup->T_s_c, setup->T_c0_c1);
  if (!mapper) return mapper.error();

  std::vector<dataset::RigFrame> frames = framesToRun(seq, stereo);
  if (options.max_frames > 0 && frames.size() > options.max_frames) frames.resize(options.max_frames);
  if (frames.empty()) return Error{ErrorCode::kDataError, "the dataset has no usable camera frames"};

  std::error_code ec;
  std::filesystem::create_directories(options.output, ec);
  if (ec) {
    return Error{ErrorCode::kIoError,
                 "cannot create the output folder " + options.output.string() + ": " + ec.message()};
  }

  // iceoryx: RouDi in this process, or an external iox-roudi.
  std::unique_ptr<EmbeddedRouDi> roudi;
  const ChannelDepths depths = ChannelDepths::forLag(options.tracking.lag);
  const std::string runtime_name =
      options.runtime_name.empty() ? "cvislam_agent_" + std::to_string(options.agent) : options.runtime_name;
  if (options.roudi == RouDiMode::kEmbedded) {
    EmbeddedRouDiOptions roudi_options;
    roudi_options.runtime_name = runtime_name;
    // A pool per message type, sized from its channel's queue (see ChannelDepths).
    std::vector<MemPoolSpec> pools = {
        {128, 64},
        {static_cast<std::uint32_t>(sizeof(KeyframeMessage)), depths.keyframeChunks()},
        {static_cast<std::uint32_t>(sizeof(MapSnapshotMessage)), depths.snapshotChunks()}};
    if (!options.link.server.empty()) {
      pools.push_back({static_cast<std::uint32_t>(sizeof(MapDeltaMessage)), depths.deltaChunks()});
      pools.push_back({static_cast<std::uint32_t>(sizeof(AnchorMessage)), depths.anchorChunks()});
    }
    std::sort(pools.begin(), pools.end(),
              [](const MemPoolSpec& a, const MemPoolSpec& b) { return a.chunk_payload_bytes < b.chunk_payload_bytes; });
    // Sizes must grow by at least a few KiB from pool to pool: near-equal ones share one pool.
    roudi_options.mempools.clear();
    for (const MemPoolSpec& p : pools) {
      if (!roudi_options.mempools.empty() &&
          p.chunk_payload_bytes < roudi_options.mempools.back().chunk_payload_bytes + 4096) {
        roudi_options.mempools.back().chunk_payload_bytes = p.chunk_payload_bytes + 4096;
        roudi_options.mempools.back().chunk_count += p.chunk_count;
      } else {
        roudi_options.mempools.push_back(p);
      }
    }
    auto started = EmbeddedRouDi::start(roudi_options);
    if (!started) return started.error();
    roudi = std::move(started.value());
  } else if (Status s = attachToExternalRouDi(runtime_name); !s.ok()) {
    return s.error();
  }

  const std::size_t n_frames = frames.size();
  LatencyRecorder orb_ms("orb_extraction", n_frames);
  LatencyRecorder matching_ms("matching", n_frames);
  LatencyRecorder pose_ms("pose_optimisation", n_frames);
  LatencyRecorder motion_ms("motion_ba", n_frames);
  LatencyRecorder keyframe_ms("keyframe_write", n_frames);
  LatencyRecorder tracking_ms("tracking_total", n_frames);
  LatencyRecorder receive_ms("keyframe_publish_to_receive", n_frames);
  LatencyRecorder ba_ms("local_ba", n_frames);
  LatencyRecorder mapping_ms("mapping_total", n_frames);
  MappingStats mapping_stats;

  AgentRunSummary summary;
  TrajectoryRecorder recorder(n_frames);
  const int width = seq.cam0().calibration.width;
  const int height = seq.cam0().calibration.height;
  const auto pixels = static_cast<std::size_t>(width) * static_cast<std::size_t>(height);
  FrameRing ring(options.frame_ring_size, pixels, stereo);
  std::atomic<bool> loader_stop{false};
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
  const auto schedule_this_thread = [&](const char* name, const ThreadSchedule& schedule) {
    if (!scheduling) return;
    const ScheduleOutcome outcome = applyToThisThread(schedule);
    if (!outcome.applied) std::fprintf(stderr, "[agent] threads.%s: %s\n", name, outcome.note.c_str());
  };

  std::thread loader([&] {
    schedule_this_thread("loader", threads.loader);
    dataset::GrayPngDecoder png;  // its buffers settle at the first frame's size
    for (std::size_t i = 0; i < frames.size(); ++i) {
      FrameRing::Slot* slot = nullptr;
      while ((slot = ring.producerSlot()) == nullptr) {
        if (loader_stop.load() || stop.load()) {
          ring.finish();
          return;
        }
        std::this_thread::sleep_for(std::chrono::microseconds(200));
      }
      slot->t_ns = frames[i].t_ns;
      slot->frame = i;
      slot->ok = true;
      slot->error.clear();
      Status st = seq.loadImageInto(0, frames[i].cam0, slot->left, png);
      if (st.ok() && stereo) st = seq.loadImageInto(1, *frames[i].cam1, slot->right, png);
      if (!st.ok()) {
        slot->ok = false;
        slot->error = st.error().toString();
      }
      ring.produced();
    }
    ring.finish();
  });

  // The link to the server, when there is one: its own thread, fed by mapping's deltas.
  std::unique_ptr<Link> link;
  std::atomic<bool> link_stop{false};
  std::atomic<bool> link_done{false};
  std::thread link_thread;
  if (!options.link.server.empty()) {
    LinkOptions link_options = options.link;
    link_options.local_map_keyframes = static_cast<std::uint32_t>(options.mapping.max_keyframes);
    auto created = Link::create(link_options, options.agent, linkSensors(seq, *setup, stereo, options.use_imu));
    if (!created) return created.error();
    link = std::move(created.value());
    if (!options.quiet) {
      std::fprintf(stderr, "[link] server %s, mission '%s', agent %u\n", options.link.server.c_str(),
                   options.link.mission.c_str(), static_cast<unsigned>(options.agent));
    }
    link_thread = std::thread([&] {
      schedule_this_thread("link", threads.link);
      iox::popo::SubscriberOptions delta_options;
      delta_options.queueCapacity = depths.deltas;
      iox::popo::Subscriber<MapDeltaMessage> subscriber(service(options.agent, "map_delta"), delta_options);
      IceoryxDeltaSource source(subscriber);
      iox::popo::PublisherOptions anchor_options;
      iox::popo::Publisher<AnchorMessage> anchor_publisher(service(options.agent, "anchors"), anchor_options);
      IceoryxAnchorSink anchor_sink(anchor_publisher);
      link->run(source, link_stop, &anchor_sink);
      link_done.store(true);
    });
  }

  std::thread mapping([&] {
    schedule_this_thread("mapping", threads.mapping);
    mappingThread(**mapper, options, tracking_done, stop, receive_ms, ba_ms, mapping_ms, mapping_stats, mapping_ready,
                  yield_requests);
  });

  // The calling thread is tracking for the run only: its own scheduling comes back when runAgent returns.
  const ThreadScheduleRestorer restore_caller;
  schedule_this_thread("tracking", threads.tracking);
  {
    iox::popo::PublisherOptions pub_options;
    iox::popo::Publisher<KeyframeMessage> keyframe_pub(service(options.agent, "keyframes"), pub_options);
    iox::popo::SubscriberOptions sub_options;
    sub_options.queueCapacity = depths.snapshots;
    iox::popo::Subscriber<MapSnapshotMessage> snapshot_sub(service(options.agent, "map_snapshot"), sub_options);
    IceoryxKeyframeSink sink(keyframe_pub);
    std::optional<iox::popo::Sample<const MapSnapshotMessage>> held;

    // Both sides must be connected before the first keyframe (RouDi connects them asynchronously).
    const auto connect_deadline = Clock::now() + std::chrono::seconds(10);
    while ((!mapping_ready.load() || !keyframe_pub.hasSubscribers()) && Clock::now() < connect_deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    if (!keyframe_pub.hasSubscribers())
      std::fprintf(stderr, "[agent] warning: mapping did not subscribe within 10 s\n");

    const auto drain_snapshots = [&] {
      while (true) {
        auto taken = snapshot_sub.take();
        if (taken.has_error()) break;
        if (held) tsanRelease(held->get());
        held.emplace(std::move(taken.value()));
        tsanAcquire(held->get());
        tracker.value()->adoptSnapshot(held->get());
        recorder.addSnapshot(*held->get());
      }
    };

    const std::vector<dataset::ImuSample>& imu = seq.imu();
    const auto wall_start = Clock::now();
    auto last_progress = wall_start;
    std::size_t frames_at_progress = 0;
    std::int64_t previous_t_ns = -1;
    std::size_t tracked_points_sum = 0;
    TrackingStatus previous_status = TrackingStatus::kWaitingForMap;
    while (true) {
      if (stop.load()) {
        summary.interrupted = true;
        break;
      }
      FrameRing::Slot* slot = ring.consumerSlot();
      if (slot == nullptr) {
        if (ring.finished() && ring.consumerSlot() == nullptr) break;
        std::this_thread::sleep_for(std::chrono::microseconds(100));
        continue;
      }
      if (options.pace == Pace::kRealtime) {
        const auto due = wall_start + std::chrono::nanoseconds(static_cast<std::int64_t>(
                                          static_cast<double>(slot->t_ns - frames.front().t_ns) / options.rate));
        std::this_thread::sleep_until(due);
      }
      drain_snapshots();
      ++summary.frames;
      if (!slot->ok) {
        ++summary.unreadable_frames;
        if (!options.quiet)
          std::fprintf(stderr, "[tracking] frame %zu skipped: %s\n", slot->frame, slot->error.c_str());
        ring.consumed();
        continue;
      }
      // The IMU covering [previous frame, this frame].
      std::span<const dataset::ImuSample> imu_span;
      if (options.use_imu) imu_span = imuCovering(imu, previous_t_ns < 0 ? slot->t_ns : previous_t_ns, slot->t_ns);
      FrameInput input;
      input.t_ns = slot->t_ns;
      input.width = width;
      input.height = height;
      input.left = slot->left;
      if (stereo) input.right = slot->right;
      input.imu = imu_span;
      const FrameResult r = tracker.value()->track(input, sink);
      previous_t_ns = slot->t_ns;
      ring.consumed();

      orb_ms.add(r.times.orb_ns);
      if (r.times.matching_ns > 0) matching_ms.add(r.times.matching_ns);
      if (r.times.pose_ns > 0) pose_ms.add(r.times.pose_ns);
      if (r.times.motion_ba_ns > 0) motion_ms.add(r.times.motion_ba_ns);
      if (r.keyframe) keyframe_ms.add(r.times.keyframe_ns);
      tracking_ms.add(r.times.total_ns);
      recorder.addFrame(input.t_ns, r);
      if (r.tracked) {
        ++summary.tracked_frames;
        tracked_points_sum += static_cast<std::size_t>(r.inliers);
      }
      if (r.keyframe) ++summary.keyframes;
      if (r.issue == FrameIssue::kImuGap) {
        ++summary.imu_gaps;
        if (!options.quiet)
          std::fprintf(stderr, "[tracking] t=%.3f s: IMU gap; this frame predicts without it\n", input.t_ns * 1e-9);
      }
      if (r.issue == FrameIssue::kKeyframeDropped) ++summary.dropped_keyframes;
      if (r.keyframe_deferred) ++summary.deferred_keyframes;
      if (r.keyframe_overdue) yield_requests.request();
      if (r.needs_mapping) ++summary.frames_needing_mapping;
      summary.most_pending_keyframes = std::max(summary.most_pending_keyframes, r.pending_keyframes);
      if (!r.tracked && r.status != TrackingStatus::kWaitingForMap) {
        ++summary.lost_frames;
        if (!options.quiet && r.status == TrackingStatus::kRelocalising) {
          std::fprintf(stderr, "[tracking] t=%.3f s: %s (%d keypoints, %d matches); relocalising\n", input.t_ns * 1e-9,
                       toString(r.issue), r.keypoints, r.matches);
        }
      }
      if (r.status == TrackingStatus::kWaitingForMap && previous_status == TrackingStatus::kRelocalising &&
          !options.quiet) {
        std::fprintf(stderr, "[tracking] t=%.3f s: relocalisation failed for %d frames: starting a new map\n",
                     static_cast<double>(input.t_ns) * 1e-9, options.tracking.max_lost_frames);
      }
      previous_status = r.status;

      if (options.pace == Pace::kFast && r.needs_mapping) {
        // No sensor clock to keep: wait for mapping to answer a pending keyframe rather than run ahead of the map.
        const auto deadline = Clock::now() + std::chrono::seconds(10);
        while (tracker.value()->pendingKeyframes() >= r.pending_keyframes && r.pending_keyframes > 0 &&
               Clock::now() < deadline && !stop.load()) {
          std::this_thread::sleep_for(std::chrono::microseconds(200));
          drain_snapshots();
        }
      }
      if (options.pace == Pace::kSync && r.keyframe) {
        const auto deadline = Clock::now() + std::chrono::seconds(30);
        while (tracker.value()->awaitingKeyframe(nullptr) && Clock::now() < deadline && !stop.load()) {
          std::this_thread::sleep_for(std::chrono::microseconds(200));
          drain_snapshots();
        }
      }

      const auto now = Clock::now();
      if (!options.quiet && std::chrono::duration<double>(now - last_progress).count() >= options.progress_interval_s) {
        const double fps = static_cast<double>(summary.frames - frames_at_progress) /
                           std::chrono::duration<double>(now - last_progress).count();
        const MapSnapshotMessage* map = held ? held->get() : nullptr;
        std::fprintf(stderr,
                     "[agent] frame %zu/%zu  t=%.1f s  %.1f fps  %-15s  inliers %3d  map %2u KF %5u pts  IMU %s%s%s\n",
                     summary.frames, n_frames, static_cast<double>(input.t_ns - frames.front().t_ns) * 1e-9, fps,
                     toString(r.status), r.inliers, map ? map->keyframe_count : 0U, map ? map->point_count : 0U,
                     tracker.value()->imuInitialised() ? "initialised" : "not yet", link ? "  " : "",
                     link ? link->progressText().c_str() : "");
        last_progress = now;
        frames_at_progress = summary.frames;
      }
    }
    summary.wall_s = std::chrono::duration<double>(Clock::now() - wall_start).count();
    summary.mean_tracked_points =
        summary.tracked_frames > 0 ? static_cast<double>(tracked_points_sum) / summary.tracked_frames : 0.0;
    loader_stop.store(true);
    tracking_done.store(true);
    mapping.join();
    loader.join();
    drain_snapshots();  // the last refinements
  }
  if (link) {
    // Mapping has published its last delta: the link sends what is left and waits for the acknowledgements.
    if (!options.quiet) std::fprintf(stderr, "[link] end of run: %s; flushing\n", link->progressText().c_str());
    link_stop.store(true);
    // The link ends within its flush timeout, unless a write is stuck on a server that stopped reading (it still
    // answers keepalive pings): then its stream is cancelled.
    const auto give_up = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                            std::chrono::duration<double>(options.link.flush_timeout_s + 5.0));
    while (!link_done.load() && Clock::now() < give_up) std::this_thread::sleep_for(std::chrono::milliseconds(20));
    if (!link_done.load()) {
      std::fprintf(stderr, "[link] the server stopped reading: cancelling the stream\n");
      link->abort();
    }
    link_thread.join();
    summary.link_enabled = true;
    summary.link = link->status();
    if (!options.quiet) {
      const std::size_t waiting = summary.link.backlog.keyframes_unsent + summary.link.backlog.keyframes_unacked;
      std::fprintf(stderr, "[link] %s: %llu batches acknowledged, %zu keyframes not acknowledged\n",
                   summary.link.flushed ? "flushed" : "NOT flushed (server unreachable or too slow)",
                   static_cast<unsigned long long>(summary.link.acked_sequence), waiting);
    }
  }

  summary.new_maps = mapping_stats.new_maps;
  summary.local_ba_skipped = mapping_stats.ba_skipped;
  summary.local_ba_stopped_early = mapping_stats.ba_stopped_early;
  summary.local_ba_yielded_to_tracking = mapping_stats.ba_yielded_to_tracking;
  summary.mapping_yield_requests = yield_requests.requests();
  summary.lost_keyframe_messages = mapping_stats.lost_messages;
  summary.imu_initialised_at_s =
      mapping_stats.imu_initialised_at_s < 0
          ? -1.0
          : mapping_stats.imu_initialised_at_s - static_cast<double>(frames.front().t_ns) * 1e-9;
  for (const LatencyRecorder* r :
       {&orb_ms, &matching_ms, &pose_ms, &motion_ms, &keyframe_ms, &tracking_ms, &receive_ms, &ba_ms, &mapping_ms}) {
    summary.stages.push_back(summarise(*r));
  }

  // Outputs, on every path that got here (end of data, SIGINT/SIGTERM).
  dataset::Trajectory refined;
  dataset::Trajectory online;
  dataset::Trajectory keyframes;
  recorder.build(refined, online, keyframes);
  summary.trajectory = options.output / "trajectory.txt";
  summary.keyframe_trajectory = options.output / "keyframes.txt";
  summary.latency_json = options.output / "latency.json";
  for (const auto& [path, trajectory] :
       {std::pair{summary.trajectory, &refined}, std::pair{options.output / "trajectory_online.txt", &online},
        std::pair{summary.keyframe_trajectory, &keyframes}}) {
    if (Status s = dataset::writeTrajectory(path, *trajectory, dataset::TrajectoryFormat::kTum); !s.ok()) {
      return s.error();
    }
  }
  if (link) {
    if (Status s = link->writeReport(options.output); !s.ok()) return s.error();
  }
  std::ofstream latency(summary.latency_json);
  latency << latencyJson(summary.stages);
  if (!latency) return Error{ErrorCode::kIoError, "cannot write " + summary.latency_json.string()};
  nlohmann::json j = {{"frames", summary.frames},
                      {"tracked_frames", summary.tracked_frames},
                      {"keyframes", summary.keyframes},
                      {"new_maps", summary.new_maps},
                      {"lost_frames", summary.lost_frames},
                      {"unreadable_frames", summary.unreadable_frames},
                      {"imu_gaps", summary.imu_gaps},
                      {"dropped_keyframes", summary.dropped_keyframes},
                      {"deferred_keyframes", summary.deferred_keyframes},
                      {"frames_needing_mapping", summary.frames_needing_mapping},
                      {"most_pending_keyframes", summary.most_pending_keyframes},
                      {"mapping_yield_requests", summary.mapping_yield_requests},
                      {"local_ba_skipped", summary.local_ba_skipped},
                      {"local_ba_stopped_early", summary.local_ba_stopped_early},
                      {"local_ba_yielded_to_tracking", summary.local_ba_yielded_to_tracking},
                      {"imu_initialised_at_s", summary.imu_initialised_at_s},
                      {"mean_tracked_points", summary.mean_tracked_points},
                      {"mode", stereo ? "stereo" : "mono"},
                      {"imu_noise_inflation", inflation},
                      {"interrupted", summary.interrupted},
                      {"wall_s", summary.wall_s}};
  if (summary.link_enabled) {
    j["link"] = {
        {"server", options.link.server},
        {"mission", options.link.mission},
        {"flushed", summary.link.flushed},
        {"connections", summary.link.connections},
        {"acked_sequence", summary.link.acked_sequence},
        {"keyframes_unacknowledged", summary.link.backlog.keyframes_unsent + summary.link.backlog.keyframes_unacked},
        {"keyframes_dropped", summary.link.store.keyframes_dropped},
        {"deltas_lost", summary.link.store.deltas_lost},
        {"up_bytes", summary.link.up_bytes},
        {"down_bytes", summary.link.down_bytes}};
    j["downlink"] = mapping_stats.downlinkJson();
  }
  std::ofstream(options.output / "summary.json") << j.dump(2) << "\n";
  return summary;
}

std::string formatSummary(const AgentRunSummary& s) {
  char text[1024];
  std::snprintf(
      text, sizeof(text),
      "frames %zu, tracked %zu (%.1f %%), keyframes %zu, maps %zu, mean tracked points %.0f\n"
      "IMU initialised at %s, unreadable frames %zu, IMU gaps %zu, frames lost %zu, keyframes dropped %zu\n"
      "mapping busy: keyframes deferred %zu, frames that needed mapping's answer %zu, most keyframes pending %d\n"
      "mapping asked to yield on %zu frames; local BAs skipped %zu, cut short %zu (for tracking's request %zu)\n",
      s.frames, s.tracked_frames, s.frames > 0 ? 100.0 * s.tracked_frames / s.frames : 0.0, s.keyframes, s.new_maps,
      s.mean_tracked_points,
      s.imu_initialised_at_s < 0 ? "never" : (std::to_string(s.imu_initialised_at_s) + " s").c_str(),
      s.unreadable_frames, s.imu_gaps, s.lost_frames, s.dropped_keyframes, s.deferred_keyframes,
      s.frames_needing_mapping, s.most_pending_keyframes, s.mapping_yield_requests, s.local_ba_skipped,
      s.local_ba_stopped_early, s.local_ba_yielded_to_tracking);
  return std::string(text) + formatLatencyTable(s.stages);
}

}  // namespace cvislam::agent
