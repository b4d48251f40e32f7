// Tracking latency per frame: Tracker::track() (IMU prediction, ORB, projection searches, pose optimisation,
// motion-only VI BA, keyframe decision and message write) on every frame of a EuRoC-format sequence, with
// mapping answering each keyframe in the same thread between frames (not timed). Frames are read before they
// are timed. Writes p50/p90/p99/max per stage and p99/p50 (the measure of determinism) as JSON.
//
//   taskset -c 1 build/default/bin/bench_agent_tracking [--dataset SEQ_DIR] [--mode stereo|mono]
//                                                        [--passes N] [--json OUT]
//
// Default dataset: the real V1_01 excerpt ($CVISLAM_DATA_DIR/euroc-v101-excerpt), stereo. Each pass runs
// the sequence from scratch (a new tracker and map), so every pass includes the start-up frames.
//
// With --server HOST:PORT (a cvislam_server running elsewhere, e.g. unpinned), passes alternate between no link
// and a link thread in this process streaming mapping's deltas to that server, so both see the same machine:
// two tables, without and with the link, in one run. Pinned with taskset, the link thread shares the core.
// With the link, what the server sends down (its covisible map, corrections) goes back into mapping between
// keyframes, as in the agent, so the link passes track against a local map with anchors in it. Local BA's time
// per keyframe is recorded too (mapping runs between frames, untimed for tracking). --local-map-keyframes N
// shrinks the local map (the newest N own keyframes, none kept for their places) so that on a short sequence the
// server already has older ones to send down. On the simulator's loop (60 s, which comes back over its start beyond the
// default local map):
//
//   build/default/bin/cvislam_sim --preset loop --seed 1 --stereo --out /tmp/loop
//   taskset -c 1 build/default/bin/bench_agent_tracking --dataset /tmp/loop/agent0 --server 127.0.0.1:50051
//
// With --compare-trace, passes alternate between tracing off and on (cvislam_agent --trace: every stage recorded
// into the thread's ring), so the trace's cost on tracking shows side by side in one run.
//
// With --compare-keyframe-interval, passes alternate between keyframes spaced by the frame count alone and the
// default time cap with the IMU (tracking.max_keyframe_interval_s): what the extra keyframes cost tracking.
//
// With --compare-place-keyframes, passes alternate between a local map of the newest keyframes only
// (mapping.place_keyframes 0) and the default, which keeps older keyframes for their places: what the larger map
// costs tracking, and local BA.
#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "agent_rt/link/link.hpp"
#include "agent_rt/runtime/latency_profile.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "common/trace/trace.hpp"
#include "test/support/delta_queue.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/test_data.hpp"

namespace {
// Per-frame figures of one kind of pass.
struct Recorders {
  explicit Recorders(std::size_t capacity)
      : total("tracking_total", capacity),
        orb("orb_extraction", capacity),
        matching("matching", capacity),
        pose("pose_optimisation", capacity),
        motion("motion_ba", capacity),
        local_ba("local_ba", capacity) {}
  cvislam::agent::LatencyRecorder total;
  cvislam::agent::LatencyRecorder orb;
  cvislam::agent::LatencyRecorder matching;
  cvislam::agent::LatencyRecorder pose;
  cvislam::agent::LatencyRecorder motion;
  cvislam::agent::LatencyRecorder local_ba;
  std::size_t frames = 0;
  std::size_t keyframes_with_anchors = 0;  // local BAs in which anchors' observations took part
  int anchors_added = 0;
  std::size_t tracked = 0;
  std::size_t keyframes = 0;
  std::uint64_t batches = 0;
  std::uint64_t up_bytes = 0;
  int unflushed = 0;
  std::size_t dropped = 0;
};

std::int64_t nowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Per-frame tracking latency of the cvislam agent on a EuRoC-format sequence"};
  std::string dataset = (cvislam::test::dataRoot() / "euroc-v101-excerpt").string();
  std::string mode = "stereo";
  std::string json;
  int passes = 5;
  std::string server;
  int local_map_keyframes = 0;
  app.add_option("--dataset", dataset, "Sequence folder that holds mav0");
  app.add_option("--local-map-keyframes", local_map_keyframes,
                 "N own keyframes in the local map, none kept for their places (default: the mapper's, 20 newest "
                 "and 40 for their places)")
      ->check(CLI::Range(10, 40));
  app.add_option("--server", server,
                 "cvislam_server HOST:PORT: alternate passes without and with the link streaming to it");
  app.add_option("--mode", mode, "stereo or mono")->check(CLI::IsMember({"stereo", "mono"}));
  app.add_option("--passes", passes, "Runs over the whole sequence")->check(CLI::PositiveNumber);
  app.add_option("--json", json, "Write the summary here as JSON");
  bool compare_trace = false;
  app.add_flag("--compare-trace", compare_trace, "Alternate passes with tracing off and on (cvislam_agent --trace)")
      ->excludes("--server");
  bool compare_interval = false;
  app.add_flag("--compare-keyframe-interval", compare_interval,
               "Alternate passes without and with the keyframe time cap (tracking.max_keyframe_interval_s)")
      ->excludes("--server")
      ->excludes("--compare-trace");
  bool compare_places = false;
  app.add_flag("--compare-place-keyframes", compare_places,
               "Alternate passes with the newest keyframes only and with the keyframes kept for their places "
               "(mapping.place_keyframes)")
      ->excludes("--server")
      ->excludes("--compare-trace")
      ->excludes("--compare-keyframe-interval")
      ->excludes("--local-map-keyframes");
  CLI11_PARSE(app, argc, argv);

  auto sequence = cvislam::dataset::EurocSequence::open(dataset);
  if (!sequence) {
    std::cerr << "bench_agent_tracking: " << sequence.error().toString() << "\n";
    return 1;
  }
  const std::size_t capacity = static_cast<std::size_t>(passes) * sequence->cam0().frames.size();
  // Index 0: without the link (or the trace, the keyframe time cap, the place keyframes); 1: with it.
  const bool compare = !server.empty() || compare_trace || compare_interval || compare_places;
  // What the two kinds of pass are called in the tables and the JSON.
  struct Variant {
    const char* label;
    const char* key;
  };
  std::array<Variant, 2> variants{Variant{"without the link", "without_link"},
                                  Variant{"with the link streaming to the server", "with_link"}};
  if (compare_trace) {
    variants = {Variant{"tracing off", "tracing_off"},
                Variant{"tracing on (every stage into the thread's ring)", "tracing_on"}};
  } else if (compare_interval) {
    variants = {Variant{"keyframes by frame count", "keyframe_interval_off"},
                Variant{"keyframes with the time cap", "keyframe_interval_on"}};
  } else if (compare_places) {
    variants = {Variant{"the newest keyframes only", "place_keyframes_off"},
                Variant{"keyframes kept for their places", "place_keyframes_on"}};
  }
  std::vector<Recorders> recorders;
  recorders.emplace_back(capacity);
  if (compare) recorders.emplace_back(capacity);
  const int total_passes = compare ? 2 * passes : passes;
  for (int pass = 0; pass < total_passes; ++pass) {
    const bool second = compare && pass % 2 == 1;
    const bool with_link = !server.empty() && second;
    const bool with_trace = compare_trace && second;
    Recorders& rec = recorders[second ? 1 : 0];
    std::optional<cvislam::trace::Session> trace_session;
    if (with_trace) {
      cvislam::trace::SessionOptions trace_options;
      trace_options.process_name = "agent 0";
      trace_options.events_per_thread = std::size_t{1} << 18;
      trace_session.emplace(trace_options);
      cvislam::trace::bindThread("tracking");
    }
    cvislam::agent::MapperOptions mapper_options;
    if (local_map_keyframes > 0) {
      mapper_options.max_keyframes = local_map_keyframes;
      mapper_options.imu_init_keyframes = std::min(mapper_options.imu_init_keyframes, local_map_keyframes - 5);
      mapper_options.imu_init_max_keyframes = local_map_keyframes;
      mapper_options.retention.place_keyframes = 0;
    }
    if (compare_places && !second) mapper_options.retention.place_keyframes = 0;
    cvislam::agent::TrackerOptions tracker_options;
    if (compare_interval && !second) tracker_options.keyframe.max_interval_s = 0.0;
    auto agent = cvislam::test::InlineAgent::create(*sequence, mode == "stereo", tracker_options, mapper_options);
    if (!agent) {
      std::cerr << "bench_agent_tracking: " << agent.error().toString() << "\n";
      return 1;
    }
    std::unique_ptr<cvislam::agent::Link> link;
    std::unique_ptr<cvislam::agent::test::DeltaQueue> deltas;
    cvislam::agent::test::AnchorQueue anchors(16);
    (*agent)->afterKeyframe([&](const cvislam::agent::MapperReport& report) {
      if (!report.ba_ran) return;
      rec.local_ba.add(report.ba_ns);
      rec.keyframes_with_anchors += report.ba.anchor_factors > 0 ? 1 : 0;
    });
    std::atomic<bool> stop{false};
    std::thread link_thread;
    if (with_link) {
      cvislam::agent::LinkOptions options;
      options.server = server;
      options.mission = "bench-pass" + std::to_string(pass);  // a fresh mission each pass: same ids, no clash
      options.flush_timeout_s = 5.0;
      options.local_map_keyframes = static_cast<std::uint32_t>(mapper_options.max_keyframes);
      auto setup = cvislam::agent::makeSensorSetup(*sequence, mode == "stereo", 1.0);
      if (!setup) {
        std::cerr << "bench_agent_tracking: " << setup.error().toString() << "\n";
        return 1;
      }
      auto created = cvislam::agent::Link::create(  // agent 0: the inline agent's id
          options, 0, cvislam::agent::linkSensors(*sequence, *setup, mode == "stereo", true));
      if (!created) {
        std::cerr << "bench_agent_tracking: " << created.error().toString() << "\n";
        return 1;
      }
      link = std::move(created.value());
      deltas = std::make_unique<cvislam::agent::test::DeltaQueue>(64);
      (*agent)->onDelta([&](const cvislam::agent::MapDeltaMessage& d) { deltas->push(d); });
      (*agent)->beforeKeyframe([&](cvislam::agent::Mapper& mapper) {
        for (const cvislam::agent::AnchorMessage* m = anchors.take(); m != nullptr; m = anchors.take()) {
          if (auto r = mapper.applyDownlink(*m); r.ok()) rec.anchors_added += r->anchors_added;
          anchors.done();
        }
      });
      link_thread = std::thread([&] { link->run(*deltas, stop, &anchors); });
    }
    for (std::size_t i = 0; i < (*agent)->frameCount(); ++i) {
      if (!(*agent)->load(i).ok()) continue;
      std::int64_t t0 = 0;
      std::int64_t t1 = 0;
      // As in the agent's tracking loop, whose span is outside the tracker's own timing.
      cvislam::trace::Span frame_span("track_frame", {{"frame", static_cast<std::int64_t>(i)}});
      const cvislam::agent::FrameResult r = (*agent)->track([&] { t0 = nowNs(); }, [&] { t1 = nowNs(); });
      ++rec.frames;
      rec.total.add(t1 - t0);
      rec.orb.add(r.times.orb_ns);
      if (r.tracked) {
        ++rec.tracked;
        rec.matching.add(r.times.matching_ns);
        rec.pose.add(r.times.pose_ns);
        if (r.times.motion_ba_ns > 0) rec.motion.add(r.times.motion_ba_ns);
      }
      rec.keyframes += r.keyframe ? 1 : 0;
    }
    if (with_link) {
      stop.store(true);
      link_thread.join();
      const cvislam::agent::LinkStatus status = link->status();
      rec.batches += status.acked_sequence;
      rec.up_bytes += status.up_bytes;
      rec.unflushed += status.flushed ? 0 : 1;
      rec.dropped += deltas->dropped();
    }
  }
  nlohmann::json out = nlohmann::json::object();
  for (std::size_t k = 0; k < recorders.size(); ++k) {
    Recorders& rec = recorders[k];
    std::vector<cvislam::agent::StageSummary> stages;
    for (const auto* r : {&rec.total, &rec.orb, &rec.matching, &rec.pose, &rec.motion, &rec.local_ba}) {
      stages.push_back(cvislam::agent::summarise(*r));
    }
    const char* label = variants[k].label;
    std::printf("%s, %s: %zu frames (%d passes), %zu tracked, %zu keyframes\n%s", dataset.c_str(), label, rec.frames,
                passes, rec.tracked, rec.keyframes, cvislam::agent::formatLatencyTable(stages).c_str());
    const double determinism = stages[0].ms.p50 > 0 ? stages[0].ms.p99 / stages[0].ms.p50 : 0.0;
    std::printf("tracking p99/p50 = %.2f\n", determinism);
    if (k == 1 && !server.empty()) {
      std::printf("link: %llu batches acknowledged, %.2f MB up, %d passes not flushed, %zu deltas dropped\n",
                  static_cast<unsigned long long>(rec.batches), static_cast<double>(rec.up_bytes) * 1e-6, rec.unflushed,
                  rec.dropped);
      std::printf("downlink: %d anchors added; %zu of %zu local BAs with anchors' observations in them\n",
                  rec.anchors_added, rec.keyframes_with_anchors, rec.local_ba.samplesMs().size());
    }
    out[variants[k].key] = nlohmann::json::parse(cvislam::agent::latencyJson(stages));
  }
  if (!json.empty()) std::ofstream(json) << (compare ? out.dump(2) : out["without_link"].dump(2)) << "\n";
  return 0;
}
