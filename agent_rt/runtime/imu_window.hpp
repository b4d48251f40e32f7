// The IMU samples a frame feed keeps between frames, as they arrive from a driver: in time order, from the one at
// or before the newest handed-over frame, so that each frame gets exactly the samples a recording would give it
// (imuCovering). Fixed memory, allocation-free after construction; what it must drop is counted.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "common/dataset/types.hpp"

namespace cvislam::agent {

class ImuWindow {
 public:
  explicit ImuWindow(std::size_t capacity) { samples_.reserve(capacity); }

  // False (and nothing kept) when the sample is not later than the newest one.
  bool add(const dataset::ImuSample& sample);
  // Forgets every sample (a driver that started again).
  void clear() { samples_.clear(); }
  // A sample at or after t_ns has arrived.
  [[nodiscard]] bool covers(std::int64_t t_ns) const { return !samples_.empty() && samples_.back().t_ns >= t_ns; }
  // From the last sample at or before t0_ns to the first at or after t1_ns (as imuCovering).
  [[nodiscard]] std::span<const dataset::ImuSample> covering(std::int64_t t0_ns, std::int64_t t1_ns) const;
  // Keeps the last sample at or before t_ns (the start of the next frame's interval) and what follows it.
  void dropBefore(std::int64_t t_ns);
  // Samples dropped because the window was full (no frame came to use them).
  [[nodiscard]] std::uint64_t overflowed() const { return overflowed_; }

 private:
  std::vector<dataset::ImuSample> samples_;
  std::uint64_t overflowed_ = 0;
};

}  // namespace cvislam::agent
