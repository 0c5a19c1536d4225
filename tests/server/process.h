// Child processes for the end-to-end tests.
#ifndef INTERSLICE_TESTS_SERVER_PROCESS_H_
#define INTERSLICE_TESTS_SERVER_PROCESS_H_

#include <sys/types.h>

#include <string>
#include <vector>

namespace interslice::testing {

struct CommandResult {
  int exit_code = -1;  // -1: killed or timed out
  std::string out;
  std::string err;
};

// Runs `argv` to completion (killed after `timeout_seconds`).
CommandResult RunCommand(const std::vector<std::string>& argv,
                         double timeout_seconds = 120);

// Starts `argv` with stdout and stderr appended to `log_path`.
pid_t StartProcess(const std::vector<std::string>& argv,
                   const std::string& log_path);
// Waits up to `timeout_seconds`; the exit code, or -1.
int WaitProcess(pid_t pid, double timeout_seconds);

std::string ReadFileOrEmpty(const std::string& path);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_SERVER_PROCESS_H_
