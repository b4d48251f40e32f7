// A wake-up between threads with a deadline: producers ring, one consumer waits until a ring it has not seen or
// its timeout. A futex on a counter: ringing costs an atomic add, and a system call only while someone waits (the
// sequentially consistent order of the counter and the waiters is what makes that safe), so
// a sensor driver's thread can ring it at IMU rate. Linux only, as the agent is.
#pragma once

#include <linux/futex.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <climits>
#include <cstdint>
#include <ctime>

namespace cvislam::agent {

class Doorbell {
 public:
  void ring() {
    count_.fetch_add(1);
    if (waiters_.load() > 0) {
      syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(&count_), FUTEX_WAKE_PRIVATE, INT_MAX, nullptr, nullptr, 0);
    }
  }
  // What a waiter has seen before it looks at the state the ring announces.
  [[nodiscard]] std::uint32_t seen() const { return count_.load(); }
  // Returns at a ring after `seen`, at the timeout, or at once when one came already.
  void waitFor(std::uint32_t seen, std::chrono::nanoseconds timeout) {
    if (timeout.count() <= 0) return;
    timespec ts{};
    ts.tv_sec = static_cast<time_t>(timeout.count() / 1'000'000'000);
    ts.tv_nsec = static_cast<long>(timeout.count() % 1'000'000'000);
    waiters_.fetch_add(1);
    syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(&count_), FUTEX_WAIT_PRIVATE, seen, &ts, nullptr, 0);
    waiters_.fetch_sub(1);
  }

 private:
  static_assert(sizeof(std::atomic<std::uint32_t>) == sizeof(std::uint32_t), "the futex word is the counter itself");
  std::atomic<std::uint32_t> count_{0};
  std::atomic<int> waiters_{0};
};

}  // namespace cvislam::agent
