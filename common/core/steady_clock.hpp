// Now on the steady clock [ns]: CLOCK_MONOTONIC on Linux, the same in every process of the machine, so one process
// can stamp a message and another measure its latency from that stamp.
#pragma once

#include <chrono>
#include <cstdint>

namespace cvislam {

inline std::int64_t steadyNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

}  // namespace cvislam
