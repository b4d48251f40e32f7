// Each agent thread's CPU time, for the health topic (agent_rt/live/state_topics.hpp): read from
// /proc/self/task/<tid>/stat into a buffer on the stack, so that sampling it from the tracking thread allocates
// nothing.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <string_view>

#include "agent_rt/live/state_topics.hpp"

namespace cvislam::agent {

// utime + stime [clock ticks] of a /proc/<pid>/task/<tid>/stat line; -1 when it does not have that form. The
// thread's name, in parentheses, may itself hold spaces and parentheses: fields are counted after the last ')'.
std::int64_t cpuTicksOfStatLine(std::string_view line);

class ThreadCpuClock {
 public:
  // The calling thread is `name`, one of live::kHealthThreads (any other name is ignored). Any thread may call it.
  void registerCurrentThread(std::string_view name);
  // Each registered thread's CPU since the previous call, in percent of one core; -1 for a thread that is not
  // registered, and for every thread on the first call.
  void sample(std::int64_t now_ns, double (&percent)[live::kHealthThreadCount]);

 private:
  std::array<std::atomic<std::int64_t>, live::kHealthThreadCount> tids_{};  // 0: not registered
  std::array<std::int64_t, live::kHealthThreadCount> last_ticks_{};
  std::int64_t last_ns_ = -1;
};

}  // namespace cvislam::agent
