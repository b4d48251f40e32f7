// The embedded RouDi with real iceoryx: a tracking thread publishes keyframe-sized messages by loaning chunks,
// a mapping thread receives them, and both see the same memory (zero copy). A second RouDi is refused with a
// message instead of an abort. Tests of this binary hold the CTest resource lock "iceoryx_roudi".
#include "agent_rt/ipc/embedded_roudi.hpp"

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <thread>
#include <type_traits>

#include <gtest/gtest.h>

#include "iceoryx_posh/popo/publisher.hpp"
#include "iceoryx_posh/popo/subscriber.hpp"

namespace cvislam::agent {
namespace {

// About the size of a keyframe with 500 ORB keypoints: positions, descriptors and map point links.
struct KeyframeSizedMessage {
  std::uint32_t sequence = 0;
  std::array<float, std::size_t{2} * 500> keypoints_px{};
  std::array<std::uint8_t, std::size_t{32} * 500> descriptors{};
  std::array<std::uint32_t, 500> map_points{};
};
static_assert(std::is_trivially_copyable_v<KeyframeSizedMessage>);

constexpr std::uint32_t kMessages = 200;

EmbeddedRouDiOptions testOptions() {
  EmbeddedRouDiOptions options;
  options.runtime_name = "cvislam_ipc_test";
  options.mempools = {{128, 100}, {sizeof(KeyframeSizedMessage), 256}};
  return options;
}

TEST(EmbeddedRouDi, KeyframesCrossThreadsZeroCopyAndInOrder) {
  auto roudi = EmbeddedRouDi::start(testOptions());
  ASSERT_TRUE(roudi.ok()) << roudi.error().toString();

  std::array<const void*, kMessages> loaned{};
  std::array<const void*, kMessages> received{};
  std::atomic<std::uint32_t> received_count{0};
  std::atomic<bool> subscribed{false};

  std::thread mapping([&] {
    iox::popo::SubscriberOptions options;
    options.queueCapacity = 256;
    iox::popo::Subscriber<KeyframeSizedMessage> subscriber({"cvislam", "agent", "keyframe"}, options);
    subscribed = true;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    std::uint32_t expected = 0;
    while (received_count < kMessages && std::chrono::steady_clock::now() < deadline) {
      subscriber.take()
          .and_then([&](auto& sample) {
            EXPECT_EQ(sample->sequence, expected);
            if (sample->sequence < kMessages) received[sample->sequence] = sample.get();
            ++expected;
            ++received_count;
          })
          .or_else([](auto&) { std::this_thread::sleep_for(std::chrono::microseconds(100)); });
    }
  });

  {
    iox::popo::Publisher<KeyframeSizedMessage> publisher({"cvislam", "agent", "keyframe"});
    while (!subscribed) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    // The subscriber's port connects asynchronously; wait until RouDi has matched it.
    const auto connect_deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while (!publisher.hasSubscribers() && std::chrono::steady_clock::now() < connect_deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    ASSERT_TRUE(publisher.hasSubscribers());
    for (std::uint32_t i = 0; i < kMessages; ++i) {
      bool published = false;
      publisher.loan()
          .and_then([&](auto& sample) {
            sample->sequence = i;
            sample->keypoints_px[0] = static_cast<float>(i);
            loaned[i] = sample.get();
            sample.publish();
            published = true;
          })
          .or_else([](auto&) {});
      ASSERT_TRUE(published) << "could not loan a chunk for message " << i;
    }
    mapping.join();
  }

  ASSERT_EQ(received_count.load(), kMessages);
  for (std::uint32_t i = 0; i < kMessages; ++i) {
    EXPECT_EQ(received[i], loaned[i]) << "message " << i << " was copied";
  }
}

TEST(EmbeddedRouDi, ASecondRouDiIsRefusedWithAMessage) {
  auto first = EmbeddedRouDi::start(testOptions());
  ASSERT_TRUE(first.ok()) << first.error().toString();
  EmbeddedRouDiOptions options = testOptions();
  options.runtime_name = "cvislam_ipc_test_2";
  auto second = EmbeddedRouDi::start(options);
  ASSERT_FALSE(second.ok());
  EXPECT_NE(second.error().message().find("another iceoryx RouDi"), std::string::npos) << second.error().message();
}

TEST(EmbeddedRouDiOptions, ValidateNamesTheBadField) {
  EmbeddedRouDiOptions options;
  EXPECT_TRUE(options.validate().ok());
  options.mempools.push_back({0, 10});
  const Status status = options.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message().find("mempools[4]"), std::string::npos) << status.error().message();
  options = {};
  options.runtime_name.clear();
  EXPECT_FALSE(options.validate().ok());
  options = {};
  options.mempools = {{1024, 10}, {128, 10}};  // decreasing: iceoryx would abort
  const Status unordered = options.validate();
  ASSERT_FALSE(unordered.ok());
  EXPECT_NE(unordered.error().message().find("increase strictly"), std::string::npos);
  options.mempools = {{121, 10}, {128, 10}};  // both round up to 128
  EXPECT_FALSE(options.validate().ok());
}

}  // namespace
}  // namespace cvislam::agent
