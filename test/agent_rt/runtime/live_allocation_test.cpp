// The design card's promise with live input: after start-up, taking a frame from a driver's live topics, tracking it
// and handing it back make no heap allocation. This binary replaces malloc (test/support/malloc_counter) and counts
// the calls made by the tracking thread alone. A driver thread plays a simulated stereo sequence (rendered at test
// time, fixed seed) through a real SensorPublisher and an in-process RouDi, one frame after the other, and the real
// Tracker and Mapper run on what the live feed hands over (test/support/inline_agent).
#include <atomic>
#include <cstdio>
#include <thread>

#include <gtest/gtest.h>

#include "agent_rt/ipc/embedded_roudi.hpp"
#include "agent_rt/live/sensor_publisher.hpp"
#include "agent_rt/live/sensor_topics.hpp"
#include "agent_rt/runtime/live_feed.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "common/dataset/euroc.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/malloc_counter.hpp"
#include "test/support/rendered_mission.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::agent {
namespace {

// The driver: the sequence's IMU up to each frame and then the frame, each frame only once the one before was
// handed back, so that none is dropped and the run repeats.
void drive(const dataset::EurocSequence& sequence, const std::vector<dataset::RigFrame>& frames,
           live::SensorPublisher& publisher, const std::atomic<std::size_t>& released, std::atomic<bool>& failed) {
  const auto imu = sequence.imu();
  std::size_t next_imu = 0;
  for (std::size_t i = 0; i < frames.size(); ++i) {
    while (released.load() < i) released.wait(released.load());
    for (; next_imu < imu.size() && imu[next_imu].t_ns <= frames[i].t_ns; ++next_imu)
      publisher.publishImu(imu[next_imu]);
    if (next_imu < imu.size()) publisher.publishImu(imu[next_imu++]);  // the first sample after the frame closes it
    std::span<std::uint8_t> pixels = publisher.loanFrame();
    const std::size_t one = pixels.size() / 2;
    if (pixels.empty() || !sequence.loadImageInto(0, frames[i].cam0, pixels.subspan(0, one)).ok() ||
        !sequence.loadImageInto(1, *frames[i].cam1, pixels.subspan(one, one)).ok()) {
      failed.store(true);
      return;
    }
    publisher.publishFrame(frames[i].t_ns);
  }
  publisher.publishEndOfStream();
}

TEST(LiveTrackingAllocations, TakingTrackingAndHandingBackALiveFrameAllocateNothing) {
  test::TempDir dir;
  auto mission = test::renderedMission({"loop", 5, 8.0, /*stereo=*/true}, dir.path());
  ASSERT_TRUE(mission.ok()) << mission.error().toString();
  auto sequence = dataset::EurocSequence::open(*mission / "agent0");
  ASSERT_TRUE(sequence.ok()) << sequence.error().toString();
  const auto& cam0 = sequence->cam0().calibration;
  const std::uint32_t frame_bytes = static_cast<std::uint32_t>(
      live::frameChunkBytes(static_cast<std::uint32_t>(cam0.width), static_cast<std::uint32_t>(cam0.height), 2));
  EmbeddedRouDiOptions roudi_options;
  roudi_options.runtime_name = "cvislam_live_allocation_test";
  roudi_options.mempools = {{128, 2000}, {frame_bytes, 16}};
  auto roudi = EmbeddedRouDi::start(roudi_options);
  ASSERT_TRUE(roudi.ok()) << roudi.error().toString();

  auto agent = test::InlineAgent::create(*sequence, /*stereo=*/true);
  ASSERT_TRUE(agent.ok()) << agent.error().toString();
  LiveFeedOptions feed_options;
  feed_options.stream = "alloc";
  feed_options.width = cam0.width;
  feed_options.height = cam0.height;
  feed_options.stereo = true;
  feed_options.quiet = true;
  feed_options.imu_wait_s = 1.0;
  feed_options.stall_after_s = 10.0;
  auto feed = openLiveFeed(feed_options);
  ASSERT_TRUE(feed.ok()) << feed.error().toString();
  live::SensorPublisherOptions publisher_options;
  publisher_options.stream = "alloc";
  publisher_options.width = static_cast<std::uint32_t>(cam0.width);
  publisher_options.height = static_cast<std::uint32_t>(cam0.height);
  publisher_options.cameras = 2;
  auto publisher = live::SensorPublisher::create(publisher_options);
  ASSERT_TRUE(publisher.ok()) << publisher.error().toString();
  for (int i = 0; i < 500 && !(*publisher)->hasSubscribers(); ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  ASSERT_TRUE((*publisher)->hasSubscribers());
  std::this_thread::sleep_for(std::chrono::milliseconds(50));  // the IMU topic connects beside the frames

  const auto frames = framesToRun(*sequence, /*stereo=*/true);
  std::atomic<std::size_t> released{0};
  std::atomic<bool> driver_failed{false};
  std::thread driver([&] { drive(*sequence, frames, **publisher, released, driver_failed); });

  int steady_frames = 0;
  int steady_keyframes = 0;
  long steady_allocations = 0;
  while (true) {
    const bool steady = (*agent)->imuInitialised();
    const long before = test::threadMallocCount();
    const FeedFrame* frame = (*feed)->next();
    if (frame == nullptr) break;
    ASSERT_TRUE(frame->ok) << frame->error;
    FrameInput input;
    input.t_ns = frame->t_ns;
    input.width = cam0.width;
    input.height = cam0.height;
    input.left = frame->left;
    input.right = frame->right;
    input.imu = frame->imu;
    (*agent)->setInput(input);
    long tracked = 0;
    const FrameResult r = (*agent)->track([] {}, [&] { tracked = test::threadMallocCount(); });
    const long before_release = test::threadMallocCount();
    (*feed)->release();
    const long after = test::threadMallocCount();
    released.fetch_add(1);
    released.notify_all();
    if (!steady) continue;
    const long allocations = (tracked - before) + (after - before_release);
    ++steady_frames;
    steady_keyframes += r.keyframe ? 1 : 0;
    steady_allocations += allocations;
    if (allocations != 0) std::printf("frame %d: %ld allocations\n", steady_frames, allocations);
  }
  driver.join();
  ASSERT_FALSE(driver_failed.load());
  std::printf("steady state: %d frames, %d keyframes, %ld allocations\n", steady_frames, steady_keyframes,
              steady_allocations);
  EXPECT_GE(steady_frames, 100);
  EXPECT_GE(steady_keyframes, 3);
  EXPECT_EQ(steady_allocations, 0);
  EXPECT_FALSE((*feed)->faults().any());
}

}  // namespace
}  // namespace cvislam::agent
