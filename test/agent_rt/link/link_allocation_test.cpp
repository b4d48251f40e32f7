// The design card's promise holds with the link running: after start-up, the tracking loop makes no heap
// allocation. The real tracker and mapper track a rendered stereo sequence (fixed seed) on this thread while a
// link thread streams their deltas to a real cvislam server over loopback gRPC. malloc is replaced
// (test/support/malloc_counter); the link thread allocates (gRPC, protobuf), so the count here is the tracking
// thread's own. The link thread's allocations are printed per second of sequence, for the record. What the
// server sends down (the agent's own older keyframes, once the loop comes back over its start) goes through a
// queue into mapping, so tracking runs against a local map with anchors in it too.
#include <atomic>
#include <cstdio>
#include <thread>

#include <gtest/gtest.h>

#include "agent_rt/link/link.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "cvislam/v1/monitor.pb.h"
#include "server_cloud/service/grpc_server.hpp"
#include "test/agent_rt/link/link_test_support.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/malloc_counter.hpp"
#include "test/support/rendered_mission.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::agent {
namespace {

// A pose that moves each time the link asks for one; the newest handed out is remembered.
class MovingPoses final : public PoseSource {
 public:
  bool newest(LivePose& out) override {
    const std::int64_t n = ++asked_;
    out.t_ns = test::kStartNs + n;  // a new time each batch
    out.map_id = 0;
    out.T_w_s = geometry::SE3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.01 * static_cast<double>(n), 0, 1));
    out.metric = true;
    last_t_ns_.store(out.t_ns);
    return true;
  }
  [[nodiscard]] std::int64_t lastTns() const { return last_t_ns_.load(); }

 private:
  std::int64_t asked_ = 0;
  std::atomic<std::int64_t> last_t_ns_{0};
};

TEST(LinkAllocations, TrackingAllocatesNothingWhileTheLinkStreamsToAServer) {
  cvislam::test::TempDir dir;
  // Long enough for the loop to come back over its start: the server then sends the agent's own older
  // keyframes down, and tracking runs against a local map with anchors in it.
  constexpr double kDurationS = 16.0;
  auto mission = cvislam::test::renderedMission({"loop", 5, kDurationS, /*stereo=*/true}, dir.path());
  ASSERT_TRUE(mission.ok()) << mission.error().toString();
  auto seq = dataset::EurocSequence::open(*mission / "agent0");
  ASSERT_TRUE(seq.ok()) << seq.error().toString();

  // A real server on loopback.
  server::ServerOptions server_options;
  server_options.listen = "127.0.0.1:0";
  server::ServerCore core(server_options);
  auto grpc_server = server::GrpcServer::start(core);
  ASSERT_TRUE(grpc_server.ok()) << grpc_server.error().toString();

  LinkOptions link_options;
  link_options.server = (*grpc_server)->address();
  link_options.mission = "allocations";
  // A local map of 15 own keyframes (the server sends down the older ones it sees covisible).
  constexpr int kLocalMapKeyframes = 15;
  link_options.local_map_keyframes = kLocalMapKeyframes;
  auto setup = makeSensorSetup(*seq, /*stereo=*/true, 1.0);
  ASSERT_TRUE(setup.ok()) << setup.error().toString();
  auto link = Link::create(link_options, test::kAgent, linkSensors(*seq, *setup, /*stereo=*/true, /*uses_imu=*/true));
  ASSERT_TRUE(link.ok()) << link.error().toString();
  test::DeltaQueue deltas(16);
  test::AnchorQueue anchors(8);
  // The link thread's own allocation count, sampled by the link thread itself once half the sequence has passed.
  std::atomic<bool> halfway{false};
  long link_allocations_at_halfway = -1;
  auto halfway_at = std::chrono::steady_clock::now();
  deltas.on_poll = [&] {
    if (halfway.load() && link_allocations_at_halfway < 0) {
      link_allocations_at_halfway = cvislam::test::threadMallocCount();
      halfway_at = std::chrono::steady_clock::now();
    }
  };
  std::atomic<bool> stop{false};
  long link_allocations = 0;
  long link_allocations_at_end = 0;
  auto end_at = std::chrono::steady_clock::now();
  MovingPoses poses;
  std::thread link_thread([&] {
    const long before = cvislam::test::threadMallocCount();
    (*link)->run(deltas, stop, &anchors, &poses);
    link_allocations_at_end = cvislam::test::threadMallocCount();
    link_allocations = link_allocations_at_end - before;
  });

  TrackerOptions tracker_options;
  tracker_options.agent = test::kAgent;
  MapperOptions mapper_options;
  mapper_options.agent = test::kAgent;
  mapper_options.max_keyframes = kLocalMapKeyframes;
  // None kept for their places: on this short sequence the map would keep every keyframe, and the server's
  // covisible ones would all be held already.
  mapper_options.retention.place_keyframes = 0;
  mapper_options.imu_init_keyframes = 10;
  mapper_options.imu_init_max_keyframes = kLocalMapKeyframes;
  auto agent = cvislam::test::InlineAgent::create(*seq, true, tracker_options, mapper_options);
  ASSERT_TRUE(agent.ok()) << agent.error().toString();
  (*agent)->onDelta([&](const MapDeltaMessage& d) { deltas.push(d); });
  DownlinkReport downlink;         // summed
  int keyframes_with_anchors = 0;  // keyframes mapping processed with anchors in the local map
  (*agent)->beforeKeyframe([&](Mapper& mapper) {
    for (const AnchorMessage* m = anchors.take(); m != nullptr; m = anchors.take()) {
      if (auto r = mapper.applyDownlink(*m); r.ok()) {
        downlink.anchors_added += r->anchors_added;
        downlink.points_added += r->points_added;
        downlink.corrections_applied += r->corrections_applied + r->corrections_deferred;
      }
      anchors.done();
    }
    bool any = false;
    mapper.map().keyframes().forEach([&](PoolHandle, const KeyframeData& kf) { any = any || kf.anchor; });
    keyframes_with_anchors += any ? 1 : 0;
  });
  auto counted = (*agent)->countSteadyAllocations([] { return cvislam::test::threadMallocCount(); },
                                                  [&](std::size_t i) {
                                                    // Paced like the sensor (20 Hz): the link streams while tracking
                                                    // runs.
                                                    std::this_thread::sleep_for(std::chrono::milliseconds(20));
                                                    if (i == (*agent)->frameCount() / 2) halfway.store(true);
                                                    if (i + 1 == (*agent)->frameCount()) {
                                                      end_at = std::chrono::steady_clock::now();
                                                    }
                                                  });
  ASSERT_TRUE(counted.ok()) << counted.error().toString();
  const int steady_frames = counted->frames;
  const int steady_keyframes = counted->keyframes;
  const long steady_allocations = counted->allocations;
  stop.store(true);
  link_thread.join();
  const LinkStatus status = (*link)->status();
  const double second_half_s = std::chrono::duration<double>(end_at - halfway_at).count();
  const long second_half = link_allocations_at_end - link_allocations_at_halfway;
  std::printf(
      "tracking: %d steady frames, %d keyframes, %ld allocations; link thread: %ld allocations in all, %ld in "
      "the second half (%.1f s: %.0f per second, the flush included), %llu batches, %.2f MB up, flushed %d\n",
      steady_frames, steady_keyframes, steady_allocations, link_allocations, second_half, second_half_s,
      static_cast<double>(second_half) / second_half_s, static_cast<unsigned long long>(status.acked_sequence),
      static_cast<double>(status.up_bytes) * 1e-6, status.flushed ? 1 : 0);
  std::printf(
      "downlink applied by mapping: %d anchors with %d points, %d corrections; %d keyframes processed with "
      "anchors in the local map\n",
      downlink.anchors_added, downlink.points_added, downlink.corrections_applied, keyframes_with_anchors);
  EXPECT_GT(downlink.anchors_added, 0) << "tracking ran against anchors from the server";
  EXPECT_EQ(anchors.dropped(), 0U);
  ASSERT_GE(steady_frames, 100);
  EXPECT_GE(steady_keyframes, 3);
  EXPECT_EQ(steady_allocations, 0);
  // The link really streamed while tracking ran: the server holds the map.
  EXPECT_TRUE(status.flushed);
  EXPECT_EQ(deltas.dropped(), 0U);
  EXPECT_GT(status.acked_sequence, 5U);
  v1::ServerStats stats;
  core.fillStats("allocations", stats);
  ASSERT_EQ(stats.agents_size(), 1);
  EXPECT_GE(stats.agents(0).keyframes(), static_cast<std::uint64_t>(steady_keyframes));
  // Every batch carried the newest pose: the server holds the last one handed to the link.
  const auto record = core.missions().find("allocations")->findAgent(test::kAgent);
  ASSERT_NE(record, nullptr);
  ASSERT_TRUE(record->read()->live_pose.has_value());
  EXPECT_EQ(record->read()->live_pose->t_ns, poses.lastTns());
  (*grpc_server)->shutdown();
}

}  // namespace
}  // namespace cvislam::agent
