// A program the test starts as its own process (a server, an agent, iox-roudi), its output into a log file.
// The destructor kills what is still running, so a failing test leaves nothing behind.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <filesystem>
#include <optional>
#include <string>
#include <thread>
#include <vector>

namespace cvislam::test {

class ChildProcess {
 public:
  // Starts `argv[0]` with `argv`, stdout and stderr into `log`. Throws nothing: check running().
  ChildProcess(const std::vector<std::string>& argv, const std::filesystem::path& log);
  ~ChildProcess();
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  [[nodiscard]] bool running();
  void signal(int signal_number);
  // Waits for the exit: its status (exit code, or 128 + signal), or nothing on timeout.
  std::optional<int> wait(std::chrono::milliseconds timeout);
  [[nodiscard]] pid_t pid() const { return pid_; }
  [[nodiscard]] const std::filesystem::path& log() const { return log_; }

 private:
  pid_t pid_ = -1;
  std::optional<int> status_;
  std::filesystem::path log_;
};

// Waits until `predicate` holds or `timeout` passes; returns whether it held.
template <typename P>
bool waitFor(P&& predicate, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (!predicate()) {
    if (std::chrono::steady_clock::now() > deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return true;
}

// A free TCP port on 127.0.0.1 at the time of asking.
int freeLoopbackPort();

}  // namespace cvislam::test
