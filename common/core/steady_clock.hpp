// Now on the steady clock [ns]: CLOCK_MONOTONIC on Linux, the same in every process of the machine, so one process
// can stamp a message and another measure its latency from that stamp.
#pragma once

#include <time.h>

#include <chrono>
#include <cstdint>

namespace cvislam {

inline std::int64_t steadyNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

// Seconds on the steady clock since `start`.
inline double secondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// The calling thread's CPU time [ms]. On a loaded machine a step's wall time is mostly the scheduler's; this tells
// the work the thread did apart from the time it waited for a core or a lock.
inline double threadCpuMs() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) * 1e3 + static_cast<double>(t.tv_nsec) * 1e-6;
}

}  // namespace cvislam
