#include "agent_rt/runtime/mapping_thread.hpp"

#include <chrono>
#include <cstdio>
#include <functional>
#include <memory>
#include <optional>
#include <thread>

#include "agent_rt/runtime/iceoryx_channels.hpp"

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

void mappingThread(Mapper& mapper, const AgentOptions& options, std::atomic<bool>& tracking_done,
                   const std::atomic<bool>& stop, LatencyRecorder& receive, LatencyRecorder& local_ba,
                   LatencyRecorder& mapping_total, MappingStats& stats, std::atomic<bool>& ready,
                   YieldRequests& yield_requests) {
  const bool with_link = !options.link.server.empty();
  iox::popo::SubscriberOptions sub_options;
  const ChannelDepths depths = ChannelDepths::forLag(options.tracking.lag);
  sub_options.queueCapacity = depths.keyframes;
  iox::popo::Subscriber<KeyframeMessage> keyframes(service(options.agent, "keyframes"), sub_options);
  iox::popo::PublisherOptions pub_options;
  iox::popo::Publisher<MapSnapshotMessage> snapshots(service(options.agent, "map_snapshot"), pub_options);
  std::optional<iox::popo::Publisher<MapDeltaMessage>> deltas;
  if (with_link) deltas.emplace(service(options.agent, "map_delta"), pub_options);
  // The server's covisible map and corrections, from the link: applied between keyframes, in order.
  std::optional<iox::popo::Subscriber<AnchorMessage>> anchors;
  if (with_link) {
    iox::popo::SubscriberOptions anchor_options;
    anchor_options.queueCapacity = depths.anchors;
    anchors.emplace(service(options.agent, "anchors"), anchor_options);
  }
  // anchors.txt: after every downlink message that carried a covisible map, the local map's newest own keyframe
  // and every anchor held, each with its pose in the agent's world frame, so that the anchors' consistency with
  // the agent's own estimate can be checked against ground truth after the run (tools/anchor_consistency.py).
  struct FileCloser {
    void operator()(std::FILE* f) const {
      if (f != nullptr) std::fclose(f);
    }
  };
  std::unique_ptr<std::FILE, FileCloser> anchor_log;
  if (with_link && !options.output.empty()) {
    anchor_log.reset(std::fopen((options.output / "anchors.txt").c_str(), "w"));
    if (anchor_log) {
      std::fprintf(anchor_log.get(),
                   "# kind(K: newest own keyframe, A: anchor) stream sequence keyframe_agent keyframe_counter t_ns "
                   "tx ty tz qx qy qz qw (T_w_s, the agent's world frame)\n");
    }
  }
  const auto log_anchors = [&](const AnchorMessage& m) {
    if (!anchor_log || m.has_covisible == 0) return;
    const auto write = [&](char kind, const KeyframeData& kf) {
      const Eigen::Vector3d& t = kf.T_w_s.translation();
      const Eigen::Quaterniond& q = kf.T_w_s.quaternion();
      std::fprintf(anchor_log.get(), "%c %u %llu %u %u %lld %.6f %.6f %.6f %.9f %.9f %.9f %.9f\n", kind, m.stream,
                   static_cast<unsigned long long>(m.sequence), static_cast<unsigned>(kf.id.agent),
                   static_cast<unsigned>(kf.id.counter), static_cast<long long>(kf.t_ns), t.x(), t.y(), t.z(), q.x(),
                   q.y(), q.z(), q.w());
    };
    const KeyframeData* newest = nullptr;
    mapper.map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
      if (!kf.anchor && (newest == nullptr || kf.sequence > newest->sequence)) newest = &kf;
    });
    if (newest == nullptr) return;
    write('K', *newest);
    mapper.map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) {
      if (kf.anchor) write('A', kf);
    });
  };
  const auto apply_anchors = [&] {
    if (!anchors) return;
    for (auto taken = anchors->take(); !taken.has_error(); taken = anchors->take()) {
      const AnchorMessage& m = *taken.value();
      tsanAcquire(&m);
      auto applied = mapper.applyDownlink(m);
      tsanRelease(&m);
      if (!applied) {
        ++stats.downlink_refused;
        std::fprintf(stderr, "[mapping] downlink message refused: %s\n", applied.error().toString().c_str());
        continue;
      }
      stats.add(*applied);
      log_anchors(m);
      if (options.trace_mapping) {
        std::fprintf(stderr,
                     "[mapping] downlink %u/%llu: anchors +%d -%d (held %d), points +%d (linked %d, over capacity %d), "
                     "%d unknown references, corrections %d applied / %d skipped (largest %.3f m)%s%s\n",
                     m.stream, static_cast<unsigned long long>(m.sequence), applied->anchors_added,
                     applied->anchors_released, applied->anchors_held, applied->points_added, applied->points_linked,
                     applied->points_over_capacity, applied->unknown_references, applied->corrections_applied,
                     applied->corrections_skipped, applied->largest_correction_m, applied->stale ? ", stale" : "",
                     applied->skipped.empty() ? "" : (", " + applied->skipped).c_str());
      }
    }
  };
  // RouDi connects publishers and subscribers asynchronously: a snapshot published before tracking's
  // subscriber is connected would be lost, and tracking would wait for a map that never comes (likewise the
  // link's deltas).
  const auto deadline = Clock::now() + std::chrono::seconds(10);
  while ((!snapshots.hasSubscribers() || (deltas && !deltas->hasSubscribers())) && Clock::now() < deadline &&
         !stop.load()) {
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  ready.store(true);
  bool yielded_to_tracking = false;  // this keyframe's BA yielded to a request rather than to a queued keyframe
  const std::function<bool()> keyframe_waiting = [&] {
    if (keyframes.hasData()) return true;
    if (!yield_requests.askedSinceKeyframeTaken()) return false;
    yielded_to_tracking = true;
    return true;
  };
  std::unique_ptr<MapSnapshotMessage> fallback;  // only if no chunk can be loaned
  std::unique_ptr<MapDeltaMessage> delta_fallback;
  std::uint64_t sequence = 0;
  std::uint64_t delta_sequence = 0;
  while (true) {
    apply_anchors();
    auto taken = keyframes.take();
    if (taken.has_error()) {
      if (tracking_done.load() || stop.load()) {
        if (!keyframes.hasData()) break;
        continue;
      }
      std::this_thread::sleep_for(std::chrono::microseconds(200));
      continue;
    }
    const KeyframeMessage& msg = *taken.value();
    yield_requests.keyframeTaken();
    yielded_to_tracking = false;
    tsanAcquire(&msg);
    const ChunkReleaseOnExit release_keyframe{&msg};
    const std::int64_t t0 = steadyNs();
    receive.add(t0 - msg.publish_steady_ns);
    auto loaned = snapshots.loan();
    MapSnapshotMessage* out = nullptr;
    if (!loaned.has_error()) {
      out = loaned.value().get();
      tsanAcquire(out);
    } else {
      if (!fallback) fallback = std::make_unique<MapSnapshotMessage>();
      out = fallback.get();
      std::fprintf(stderr, "[mapping] no free snapshot chunk: this keyframe's map is not sent\n");
    }
    MapDeltaMessage* delta = nullptr;
    std::optional<iox::popo::Sample<MapDeltaMessage>> delta_sample;
    if (deltas) {
      auto loaned_delta = deltas->loan();
      if (!loaned_delta.has_error()) {
        delta_sample.emplace(std::move(loaned_delta.value()));
        delta = delta_sample->get();
        tsanAcquire(delta);
      } else {
        if (!delta_fallback) delta_fallback = std::make_unique<MapDeltaMessage>();
        delta = delta_fallback.get();
        std::fprintf(stderr, "[mapping] no free delta chunk: the link misses this keyframe's changes\n");
      }
    }
    auto report = mapper.process(msg, *out, delta, keyframe_waiting);
    if (delta_sample) {
      // Published whatever happened to the keyframe: the link counts deltas by sequence.
      delta->sequence = delta_sequence;
      delta->publish_steady_ns = steadyNs();
      tsanRelease(delta);
      delta_sample->publish();
    }
    if (delta != nullptr) ++delta_sequence;
    const std::int64_t t1 = steadyNs();
    mapping_total.add(t1 - t0);
    const double t_s = static_cast<double>(msg.state.t_ns) * 1e-9;
    if (!report) {
      std::fprintf(stderr, "[mapping] keyframe %s refused: %s\n", msg.state.id.toString().c_str(),
                   report.error().toString().c_str());
      continue;
    }
    ++stats.keyframes;
    stats.lost_messages += report->lost_messages;
    if (report->ba_ran) local_ba.add(report->ba_ns);
    if (report->ba_ran && report->ba.anchor_factors > 0) ++stats.ba_with_anchors;
    stats.ba_skipped += report->ba_skipped ? 1 : 0;
    stats.ba_stopped_early += report->ba_ran && report->ba.stopped_early ? 1 : 0;
    stats.ba_yielded_to_tracking += yielded_to_tracking ? 1 : 0;
    if (options.trace_mapping) {
      std::fprintf(
          stderr,
          "[mapping] t=%.2f s keyframe %s: linked %d, fused %d, merged %d, stereo %d matched / %d new points, "
          "triangulated %d, culled %d; BA %d keyframes + %d fixed (%d anchors), %d points (%d left out), %d factors "
          "(%d cam1, %d mismatches left out, %d by anchors), cost %.1f -> %.1f in %d iterations, %.1f ms%s\n",
          t_s, msg.state.id.toString().c_str(), report->linked, report->fused, report->merged, report->stereo_matches,
          report->stereo_points, report->triangulated, report->culled, report->ba.window_keyframes,
          report->ba.fixed_keyframes, report->ba.anchor_keyframes, report->ba.map_points,
          report->ba.map_points_left_out, report->ba.reprojection_factors, report->ba.second_camera_factors,
          report->ba.second_camera_rejected, report->ba.anchor_factors, report->ba.initial_cost, report->ba.final_cost,
          report->ba.iterations, static_cast<double>(report->ba_ns) * 1e-6,
          report->ba_skipped && yielded_to_tracking         ? " (BA skipped: tracking asked)"
          : report->ba_skipped                              ? " (BA skipped: the next keyframe is waiting)"
          : report->ba.stopped_early && yielded_to_tracking ? " (BA cut short: tracking asked)"
          : report->ba.stopped_early                        ? " (BA cut short: the next keyframe is waiting)"
                                                            : "");
    }
    if (report->new_map) ++stats.new_maps;
    if (report->imu_initialised_now && stats.imu_initialised_at_s < 0) stats.imu_initialised_at_s = t_s;
    if (!options.quiet && (report->imu_initialised_now || report->mono_initialised_now || report->map_restarted ||
                           report->imu_initialisation_failed || report->new_map || report->lost_messages > 0)) {
      std::fprintf(stderr, "[mapping] t=%.2f s keyframe %s: %s%s%s%s\n", t_s, msg.state.id.toString().c_str(),
                   report->new_map ? "new map. " : "",
                   report->map_restarted ? "IMU initialisation failed 20 times: map restarted. " : "",
                   report->lost_messages > 0 ? "keyframe messages lost before this one. " : "", report->note.c_str());
    }
    if (out != fallback.get()) {
      out->sequence = sequence++;
      out->publish_steady_ns = steadyNs();
      tsanRelease(out);
      loaned.value().publish();
    }
  }
}

}  // namespace cvislam::agent
