// Runs a command line through the shell and collects its exit code and output, for tests of the tools' CLIs.
#pragma once

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <string>

namespace cvislam::test {

struct CommandResult {
  int exit_code = -1;
  std::string output;  // stdout and stderr
};

// `binary` followed by `args` (shell syntax), stderr folded into stdout.
inline CommandResult runCommand(const std::string& binary, const std::string& args) {
  const std::string command = binary + " " + args + " 2>&1";
  CommandResult run;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return run;
  std::array<char, 4096> buffer{};
  while (fgets(buffer.data(), buffer.size(), pipe) != nullptr) run.output += buffer.data();
  const int status = pclose(pipe);
  run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return run;
}

}  // namespace cvislam::test
