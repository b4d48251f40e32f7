// How each of the agent's threads is scheduled, so that tracking runs first on a board with one free core.
//
// Linux lets any process lower a thread's priority (a higher nice value) but raising one (a negative nice
// value, or a real-time SCHED_FIFO priority) needs CAP_SYS_NICE or an rtprio/nice rlimit. So tracking asks for
// SCHED_FIFO priority 10. With it, tracking preempts every ordinary thread on the machine and the others keep
// the process's nice value: lowering them too would only make the agent's mapping lose to every other program
// on the board (a planner, a driver, a test running beside it). Where the process may not take the real-time
// priority, tracking stays SCHED_OTHER and mapping, the link and the frame loader drop to positive nice values
// (mapping 10: CFS weights 1024 against 110), which needs no privilege; the agent says so once, naming what to
// grant. On one core at the sensor rate, nice values alone left tracking's p99 at 1.6x its p99 with mapping on
// another core, SCHED_FIFO at 1.3x (docs/agent.md, "On a small board").
//
// The agent applies these at --pace realtime only: with no sensor clock (fast, sync) tracking has no deadline
// to protect, and starving mapping there only costs accuracy.
#pragma once

#include <string>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::agent {

struct ThreadSchedule {
  int nice = 0;               // -20 to 19; below the process's own value needs CAP_SYS_NICE
  int realtime_priority = 0;  // SCHED_FIFO 1-99; 0 = SCHED_OTHER at `nice`
  std::vector<int> cpus;      // CPU affinity; empty = any CPU

  [[nodiscard]] Status validate(const std::string& name) const;
};

struct ThreadScheduleOptions {
  ThreadSchedule tracking{0, 10, {}};
  // The others' nice values apply when tracking runs without a real-time priority (refused, or 0), unless
  // lower_others_with_realtime; their CPUs and real-time priorities always apply.
  ThreadSchedule loader{2, 0, {}};  // decodes the dataset's images ahead of tracking (a camera driver's place)
  ThreadSchedule mapping{10, 0, {}};
  ThreadSchedule link{5, 0, {}};
  // Carries the IMU into the state between frames (live runs): above tracking, since it needs microseconds per
  // sample and its latency is its purpose. Its nice value is never lowered.
  ThreadSchedule propagation{0, 11, {}};
  bool lower_others_with_realtime = false;
  bool enabled = true;  // false: every thread keeps the scheduling it was started with

  [[nodiscard]] Status validate() const;
  // The schedules to apply, given whether tracking may take its real-time priority: without
  // lower_others_with_realtime, real-time tracking leaves loader, mapping and link at `process_nice`.
  [[nodiscard]] ThreadScheduleOptions resolved(bool tracking_realtime, int process_nice) const;
};

// What applying a schedule to the calling thread did.
struct ScheduleOutcome {
  bool applied = true;  // everything asked for took effect
  std::string note;     // what did not, and why; empty when applied
};

// Applies `schedule` to the calling thread; realtime_priority 0 also puts a thread that inherited a real-time
// policy back to SCHED_OTHER. Never fails the caller: what the process may not do is left out
// and described in the outcome (the thread then runs at the scheduling it had, or at `nice` when only the
// real-time priority was refused).
ScheduleOutcome applyToThisThread(const ThreadSchedule& schedule);

// The calling thread's policy, priority, nice value and CPUs while it lives, restored when it goes: runAgent()
// gives its calling thread tracking's schedule only for the run.
class ThreadScheduleRestorer {
 public:
  ThreadScheduleRestorer();
  ~ThreadScheduleRestorer();
  ThreadScheduleRestorer(const ThreadScheduleRestorer&) = delete;
  ThreadScheduleRestorer& operator=(const ThreadScheduleRestorer&) = delete;

 private:
  int policy_ = 0;
  int priority_ = 0;
  int nice_ = 0;
  bool have_cpus_ = false;
  unsigned char cpus_[128] = {};  // a cpu_set_t, kept opaque to keep <sched.h> out of this header
};

// Whether the calling thread may take SCHED_FIFO at `priority` (tried, then undone).
bool mayTakeRealtimePriority(int priority);
// The calling thread's nice value.
int currentNice();

// Parses "0,2-3" into {0, 2, 3}; names the bad part.
Result<std::vector<int>> parseCpuList(const std::string& text);

}  // namespace cvislam::agent
