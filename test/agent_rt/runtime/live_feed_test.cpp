// The live sensor topics with real iceoryx (an in-process RouDi): a driver's SensorPublisher on one side, the agent's
// live feed on the other. Frames arrive in place (the feed's pixels are the driver's loaned memory), each with the IMU
// samples that cover it; bad, late and foreign messages are dropped and counted, a frame waits a bounded time for the
// IMU, a restarted driver is noticed, and the end of the stream or a stop ends the feed. Tests of this binary hold
// the CTest resource lock "iceoryx_roudi".
#include "agent_rt/runtime/live_feed.hpp"

#include <atomic>
#include <chrono>
#include <cstring>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/ipc/embedded_roudi.hpp"
#include "agent_rt/live/live_service.hpp"
#include "agent_rt/live/sensor_publisher.hpp"
#include "agent_rt/messages/messages.hpp"
#include "agent_rt/runtime/sensor_setup.hpp"
#include "iceoryx_posh/popo/untyped_publisher.hpp"

namespace cvislam::agent {
namespace {

using live::SensorPublisher;
using std::chrono::milliseconds;

constexpr int kWidth = 64;
constexpr int kHeight = 48;
constexpr std::int64_t kFramePeriodNs = 50'000'000;
constexpr std::int64_t kImuPeriodNs = 5'000'000;

class LiveFeedTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    EmbeddedRouDiOptions options;
    options.runtime_name = "cvislam_live_feed_test";
    options.mempools = {{128, 2000}, {8 * 1024, 64}, {16 * 1024, 64}};
    auto started = EmbeddedRouDi::start(options);
    ASSERT_TRUE(started.ok()) << started.error().toString();
    roudi_ = std::move(started).value().release();
  }
  static void TearDownTestSuite() {
    delete roudi_;
    roudi_ = nullptr;
  }

  static LiveFeedOptions feedOptions(const std::string& stream, bool stereo = false) {
    LiveFeedOptions options;
    options.stream = stream;
    options.width = kWidth;
    options.height = kHeight;
    options.stereo = stereo;
    options.imu_wait_s = 0.2;
    options.quiet = true;
    return options;
  }
  static std::unique_ptr<SensorPublisher> publisher(const std::string& stream, std::uint32_t cameras = 1,
                                                    std::uint32_t width = kWidth) {
    live::SensorPublisherOptions options;
    options.stream = stream;
    options.width = width;
    options.height = kHeight;
    options.cameras = cameras;
    auto created = SensorPublisher::create(options);
    EXPECT_TRUE(created.ok()) << created.error().toString();
    return created.ok() ? std::move(created).value() : nullptr;
  }
  // RouDi connects publishers and subscribers asynchronously: wait until the driver sees the feed.
  static void awaitConnection(const SensorPublisher& publisher) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (!publisher.hasSubscribers() && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(milliseconds(5));
    }
    ASSERT_TRUE(publisher.hasSubscribers());
    std::this_thread::sleep_for(milliseconds(20));  // the IMU topic connects beside the frames
  }
  static dataset::ImuSample imuAt(std::int64_t t_ns) {
    dataset::ImuSample s;
    s.t_ns = t_ns;
    s.gyro_s = {0.001 * static_cast<double>(t_ns / kImuPeriodNs), 0.0, 0.0};
    s.accel_s = {0.0, 0.0, 9.81};
    return s;
  }
  // The IMU samples of (from, to] and then a frame at `to` whose pixels are all `value`; returns the loaned pixels.
  static const std::uint8_t* publishFrame(SensorPublisher& publisher, std::int64_t from_ns, std::int64_t to_ns,
                                          std::uint8_t value, std::vector<dataset::ImuSample>* imu_log = nullptr) {
    for (std::int64_t t = from_ns - from_ns % kImuPeriodNs + kImuPeriodNs; t <= to_ns; t += kImuPeriodNs) {
      publisher.publishImu(imuAt(t));
      if (imu_log != nullptr) imu_log->push_back(imuAt(t));
    }
    std::span<std::uint8_t> pixels = publisher.loanFrame();
    EXPECT_FALSE(pixels.empty());
    std::memset(pixels.data(), value, pixels.size());
    publisher.publishFrame(to_ns);
    return pixels.data();
  }

  static EmbeddedRouDi* roudi_;
};
EmbeddedRouDi* LiveFeedTest::roudi_ = nullptr;

TEST_F(LiveFeedTest, FramesArriveInPlaceWithTheImuThatCoversThem) {
  auto feed = openLiveFeed(feedOptions("inplace"));
  ASSERT_TRUE(feed.ok()) << feed.error().toString();
  auto driver = publisher("inplace");
  awaitConnection(*driver);

  std::vector<dataset::ImuSample> imu_log;
  std::int64_t previous_ns = 1'000'000'000;
  driver->publishImu(imuAt(previous_ns));
  imu_log.push_back(imuAt(previous_ns));
  for (int i = 0; i < 10; ++i) {
    const std::int64_t t_ns = previous_ns + kFramePeriodNs;
    const std::uint8_t* loaned = publishFrame(*driver, previous_ns, t_ns, static_cast<std::uint8_t>(i), &imu_log);
    const FeedFrame* frame = (*feed)->next();
    ASSERT_NE(frame, nullptr);
    ASSERT_TRUE(frame->ok) << frame->error;
    EXPECT_EQ(frame->t_ns, t_ns);
    EXPECT_EQ(frame->index, static_cast<std::uint64_t>(i));
    // Zero copy: tracking reads the memory the driver wrote into.
    EXPECT_EQ(frame->left.data(), loaned);
    ASSERT_EQ(frame->left.size(), static_cast<std::size_t>(kWidth * kHeight));
    EXPECT_EQ(frame->left[0], static_cast<std::uint8_t>(i));
    EXPECT_TRUE(frame->right.empty());
    // The same samples as a recording's frame would have: from the one at or before the previous frame (for the
    // first frame, kImuKeptBeforeStampNs before it) to the one at or after this one.
    const auto expected = imuCovering(imu_log, i == 0 ? t_ns - kImuKeptBeforeStampNs : previous_ns, t_ns);
    ASSERT_EQ(frame->imu.size(), expected.size()) << "frame " << i;
    for (std::size_t k = 0; k < expected.size(); ++k) {
      EXPECT_EQ(frame->imu[k].t_ns, expected[k].t_ns);
      EXPECT_EQ(frame->imu[k].gyro_s, expected[k].gyro_s);
      EXPECT_EQ(frame->imu[k].accel_s, expected[k].accel_s);
    }
    EXPECT_GT(frame->captured_steady_ns, 0);
    (*feed)->release();
    previous_ns = t_ns;
  }
  driver->publishEndOfStream();
  EXPECT_EQ((*feed)->next(), nullptr);
  EXPECT_FALSE((*feed)->faults().any());
}

TEST_F(LiveFeedTest, AThousandHertzImuReachesEveryFrameWhole) {
  auto feed = openLiveFeed(feedOptions("kilohertz"));
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("kilohertz");
  awaitConnection(*driver);
  constexpr std::int64_t kPeriodNs = 1'000'000;
  std::int64_t next_imu_ns = 0;
  for (int i = 1; i <= 20; ++i) {
    const std::int64_t t_ns = i * kFramePeriodNs;
    for (; next_imu_ns <= t_ns; next_imu_ns += kPeriodNs) driver->publishImu(imuAt(next_imu_ns));
    std::span<std::uint8_t> pixels = driver->loanFrame();
    ASSERT_FALSE(pixels.empty());
    driver->publishFrame(t_ns);
    const FeedFrame* frame = (*feed)->next();
    ASSERT_NE(frame, nullptr);
    // From the sample at the previous frame to the one at this frame: 51 samples, none missing.
    if (i > 1) {
      ASSERT_EQ(frame->imu.size(), 51U) << "frame " << i;
      EXPECT_EQ(frame->imu.front().t_ns, t_ns - kFramePeriodNs);
    }
    EXPECT_EQ(frame->imu.back().t_ns, t_ns);
    (*feed)->release();
  }
  EXPECT_FALSE((*feed)->faults().any());
}

TEST_F(LiveFeedTest, AnImuBurstLongerThanItsQueueLosesTheOldestSamplesAndCountsThem) {
  auto feed = openLiveFeed(feedOptions("burst"));
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("burst");
  awaitConnection(*driver);
  publishFrame(*driver, 0, 10 * kImuPeriodNs, 0);
  ASSERT_NE((*feed)->next(), nullptr);
  (*feed)->release();
  // 300 samples at once (a driver that was held up), while the feed is not reading: its queue keeps the newest 256.
  for (std::int64_t k = 11; k <= 310; ++k) driver->publishImu(imuAt(k * kImuPeriodNs));
  std::span<std::uint8_t> pixels = driver->loanFrame();
  ASSERT_FALSE(pixels.empty());
  driver->publishFrame(310 * kImuPeriodNs);
  const FeedFrame* frame = (*feed)->next();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->imu.back().t_ns, 310 * kImuPeriodNs);
  // Its interval starts at the previous frame, but the samples lost leave a hole that tracking sees as a gap.
  EXPECT_EQ(frame->imu.front().t_ns, 10 * kImuPeriodNs);
  EXPECT_EQ(frame->imu[1].t_ns, 55 * kImuPeriodNs);
  (*feed)->release();
  EXPECT_EQ((*feed)->faults().imu_lost, 300U - 256U);
  EXPECT_EQ((*feed)->faults().imu_out_of_order, 0U);
}

TEST_F(LiveFeedTest, AStereoPairCarriesBothImagesAndTheCalibrationsShiftMovesItsTime) {
  LiveFeedOptions options = feedOptions("stereo", /*stereo=*/true);
  options.timeshift_cam_imu_ns = 3'000'000;  // t_imu = t_cam + 3 ms
  options.use_imu = false;
  auto feed = openLiveFeed(options);
  ASSERT_TRUE(feed.ok()) << feed.error().toString();
  auto driver = publisher("stereo", 2);
  awaitConnection(*driver);
  std::span<std::uint8_t> pixels = driver->loanFrame();
  ASSERT_EQ(pixels.size(), static_cast<std::size_t>(2 * kWidth * kHeight));
  std::memset(pixels.data(), 1, pixels.size() / 2);
  std::memset(pixels.data() + pixels.size() / 2, 2, pixels.size() / 2);
  driver->publishFrame(500'000'000);
  const FeedFrame* frame = (*feed)->next();
  ASSERT_NE(frame, nullptr);
  ASSERT_TRUE(frame->ok) << frame->error;
  EXPECT_EQ(frame->t_ns, 503'000'000);
  ASSERT_EQ(frame->right.size(), frame->left.size());
  EXPECT_EQ(frame->left.back(), 1);
  EXPECT_EQ(frame->right.front(), 2);
  EXPECT_TRUE(frame->imu.empty());
  (*feed)->release();
}

TEST_F(LiveFeedTest, AFrameOfAnotherSizeIsRefusedNamingBothSizes) {
  auto feed = openLiveFeed(feedOptions("size"));
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("size", 1, kWidth + 16);
  awaitConnection(*driver);
  publishFrame(*driver, 0, kFramePeriodNs, 7);
  const FeedFrame* frame = (*feed)->next();
  ASSERT_NE(frame, nullptr);
  EXPECT_FALSE(frame->ok);
  ASSERT_NE(frame->error, nullptr);
  EXPECT_NE(std::string(frame->error).find("80x48"), std::string::npos) << frame->error;
  EXPECT_NE(std::string(frame->error).find("64x48"), std::string::npos) << frame->error;
  EXPECT_TRUE(frame->left.empty());
  (*feed)->release();
}

TEST_F(LiveFeedTest, LateRepeatedAndForeignMessagesAreDroppedAndCounted) {
  auto feed = openLiveFeed(feedOptions("faults"));
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("faults");
  // A stranger on the frames topic: too short, and of another layout.
  iox::popo::UntypedPublisher stranger(live::liveService("faults", live::kFramesEvent));
  awaitConnection(*driver);
  for (std::uint32_t bytes : {8U, 200U}) {
    auto chunk = stranger.loan(bytes);
    ASSERT_FALSE(chunk.has_error());
    std::memset(chunk.value(), 0xAB, bytes);
    stranger.publish(chunk.value());
  }
  // Published while the feed waits, so that the two-deep queue drops none of the messages before.
  std::thread later([&] {
    std::this_thread::sleep_for(milliseconds(50));
    publishFrame(*driver, 0, 2 * kFramePeriodNs, 1);
  });
  const FeedFrame* frame = (*feed)->next();
  later.join();
  ASSERT_NE(frame, nullptr);
  EXPECT_TRUE(frame->ok);
  EXPECT_EQ(frame->t_ns, 2 * kFramePeriodNs);
  (*feed)->release();
  EXPECT_EQ((*feed)->faults().messages_malformed, 2U);

  // The same time again, then an earlier one: neither comes through; the next later one does.
  publishFrame(*driver, 2 * kFramePeriodNs, 2 * kFramePeriodNs, 2);
  publishFrame(*driver, 2 * kFramePeriodNs, kFramePeriodNs, 3);
  std::thread good([&] {
    std::this_thread::sleep_for(milliseconds(50));
    publishFrame(*driver, 2 * kFramePeriodNs, 3 * kFramePeriodNs, 4);
  });
  frame = (*feed)->next();
  good.join();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->t_ns, 3 * kFramePeriodNs);
  EXPECT_EQ(frame->left[0], 4);
  (*feed)->release();
  EXPECT_EQ((*feed)->faults().frames_out_of_order, 2U);
  EXPECT_EQ((*feed)->faults().frames_lost, 0U);
}

TEST_F(LiveFeedTest, FramesThatTrackingWasTooSlowForAreCountedAsLost) {
  auto feed = openLiveFeed(feedOptions("slow"));
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("slow");
  awaitConnection(*driver);
  publishFrame(*driver, 0, kFramePeriodNs, 0);
  ASSERT_NE((*feed)->next(), nullptr);
  (*feed)->release();
  // Six frames while tracking is busy: the queue keeps the newest two.
  for (int i = 2; i <= 7; ++i) publishFrame(*driver, (i - 1) * kFramePeriodNs, i * kFramePeriodNs, 0);
  const FeedFrame* frame = (*feed)->next();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->t_ns, 6 * kFramePeriodNs);
  // The IMU was not lost with the frames: this frame's interval starts at the frame before it that was tracked.
  ASSERT_FALSE(frame->imu.empty());
  EXPECT_EQ(frame->imu.front().t_ns, kFramePeriodNs);
  EXPECT_EQ(frame->imu.back().t_ns, 6 * kFramePeriodNs);
  (*feed)->release();
  EXPECT_EQ((*feed)->faults().frames_lost, 4U);
  frame = (*feed)->next();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->t_ns, 7 * kFramePeriodNs);
  ASSERT_FALSE(frame->imu.empty());
  EXPECT_EQ(frame->imu.front().t_ns, 6 * kFramePeriodNs);
  EXPECT_EQ(frame->imu.back().t_ns, 7 * kFramePeriodNs);
  (*feed)->release();
}

TEST_F(LiveFeedTest, AFrameWaitsABoundedTimeForItsImuAndThenGoesOnWithout) {
  LiveFeedOptions options = feedOptions("imuwait");
  options.imu_wait_s = 0.05;
  auto feed = openLiveFeed(options);
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("imuwait");
  awaitConnection(*driver);
  // IMU up to 20 ms before the frame only.
  for (std::int64_t t = 0; t <= kFramePeriodNs - 20'000'000; t += kImuPeriodNs) driver->publishImu(imuAt(t));
  std::span<std::uint8_t> pixels = driver->loanFrame();
  std::memset(pixels.data(), 0, pixels.size());
  driver->publishFrame(kFramePeriodNs);
  const auto start = std::chrono::steady_clock::now();
  const FeedFrame* frame = (*feed)->next();
  const auto waited = std::chrono::steady_clock::now() - start;
  ASSERT_NE(frame, nullptr);
  EXPECT_GE(waited, milliseconds(45));
  EXPECT_EQ((*feed)->faults().imu_wait_timeouts, 1U);
  ASSERT_FALSE(frame->imu.empty());
  EXPECT_LT(frame->imu.back().t_ns, frame->t_ns);  // tracking sees the gap and predicts without the IMU
  (*feed)->release();

  // A sample that arrives while the frame waits releases it at once.
  std::thread late_imu([&] {
    std::this_thread::sleep_for(milliseconds(10));
    driver->publishImu(imuAt(2 * kFramePeriodNs));
  });
  pixels = driver->loanFrame();
  std::memset(pixels.data(), 0, pixels.size());
  driver->publishFrame(2 * kFramePeriodNs);
  frame = (*feed)->next();
  late_imu.join();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->imu.back().t_ns, 2 * kFramePeriodNs);
  EXPECT_EQ((*feed)->faults().imu_wait_timeouts, 1U);
  (*feed)->release();
}

TEST_F(LiveFeedTest, ADriverThatStartsAgainIsNoticedAndFollowed) {
  auto feed = openLiveFeed(feedOptions("restart"));
  ASSERT_TRUE(feed.ok());
  {
    auto driver = publisher("restart");
    awaitConnection(*driver);
    for (int i = 1; i <= 2; ++i) {
      publishFrame(*driver, (i - 1) * kFramePeriodNs, i * kFramePeriodNs, 0);
      const FeedFrame* first = (*feed)->next();
      ASSERT_NE(first, nullptr);
      EXPECT_FALSE(first->stream_restarted);
      (*feed)->release();
    }
  }
  // The new process counts its frames from 0 again, and its clock may start anew.
  auto driver = publisher("restart");
  awaitConnection(*driver);
  publishFrame(*driver, 0, kFramePeriodNs / 2, 5);
  const FeedFrame* frame = (*feed)->next();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->t_ns, kFramePeriodNs / 2);
  EXPECT_EQ(frame->left[0], 5);
  EXPECT_TRUE(frame->stream_restarted);
  // Its IMU is taken as new too, not as samples from the past.
  ASSERT_FALSE(frame->imu.empty());
  EXPECT_EQ(frame->imu.back().t_ns, kFramePeriodNs / 2);
  (*feed)->release();
  EXPECT_EQ((*feed)->faults().driver_restarts, 1U);
  EXPECT_EQ((*feed)->faults().imu_out_of_order, 0U);
  EXPECT_EQ((*feed)->faults().imu_wait_timeouts, 0U);
}

TEST_F(LiveFeedTest, ACameraThatStopsAndComesBackIsCountedOnce) {
  LiveFeedOptions options = feedOptions("stall");
  options.stall_after_s = 0.1;
  auto feed = openLiveFeed(options);
  ASSERT_TRUE(feed.ok());
  auto driver = publisher("stall");
  awaitConnection(*driver);
  publishFrame(*driver, 0, kFramePeriodNs, 1);
  ASSERT_NE((*feed)->next(), nullptr);
  (*feed)->release();
  std::thread later([&] {
    std::this_thread::sleep_for(milliseconds(400));
    publishFrame(*driver, kFramePeriodNs, 2 * kFramePeriodNs, 2);
  });
  const FeedFrame* frame = (*feed)->next();
  later.join();
  ASSERT_NE(frame, nullptr);
  EXPECT_EQ(frame->left[0], 2);
  (*feed)->release();
  EXPECT_EQ((*feed)->faults().stalls, 1U);
  EXPECT_EQ((*feed)->faults().frames_lost, 0U);
}

TEST_F(LiveFeedTest, AStopEndsAWaitForFramesThatNeverCome) {
  std::atomic<bool> stop{false};
  LiveFeedOptions options = feedOptions("silent");
  options.stop = &stop;
  auto feed = openLiveFeed(options);
  ASSERT_TRUE(feed.ok());
  std::thread stopper([&] {
    std::this_thread::sleep_for(milliseconds(150));
    stop.store(true);
  });
  EXPECT_EQ((*feed)->next(), nullptr);
  stopper.join();
}

TEST(LiveFeedOptions, BadValuesAreNamed) {
  LiveFeedOptions options;
  options.width = 752;
  options.height = 480;
  EXPECT_NE(options.validate().error().message().find("stream name"), std::string::npos);
  options.stream = "cam";
  options.imu_wait_s = 2.0;
  EXPECT_NE(options.validate().error().message().find("imu_wait_s"), std::string::npos);
  live::SensorPublisherOptions publisher;
  publisher.stream = "cam";
  publisher.cameras = 3;
  EXPECT_NE(publisher.validate().error().message().find("cameras"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::agent
