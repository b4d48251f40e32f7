// The loader-to-tracking ring: each side blocks on the other's event and wakes when it comes, frames arrive in
// order and whole, and closing or finishing releases whichever side is waiting.
#include "agent_rt/runtime/frame_ring.hpp"

#include <chrono>
#include <future>
#include <thread>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

using namespace std::chrono_literals;

TEST(FrameRing, ConsumerWaitsForTheFrameAndWakesWhenItIsProduced) {
  FrameRing ring(2, 4, false);
  auto consumer = std::async(std::launch::async, [&] {
    FrameRing::Slot* slot = ring.waitForFrame();
    return slot == nullptr ? std::int64_t{-1} : slot->t_ns;
  });
  EXPECT_EQ(consumer.wait_for(50ms), std::future_status::timeout) << "nothing was produced yet";
  FrameRing::Slot* slot = ring.waitForFreeSlot();
  ASSERT_NE(slot, nullptr);
  slot->t_ns = 42;
  ring.produced();
  ASSERT_EQ(consumer.wait_for(5s), std::future_status::ready);
  EXPECT_EQ(consumer.get(), 42);
}

TEST(FrameRing, ProducerWaitsForAFreeSlotAndWakesWhenOneIsConsumed) {
  FrameRing ring(2, 4, true);
  for (int i = 0; i < 2; ++i) {
    ASSERT_NE(ring.waitForFreeSlot(), nullptr);
    ring.produced();
  }
  auto producer = std::async(std::launch::async, [&] { return ring.waitForFreeSlot() != nullptr; });
  EXPECT_EQ(producer.wait_for(50ms), std::future_status::timeout) << "the ring is full";
  ASSERT_NE(ring.waitForFrame(), nullptr);
  ring.consumed();
  ASSERT_EQ(producer.wait_for(5s), std::future_status::ready);
  EXPECT_TRUE(producer.get());
}

TEST(FrameRing, CloseReleasesAWaitingProducerAndFinishEndsTheConsumerAfterTheLastFrame) {
  FrameRing full(1, 4, false);
  ASSERT_NE(full.waitForFreeSlot(), nullptr);
  full.produced();
  auto producer = std::async(std::launch::async, [&] { return full.waitForFreeSlot(); });
  EXPECT_EQ(producer.wait_for(50ms), std::future_status::timeout);
  full.close();
  ASSERT_EQ(producer.wait_for(5s), std::future_status::ready);
  EXPECT_EQ(producer.get(), nullptr) << "a closed ring gives the loader no slot";

  FrameRing ring(2, 4, false);
  ASSERT_NE(ring.waitForFreeSlot(), nullptr);
  ring.produced();
  ring.finish();
  EXPECT_NE(ring.waitForFrame(), nullptr) << "frames loaded before the end are still taken";
  ring.consumed();
  EXPECT_EQ(ring.waitForFrame(), nullptr);
}

TEST(FrameRing, TenThousandFramesPassInOrderBetweenTwoThreads) {
  constexpr int kFrames = 10000;
  FrameRing ring(3, 16, true);
  std::thread loader([&] {
    for (int i = 0; i < kFrames; ++i) {
      FrameRing::Slot* slot = ring.waitForFreeSlot();
      ASSERT_NE(slot, nullptr);
      slot->t_ns = i;
      slot->left.assign(16, static_cast<std::uint8_t>(i));
      slot->right.assign(16, static_cast<std::uint8_t>(i + 1));
      ring.produced();
    }
    ring.finish();
  });
  int next = 0;
  for (FrameRing::Slot* slot = ring.waitForFrame(); slot != nullptr; slot = ring.waitForFrame()) {
    ASSERT_EQ(slot->t_ns, next);
    ASSERT_EQ(slot->left[15], static_cast<std::uint8_t>(next));
    ASSERT_EQ(slot->right[0], static_cast<std::uint8_t>(next + 1));
    ++next;
    ring.consumed();
  }
  loader.join();
  EXPECT_EQ(next, kFrames);
}

}  // namespace
}  // namespace cvislam::agent
