#include "agent_rt/runtime/thread_schedule.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <thread>

namespace cvislam::agent {

Status ThreadSchedule::validate(const std::string& name) const {
  const auto bad = [&](const std::string& what) {
    return Error{ErrorCode::kInvalidArgument, "threads." + name + ": " + what};
  };
  if (nice < -20 || nice > 19) return bad("nice = " + std::to_string(nice) + " must be in [-20, 19]");
  if (realtime_priority < 0 || realtime_priority > 99) {
    return bad("realtime_priority = " + std::to_string(realtime_priority) + " must be in [0, 99] (0 = off)");
  }
  const int online = static_cast<int>(std::thread::hardware_concurrency());
  for (int cpu : cpus) {
    if (cpu < 0 || cpu >= CPU_SETSIZE) return bad("cpu " + std::to_string(cpu) + " is not a CPU number");
    if (online > 0 && cpu >= online) {
      return bad("cpu " + std::to_string(cpu) + " does not exist here (CPUs 0-" + std::to_string(online - 1) + ")");
    }
  }
  return Status::Ok();
}

Status ThreadScheduleOptions::validate() const {
  for (const auto& [name, schedule] :
       {std::pair{"tracking", &tracking}, std::pair{"loader", &loader}, std::pair{"mapping", &mapping},
        std::pair{"link", &link}, std::pair{"propagation", &propagation}}) {
    if (Status s = schedule->validate(name); !s.ok()) return s;
  }
  return Status::Ok();
}

ThreadScheduleOptions ThreadScheduleOptions::resolved(bool tracking_realtime, int process_nice) const {
  ThreadScheduleOptions out = *this;
  if (tracking_realtime && tracking.realtime_priority > 0 && !lower_others_with_realtime) {
    for (ThreadSchedule* other : {&out.loader, &out.mapping, &out.link}) other->nice = process_nice;
  }
  return out;
}

int currentNice() {
  errno = 0;
  const int nice = getpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)));
  return errno == 0 ? nice : 0;
}

bool mayTakeRealtimePriority(int priority) {
  if (priority <= 0) return false;
  int policy = SCHED_OTHER;
  sched_param before{};
  if (pthread_getschedparam(pthread_self(), &policy, &before) != 0) return false;
  sched_param param{};
  param.sched_priority = priority;
  if (pthread_setschedparam(pthread_self(), SCHED_FIFO, &param) != 0) return false;
  (void)pthread_setschedparam(pthread_self(), policy, &before);
  return true;
}

ScheduleOutcome applyToThisThread(const ThreadSchedule& schedule) {
  ScheduleOutcome outcome;
  const auto refused = [&](const std::string& what) {
    outcome.applied = false;
    if (!outcome.note.empty()) outcome.note += "; ";
    outcome.note += what;
  };
  if (!schedule.cpus.empty()) {
    cpu_set_t set;
    CPU_ZERO(&set);
    for (int cpu : schedule.cpus) CPU_SET(cpu, &set);
    if (int e = pthread_setaffinity_np(pthread_self(), sizeof(set), &set); e != 0) {
      refused(std::string("CPU affinity refused (") + std::strerror(e) + ")");
    }
  }
  // The nice value is per thread on Linux (setpriority on the thread id); threads this one starts inherit it.
  const auto tid = static_cast<id_t>(syscall(SYS_gettid));
  errno = 0;
  const int current = getpriority(PRIO_PROCESS, tid);
  if (errno == 0 && current != schedule.nice && setpriority(PRIO_PROCESS, tid, schedule.nice) != 0) {
    refused("nice " + std::to_string(schedule.nice) + " refused (" + std::strerror(errno) +
            (schedule.nice < current ? ": a lower nice value needs CAP_SYS_NICE or RLIMIT_NICE)" : ")"));
  }
  if (schedule.realtime_priority == 0) {
    int policy = SCHED_OTHER;
    sched_param current_param{};
    if (pthread_getschedparam(pthread_self(), &policy, &current_param) == 0 && policy != SCHED_OTHER) {
      sched_param other{};
      if (int e = pthread_setschedparam(pthread_self(), SCHED_OTHER, &other); e != 0) {
        refused(std::string("leaving the inherited real-time policy refused (") + std::strerror(e) + ")");
      }
    }
  } else {
    sched_param param{};
    param.sched_priority = schedule.realtime_priority;
    if (int e = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param); e != 0) {
      refused("SCHED_FIFO priority " + std::to_string(schedule.realtime_priority) + " refused (" + std::strerror(e) +
              (e == EPERM
                   ? ": grant CAP_SYS_NICE or an rtprio limit, e.g. ulimit -r 99); it runs SCHED_OTHER at nice " +
                         std::to_string(schedule.nice)
                   : ")"));
    }
  }
  return outcome;
}

static_assert(sizeof(cpu_set_t) <= 128, "ThreadScheduleRestorer keeps a cpu_set_t in 128 bytes");

ThreadScheduleRestorer::ThreadScheduleRestorer() {
  sched_param param{};
  if (pthread_getschedparam(pthread_self(), &policy_, &param) == 0) {
    priority_ = param.sched_priority;
  } else {
    policy_ = SCHED_OTHER;
  }
  errno = 0;
  nice_ = getpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)));
  if (errno != 0) nice_ = 0;
  cpu_set_t set;
  CPU_ZERO(&set);
  have_cpus_ = pthread_getaffinity_np(pthread_self(), sizeof(set), &set) == 0;
  std::memcpy(cpus_, &set, sizeof(set));
}

ThreadScheduleRestorer::~ThreadScheduleRestorer() {
  sched_param param{};
  param.sched_priority = priority_;
  (void)pthread_setschedparam(pthread_self(), policy_, &param);
  (void)setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), nice_);
  if (have_cpus_) {
    cpu_set_t set;
    std::memcpy(&set, cpus_, sizeof(set));
    (void)pthread_setaffinity_np(pthread_self(), sizeof(set), &set);
  }
}

Result<std::vector<int>> parseCpuList(const std::string& text) {
  std::vector<int> cpus;
  std::size_t i = 0;
  const auto bad = [&] {
    return Error{ErrorCode::kInvalidArgument, "CPU list '" + text + "': use numbers and ranges, e.g. 0,2-3"};
  };
  const auto number = [&](int& out) {
    const std::size_t start = i;
    out = 0;
    while (i < text.size() && text[i] >= '0' && text[i] <= '9' && i - start < 5) out = out * 10 + (text[i++] - '0');
    return i > start;
  };
  while (i < text.size()) {
    int first = 0;
    if (!number(first)) return bad();
    int last = first;
    if (i < text.size() && text[i] == '-') {
      ++i;
      if (!number(last) || last < first) return bad();
    }
    for (int c = first; c <= last; ++c) cpus.push_back(c);
    if (i < text.size()) {
      if (text[i] != ',') return bad();
      ++i;
      if (i == text.size()) return bad();
    }
  }
  return cpus;
}

}  // namespace cvislam::agent
