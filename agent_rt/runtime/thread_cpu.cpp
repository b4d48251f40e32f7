#include "agent_rt/runtime/thread_cpu.hpp"

#include <fcntl.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>

namespace cvislam::agent {

std::int64_t cpuTicksOfStatLine(std::string_view line) {
  const std::size_t close = line.rfind(')');
  if (close == std::string_view::npos) return -1;
  // After the name: field 3 (state) ... field 14 (utime), field 15 (stime).
  std::string_view rest = line.substr(close + 1);
  std::int64_t values[2] = {-1, -1};
  int field = 2;
  std::size_t i = 0;
  while (i < rest.size() && field < 15) {
    while (i < rest.size() && rest[i] == ' ') ++i;
    if (i == rest.size()) break;
    ++field;
    const std::size_t start = i;
    while (i < rest.size() && rest[i] != ' ' && rest[i] != '\n') ++i;
    if (field == 14 || field == 15) {
      std::int64_t v = 0;
      for (std::size_t k = start; k < i; ++k) {
        if (rest[k] < '0' || rest[k] > '9') return -1;
        v = v * 10 + (rest[k] - '0');
      }
      if (i == start) return -1;
      values[field - 14] = v;
    }
  }
  if (values[0] < 0 || values[1] < 0) return -1;
  return values[0] + values[1];
}

namespace {

std::int64_t readTicks(std::int64_t tid) {
  char path[64];
  std::snprintf(path, sizeof(path), "/proc/self/task/%lld/stat", static_cast<long long>(tid));
  const int fd = ::open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) return -1;  // the thread has ended
  char buffer[1024];
  const ssize_t n = ::read(fd, buffer, sizeof(buffer) - 1);
  ::close(fd);
  if (n <= 0) return -1;
  return cpuTicksOfStatLine(std::string_view(buffer, static_cast<std::size_t>(n)));
}

}  // namespace

void ThreadCpuClock::registerCurrentThread(std::string_view name) {
  for (std::uint32_t i = 0; i < live::kHealthThreadCount; ++i) {
    if (name == live::kHealthThreads[i]) tids_[i].store(static_cast<std::int64_t>(::syscall(SYS_gettid)));
  }
}

void ThreadCpuClock::sample(std::int64_t now_ns, double (&percent)[live::kHealthThreadCount]) {
  static const double ticks_per_s = static_cast<double>(::sysconf(_SC_CLK_TCK));
  const double interval_s = last_ns_ < 0 ? 0.0 : static_cast<double>(now_ns - last_ns_) * 1e-9;
  for (std::uint32_t i = 0; i < live::kHealthThreadCount; ++i) {
    const std::int64_t tid = tids_[i].load();
    const std::int64_t ticks = tid == 0 ? -1 : readTicks(tid);
    percent[i] = -1.0;
    if (ticks >= 0 && last_ticks_[i] >= 0 && interval_s > 0.0) {
      percent[i] = 100.0 * static_cast<double>(ticks - last_ticks_[i]) / ticks_per_s / interval_s;
    }
    last_ticks_[i] = ticks;
  }
  last_ns_ = now_ns;
}

}  // namespace cvislam::agent
