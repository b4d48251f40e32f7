#include "agent_rt/runtime/mapping_thread.hpp"

#include <chrono>
#include <cstdio>
#include <functional>
#include <memory>
#include <optional>
#include <thread>

#include "agent_rt/runtime/iceoryx_channels.hpp"
#include "common/trace/trace.hpp"
#include "iceoryx_posh/popo/user_trigger.hpp"
#include "iceoryx_posh/popo/wait_set.hpp"

namespace cvislam::agent {

using Clock = std::chrono::steady_clock;

nlohmann::json MappingStats::downlinkJson() const {
  const MappingStats& m = *this;
  return nlohmann::json{{"messages_applied", m.downlink_messages},
                        {"stale", m.downlink_stale},
                        {"refused", m.downlink_refused},
                        {"covisible_maps_skipped", m.downlink_skipped},
                        {"last_skip", m.downlink_last_skip},
                        {"anchors_added", m.anchors_added},
                        {"anchors_released", m.anchors_released},
                        {"most_anchors_held", m.most_anchors_held},
                        {"anchor_points_added", m.anchor_points_added},
                        {"anchor_points_linked", m.anchor_points_linked},
                        {"anchor_updates", m.anchor_updates},
                        {"over_capacity", m.over_capacity},
                        {"unknown_references", m.unknown_references},
                        {"corrections_applied", m.corrections_applied},
                        {"corrections_deferred", m.corrections_deferred},
                        {"corrections_skipped", m.corrections_skipped},
                        {"largest_correction_m", m.largest_correction_m},
                        {"largest_correction_deg", m.largest_correction_deg},
                        {"local_ba_with_anchors", m.ba_with_anchors}};
}

namespace {

struct FileCloser {
  void operator()(std::FILE* f) const {
    if (f != nullptr) std::fclose(f);
  }
};

// anchors.txt: after every downlink message that carried a covisible map, the local map's newest own keyframe and
// every anchor held, each with its pose in the agent's world frame, so that the anchors' consistency with the
// agent's own estimate can be checked against ground truth after the run (tools/anchor_consistency.py).
class AnchorLog {
 public:
  explicit AnchorLog(const std::filesystem::path& file) : file_(std::fopen(file.c_str(), "w")) {
    if (file_) {
      std::fprintf(file_.get(),
                   "# kind(K: newest own keyframe, A: anchor) stream sequence keyframe_agent keyframe_counter t_ns "
                   "tx ty tz qx qy qz qw (T_w_s, the agent's world frame)\n");
    }
  }

  void write(const AnchorMessage& m, const LocalMap& map) {
    if (!file_ || m.has_covisible == 0) return;
    const KeyframeData* newest = nullptr;
    map.keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
      if (!kf.anchor && (newest == nullptr || kf.sequence > newest->sequence)) newest = &kf;
    });
    if (newest == nullptr) return;
    line('K', m, *newest);
    map.keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
      if (kf.anchor) line('A', m, kf);
    });
  }

 private:
  void line(char kind, const AnchorMessage& m, const KeyframeData& kf) {
    const Eigen::Vector3d& t = kf.T_w_s.translation();
    const Eigen::Quaterniond& q = kf.T_w_s.quaternion();
    std::fprintf(file_.get(), "%c %u %llu %u %u %lld %.6f %.6f %.6f %.9f %.9f %.9f %.9f\n", kind, m.stream,
                 static_cast<unsigned long long>(m.sequence), static_cast<unsigned>(kf.id.agent),
                 static_cast<unsigned>(kf.id.counter), static_cast<long long>(kf.t_ns), t.x(), t.y(), t.z(), q.x(),
                 q.y(), q.z(), q.w());
  }

  std::unique_ptr<std::FILE, FileCloser> file_;
};

void traceDownlink(const AnchorMessage& m, const DownlinkReport& r) {
  std::fprintf(stderr,
               "[mapping] downlink %u/%llu: anchors +%d -%d (held %d), points +%d (linked %d, over capacity %d), "
               "%d unknown references, corrections %d applied / %d skipped (largest %.3f m)%s%s\n",
               m.stream, static_cast<unsigned long long>(m.sequence), r.anchors_added, r.anchors_released,
               r.anchors_held, r.points_added, r.points_linked, r.points_over_capacity, r.unknown_references,
               r.corrections_applied, r.corrections_skipped, r.largest_correction_m, r.stale ? ", stale" : "",
               r.skipped.empty() ? "" : (", " + r.skipped).c_str());
}

void traceKeyframe(double t_s, const KeyframeMessage& msg, const MapperReport& report, bool yielded_to_tracking) {
  const LocalBundleAdjustmentSummary& ba = report.ba;
  std::fprintf(
      stderr,
      "[mapping] t=%.2f s keyframe %s: linked %d, fused %d, merged %d, stereo %d matched / %d new points, "
      "triangulated %d, culled %d; BA %d keyframes + %d fixed (%d anchors), %d points (%d left out), %d "
      "factors (%d cam1, %d mismatches left out, %d by anchors), cost %.1f -> %.1f in %d iterations, "
      "%.1f ms%s%s%s%s\n",
      t_s, msg.state.id.toString().c_str(), report.linked, report.fused, report.merged, report.stereo_matches,
      report.stereo_points, report.triangulated, report.culled, ba.window_keyframes, ba.fixed_keyframes,
      ba.anchor_keyframes, ba.map_points, ba.map_points_left_out, ba.reprojection_factors, ba.second_camera_factors,
      ba.second_camera_rejected, ba.anchor_factors, ba.initial_cost, ba.final_cost, ba.iterations,
      static_cast<double>(report.ba_ns) * 1e-6,
      report.ba_skipped && yielded_to_tracking  ? " (BA skipped: tracking asked)"
      : report.ba_skipped                       ? " (BA skipped: the next keyframe is waiting)"
      : ba.stopped_early && yielded_to_tracking ? " (BA cut short: tracking asked)"
      : ba.stopped_early                        ? " (BA cut short: the next keyframe is waiting)"
                                                : "",
      report.returned_to_place ? "; back over a place mapped long ago: the next BAs take the whole local map" : "",
      report.note.empty() ? "" : "; ", report.note.c_str());
}

// The mapping thread's ports, its wait set and its loop. It sleeps in the wait set until a keyframe comes, the
// server's anchors come, or tracking says it is done.
class MappingLoop {
 public:
  MappingLoop(Mapper& mapper, const AgentOptions& options, iox::popo::UserTrigger& tracking_done_trigger,
              const MappingLoopShared& shared)
      : mapper_(mapper),
        options_(options),
        shared_(shared),
        keyframes_(service(options.agent, "keyframes"), queueOf(ChannelDepths::forLag(options.tracking.lag).keyframes)),
        snapshots_(service(options.agent, "map_snapshot"), iox::popo::PublisherOptions{}) {
    const bool with_link = !options.link.server.empty();
    if (with_link) {
      deltas_.emplace(service(options.agent, "map_delta"), iox::popo::PublisherOptions{});
      // The server's covisible map and corrections, from the link: applied between keyframes, in order.
      anchors_.emplace(service(options.agent, "anchors"), queueOf(ChannelDepths::forLag(options.tracking.lag).anchors));
      if (!options.output.empty()) anchor_log_.emplace(options.output / "anchors.txt");
    }
    auto refused = [](auto) {
      std::fprintf(stderr, "[mapping] iceoryx refused an attachment to the wait set: waits fall back to 1 s\n");
    };
    wait_.attachState(keyframes_, iox::popo::SubscriberState::HAS_DATA).or_else(refused);
    if (anchors_) wait_.attachState(*anchors_, iox::popo::SubscriberState::HAS_DATA).or_else(refused);
    wait_.attachEvent(tracking_done_trigger).or_else(refused);
  }

  // RouDi connects publishers and subscribers asynchronously and iceoryx gives no event for it: a snapshot
  // published before tracking's subscriber is connected would be lost, and tracking would wait for a map that
  // never comes (likewise the link's deltas). This start-up step alone polls, bounded by 10 s.
  void awaitSubscribers() {
    const auto deadline = Clock::now() + std::chrono::seconds(10);
    while ((!snapshots_.hasSubscribers() || (deltas_ && !deltas_->hasSubscribers())) && Clock::now() < deadline &&
           !shared_.stop.load()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
  }

  void run() {
    const std::function<bool()> keyframe_waiting = [&] {
      if (keyframes_.hasData()) return true;
      if (!shared_.yield_requests.askedSinceKeyframeTaken()) return false;
      yielded_to_tracking_ = true;
      return true;
    };
    while (true) {
      applyAnchors();
      auto taken = keyframes_.take();
      if (taken.has_error()) {
        if (shared_.tracking_done.load() || shared_.stop.load()) {
          if (!keyframes_.hasData()) break;
          continue;
        }
        // The bound only lets a stop request in should every event be missed.
        wait_.timedWait(iox::units::Duration::fromSeconds(1));
        continue;
      }
      process(*taken.value(), keyframe_waiting);
    }
  }

 private:
  static iox::popo::SubscriberOptions queueOf(std::uint64_t capacity) {
    iox::popo::SubscriberOptions options;
    options.queueCapacity = capacity;
    return options;
  }

  void applyAnchors() {
    if (!anchors_) return;
    for (auto taken = anchors_->take(); !taken.has_error(); taken = anchors_->take()) {
      const AnchorMessage& m = *taken.value();
      // Where the server's corrections and covisible map reach the agent's map: the end of a keyframe's journey.
      const trace::Span span("apply_downlink", {{"downlink", static_cast<std::int64_t>(m.sequence)},
                                                {"corrections", static_cast<std::int64_t>(m.correction_count)},
                                                {"covisible", static_cast<std::int64_t>(m.has_covisible)}});
      tsanAcquire(&m);
      auto applied = mapper_.applyDownlink(m);
      tsanRelease(&m);
      if (!applied) {
        ++shared_.stats.downlink_refused;
        std::fprintf(stderr, "[mapping] downlink message refused: %s\n", applied.error().toString().c_str());
        continue;
      }
      shared_.stats.add(*applied);
      if (anchor_log_) anchor_log_->write(m, mapper_.map());
      if (options_.trace_mapping) traceDownlink(m, *applied);
    }
  }

  void process(const KeyframeMessage& msg, const std::function<bool()>& keyframe_waiting) {
    shared_.yield_requests.keyframeTaken();
    yielded_to_tracking_ = false;
    tsanAcquire(&msg);
    const ChunkReleaseOnExit release_keyframe{&msg};
    // Ends when the keyframe's local BA is done and its snapshot published.
    const trace::Span span("map_keyframe", {{"keyframe", msg.state.id.counter}});
    const std::int64_t t0 = steadyNowNs();
    shared_.receive.add(t0 - msg.publish_steady_ns);
    IceoryxLoan<MapSnapshotMessage> snapshot(snapshots_);
    MapSnapshotMessage* out = snapshot.loan();
    if (out == nullptr) {
      if (!fallback_) fallback_ = std::make_unique<MapSnapshotMessage>();
      out = fallback_.get();
      std::fprintf(stderr, "[mapping] no free snapshot chunk: this keyframe's map is not sent\n");
    }
    auto report = processInto(msg, *out, keyframe_waiting);
    shared_.mapping_total.add(steadyNowNs() - t0);
    const double t_s = static_cast<double>(msg.state.t_ns) * 1e-9;
    if (!report) {
      std::fprintf(stderr, "[mapping] keyframe %s refused: %s\n", msg.state.id.toString().c_str(),
                   report.error().toString().c_str());
      return;
    }
    count(*report, t_s);
    shared_.stats.time_corrections.emplace_back(msg.state.t_ns, report->time_correction_ns);
    if (options_.trace_mapping) traceKeyframe(t_s, msg, *report, yielded_to_tracking_);
    if (!options_.quiet) note(msg, *report, t_s);
    if (out != fallback_.get()) {
      out->sequence = snapshot_sequence_++;
      out->publish_steady_ns = steadyNowNs();
      snapshot.publish();
    }
  }

  // The mapper's work on one keyframe, with its deltas to the link. With link.keyframe_before_local_ba the keyframe
  // goes to the link as soon as it is in the map and its refined states follow after the local BA, so that the
  // BA's time (hundreds of ms when agents share the cores) is not on the keyframe's way to the server.
  Result<MapperReport> processInto(const KeyframeMessage& msg, MapSnapshotMessage& out,
                                   const std::function<bool()>& keyframe_waiting) {
    if (!deltas_) return mapper_.process(msg, out, nullptr, keyframe_waiting);
    if (!options_.link.keyframe_before_local_ba) {
      DeltaLoan delta(*this);
      return mapper_.process(msg, out, delta.get(), keyframe_waiting);
    }
    Result<MapperReport> report = [&] {
      DeltaLoan delta(*this);
      return mapper_.insert(msg, delta.get());
    }();
    if (!report) return report;
    DeltaLoan delta(*this);
    mapper_.refine(msg, *report, out, delta.get(), keyframe_waiting);
    return report;
  }

  // A delta loaned for the mapper to write, published when it goes out of scope whatever happened to the keyframe:
  // the link counts deltas by sequence.
  class DeltaLoan {
   public:
    explicit DeltaLoan(MappingLoop& loop) : loop_(loop), loan_(*loop.deltas_) {
      delta_ = loan_.loan();
      if (delta_ == nullptr) {
        if (!loop_.delta_fallback_) loop_.delta_fallback_ = std::make_unique<MapDeltaMessage>();
        delta_ = loop_.delta_fallback_.get();
        std::fprintf(stderr, "[mapping] no free delta chunk: the link misses this keyframe's changes\n");
      }
    }
    ~DeltaLoan() {
      delta_->sequence = loop_.delta_sequence_++;
      delta_->publish_steady_ns = steadyNowNs();
      loan_.publish();
    }
    DeltaLoan(const DeltaLoan&) = delete;
    DeltaLoan& operator=(const DeltaLoan&) = delete;
    [[nodiscard]] MapDeltaMessage* get() const { return delta_; }

   private:
    MappingLoop& loop_;
    IceoryxLoan<MapDeltaMessage> loan_;
    MapDeltaMessage* delta_ = nullptr;
  };

  void count(const MapperReport& report, double t_s) {
    MappingStats& stats = shared_.stats;
    ++stats.keyframes;
    stats.lost_messages += report.lost_messages;
    if (report.ba_ran) shared_.local_ba.add(report.ba_ns);
    if (report.ba_ran && report.ba.anchor_factors > 0) ++stats.ba_with_anchors;
    stats.ba_skipped += report.ba_skipped ? 1 : 0;
    stats.ba_stopped_early += report.ba_ran && report.ba.stopped_early ? 1 : 0;
    stats.ba_yielded_to_tracking += yielded_to_tracking_ ? 1 : 0;
    if (report.new_map) ++stats.new_maps;
    if (report.imu_initialised_now && stats.imu_initialised_at_s < 0) stats.imu_initialised_at_s = t_s;
  }

  static void note(const KeyframeMessage& msg, const MapperReport& report, double t_s) {
    if (!(report.imu_initialised_now || report.mono_initialised_now || report.map_restarted ||
          report.imu_initialisation_failed || report.new_map || report.lost_messages > 0)) {
      return;
    }
    std::fprintf(stderr, "[mapping] t=%.2f s keyframe %s: %s%s%s%s\n", t_s, msg.state.id.toString().c_str(),
                 report.new_map ? "new map. " : "",
                 report.map_restarted ? "IMU initialisation failed 20 times: map restarted. " : "",
                 report.lost_messages > 0 ? "keyframe messages lost before this one. " : "", report.note.c_str());
  }

  Mapper& mapper_;
  const AgentOptions& options_;
  MappingLoopShared shared_;
  iox::popo::Subscriber<KeyframeMessage> keyframes_;
  iox::popo::Publisher<MapSnapshotMessage> snapshots_;
  std::optional<iox::popo::Publisher<MapDeltaMessage>> deltas_;
  std::optional<iox::popo::Subscriber<AnchorMessage>> anchors_;
  iox::popo::WaitSet<3> wait_;
  std::optional<AnchorLog> anchor_log_;
  std::unique_ptr<MapSnapshotMessage> fallback_;  // only if no chunk can be loaned
  std::unique_ptr<MapDeltaMessage> delta_fallback_;
  std::uint64_t snapshot_sequence_ = 0;
  std::uint64_t delta_sequence_ = 0;
  bool yielded_to_tracking_ = false;  // this keyframe's BA yielded to a request rather than to a queued keyframe
};

}  // namespace

void mappingThread(Mapper& mapper, const AgentOptions& options, iox::popo::UserTrigger& tracking_done_trigger,
                   const MappingLoopShared& shared) {
  MappingLoop loop(mapper, options, tracking_done_trigger, shared);
  loop.awaitSubscribers();
  shared.ready.store(true);
  loop.run();
}

}  // namespace cvislam::agent
