// UplinkPacer with a stepped clock: the window before any acknowledgement, the rate measured from acknowledgements
// (and not inflated when they arrive bunched together), batches kept within the window, a reconnection that clears
// what was in flight, and the rate forgotten after its memory.
#include "agent_rt/link/uplink_pacer.hpp"

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

using Clock = UplinkPacer::Clock;
using std::chrono::milliseconds;

constexpr std::size_t kKiB = 1024;

class UplinkPacerTest : public ::testing::Test {
 protected:
  UplinkPacerOptions options;
  Clock::time_point t0 = Clock::now();
};

TEST_F(UplinkPacerTest, BeforeAnyAcknowledgementTheInitialWindowBoundsWhatGoes) {
  UplinkPacer sut(options);

  ASSERT_TRUE(sut.maySend());
  EXPECT_EQ(sut.batchBudget(512 * kKiB), 64 * kKiB);
  sut.onSent(1, 40 * kKiB, t0);
  EXPECT_TRUE(sut.maySend());
  EXPECT_EQ(sut.batchBudget(512 * kKiB), 24 * kKiB);
  sut.onSent(2, 30 * kKiB, t0);

  EXPECT_FALSE(sut.maySend());
  EXPECT_EQ(sut.inFlightBytes(), 70 * kKiB);
}

// A 0.5 Mbit/s link (62.5 kB/s): 125 kB sent at once come back acknowledged 2 s later. The window becomes two
// seconds of that rate, 125 kB.
TEST_F(UplinkPacerTest, TheWindowIsTwoSecondsAtTheRateTheAcknowledgementsShow) {
  UplinkPacer sut(options);
  sut.onSent(1, 62'500, t0);
  sut.onSent(2, 62'500, t0);
  sut.onAck(1, t0 + milliseconds(1000));
  sut.onAck(2, t0 + milliseconds(2000));

  EXPECT_NEAR(sut.rateBytesPerS(), 62'500.0, 1.0);
  EXPECT_EQ(sut.windowBytes(), 125'000U);
  EXPECT_EQ(sut.inFlightBytes(), 0U);

  // A faster link: 1 MB acknowledged 0.5 s after it went.
  sut.onSent(3, 1'000'000, t0 + milliseconds(3000));
  sut.onAck(3, t0 + milliseconds(3500));
  EXPECT_NEAR(sut.rateBytesPerS(), 2e6, 1.0);
  EXPECT_EQ(sut.windowBytes(), 4'000'000U);
}

// Two acknowledgements read in the same pass (1 ms apart) measure the time since their batches went, not the
// millisecond between them.
TEST_F(UplinkPacerTest, AcknowledgementsArrivingBunchedDoNotLookLikeAFastLink) {
  UplinkPacer sut(options);
  sut.onSent(1, 50'000, t0);
  sut.onSent(2, 50'000, t0 + milliseconds(200));
  sut.onAck(1, t0 + milliseconds(1000));
  sut.onAck(2, t0 + milliseconds(1001));

  EXPECT_LT(sut.rateBytesPerS(), 150'000.0);
}

// After a reconnection nothing is in flight and the window starts over: the stream may have broken because the
// link became slower than measured.
TEST_F(UplinkPacerTest, AReconnectionClearsWhatWasInFlightAndStartsTheWindowOver) {
  UplinkPacer sut(options);
  sut.onSent(1, 1'000'000, t0);
  sut.onAck(1, t0 + milliseconds(1000));
  ASSERT_EQ(sut.windowBytes(), 2'000'000U);
  sut.onSent(2, 3'000'000, t0 + milliseconds(1100));
  ASSERT_FALSE(sut.maySend());

  sut.onReconnect();

  EXPECT_TRUE(sut.maySend());
  EXPECT_EQ(sut.inFlightBytes(), 0U);
  EXPECT_EQ(sut.rateBytesPerS(), 0.0);
  EXPECT_EQ(sut.windowBytes(), options.initial_window_bytes);
  sut.onAck(2, t0 + milliseconds(2000));  // an answer of the old stream changes nothing
  EXPECT_EQ(sut.rateBytesPerS(), 0.0);
}

TEST_F(UplinkPacerTest, AFastSampleIsForgottenAfterTheRateMemory) {
  options.rate_memory_s = 5.0;
  UplinkPacer sut(options);
  sut.onSent(1, 1'000'000, t0);
  sut.onAck(1, t0 + milliseconds(500));  // 2 MB/s
  sut.onSent(2, 50'000, t0 + milliseconds(6000));
  sut.onAck(2, t0 + milliseconds(7000));  // 50 kB/s, 6.5 s later

  EXPECT_NEAR(sut.rateBytesPerS(), 50'000.0, 1.0);
}

TEST_F(UplinkPacerTest, OptionsOutOfOrderAreRefused) {
  options.initial_window_bytes = 16 * kKiB;  // below the minimum
  EXPECT_FALSE(options.validate().ok());
  options = UplinkPacerOptions{};
  options.window_s = 0.0;
  EXPECT_FALSE(options.validate().ok());
  EXPECT_TRUE(UplinkPacerOptions{}.validate().ok());
}

}  // namespace
}  // namespace cvislam::agent
