// The health topic's CPU per thread: the /proc stat line parsed after the thread's name (which may hold spaces and
// parentheses), and the clock's figures for a thread that works, one that is not registered, and the first call.
#include "agent_rt/runtime/thread_cpu.hpp"

#include <atomic>
#include <chrono>
#include <thread>

#include <gtest/gtest.h>

#include "common/core/steady_clock.hpp"
#include "test/support/malloc_counter.hpp"

namespace cvislam::agent {
namespace {

TEST(ThreadCpu, TheStatLineIsReadAfterTheName) {
  // Fields 14 and 15 (utime 250, stime 17) of a line whose name holds a space and a parenthesis.
  const char* line =
      "4242 (cvislam agent)) S 1 4242 4242 0 -1 4194368 5102 0 0 0 250 17 0 0 20 0 9 0 123 456789 1234 "
      "18446744073709551615\n";
  EXPECT_EQ(cpuTicksOfStatLine(line), 267);
  EXPECT_EQ(cpuTicksOfStatLine("4242 (x) S 1 2 3"), -1);                       // too short
  EXPECT_EQ(cpuTicksOfStatLine("no name here"), -1);                           // no ')'
  EXPECT_EQ(cpuTicksOfStatLine("1 (x) S 1 1 1 0 -1 0 0 0 0 0 2x 1 0\n"), -1);  // not a number
}

TEST(ThreadCpu, AWorkingThreadShowsAndAnAbsentOneDoesNot) {
  ThreadCpuClock clock;
  std::atomic<bool> registered{false};
  std::atomic<bool> stop{false};
  std::thread mapping([&] {
    clock.registerCurrentThread("mapping");
    registered.store(true);
    volatile double sink = 0.0;
    while (!stop.load()) sink = sink + 1.0;  // works until told
  });
  while (!registered.load()) std::this_thread::yield();
  double percent[live::kHealthThreadCount];
  clock.sample(steadyNowNs(), percent);
  for (double p : percent) EXPECT_EQ(p, -1.0);  // the first call has no interval
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  clock.sample(steadyNowNs(), percent);
  stop.store(true);
  mapping.join();
  EXPECT_GT(percent[1], 0.0);    // mapping: it ran
  EXPECT_LE(percent[1], 110.0);  // one thread, one core at most (10 ms ticks round the figure)
  EXPECT_EQ(percent[0], -1.0);   // tracking: never registered
  EXPECT_EQ(percent[4], -1.0);
}

// The tracking thread samples it once a second: that must not allocate (this binary counts every malloc).
TEST(ThreadCpu, SamplingAllocatesNothing) {
  ThreadCpuClock clock;
  clock.registerCurrentThread("tracking");
  double percent[live::kHealthThreadCount];
  const std::int64_t start_ns = steadyNowNs();
  clock.sample(start_ns, percent);  // the first call sets the clock tick rate up
  const long before = test::mallocCount();
  for (int i = 1; i <= 100; ++i) clock.sample(start_ns + i * 1'000'000'000LL, percent);
  EXPECT_EQ(test::mallocCount() - before, 0);
  EXPECT_GE(percent[0], 0.0);  // this thread's figure was read
}

}  // namespace
}  // namespace cvislam::agent
