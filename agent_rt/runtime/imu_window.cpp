#include "agent_rt/runtime/imu_window.hpp"

#include <algorithm>

#include "agent_rt/runtime/sensor_setup.hpp"

namespace cvislam::agent {

bool ImuWindow::add(const dataset::ImuSample& sample) {
  if (!samples_.empty() && sample.t_ns <= samples_.back().t_ns) return false;
  if (samples_.size() == samples_.capacity()) {
    const std::size_t dropped = samples_.size() / 2;
    samples_.erase(samples_.begin(), samples_.begin() + static_cast<std::ptrdiff_t>(dropped));
    overflowed_ += dropped;
  }
  samples_.push_back(sample);
  return true;
}

std::span<const dataset::ImuSample> ImuWindow::covering(std::int64_t t0_ns, std::int64_t t1_ns) const {
  return imuCovering(samples_, t0_ns, t1_ns);
}

void ImuWindow::dropBefore(std::int64_t t_ns) {
  auto first_after = std::upper_bound(samples_.begin(), samples_.end(), t_ns,
                                      [](std::int64_t t, const dataset::ImuSample& s) { return t < s.t_ns; });
  if (first_after - samples_.begin() > 1) samples_.erase(samples_.begin(), first_after - 1);
}

}  // namespace cvislam::agent
