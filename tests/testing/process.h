// Child processes for the tests: run a binary to completion and capture what
// it printed, start one in the background, stop it, and pick a free port.
//
// Every wait here is bounded: a child that outlives its timeout is killed
// (SIGKILL) and reaped, and the result says so (exit_code -1), so a hung
// binary fails its test with its output instead of hanging the suite.
#ifndef INTERSLICE_TESTS_TESTING_PROCESS_H_
#define INTERSLICE_TESTS_TESTING_PROCESS_H_

#include <sys/types.h>

#include <string>
#include <vector>

namespace interslice::testing {

struct CommandResult {
  // The exit status; -1 when the process was killed by a signal or did not
  // finish within its timeout (then `timed_out` is true).
  int exit_code = -1;
  bool timed_out = false;
  std::string out;  // standard output (with RunShell: stdout and stderr)
  std::string err;  // standard error
};

// Runs argv[0] (a path; no PATH lookup) with `argv` to completion; kills it
// after `timeout_seconds`. Standard input is /dev/null.
CommandResult RunCommand(const std::vector<std::string>& argv,
                         double timeout_seconds = 120);

// Runs `command_line` with /bin/sh -c (so PATH lookup, quoting and
// redirections apply), stdout and stderr interleaved in `out` as a terminal
// would show them; killed after `timeout_seconds`.
CommandResult RunShell(const std::string& command_line,
                       double timeout_seconds = 900);

// Starts `argv` in the background with stdout and stderr appended to
// `log_path`; its pid (the caller reaps it: WaitProcess or StopProcess).
// The child is killed when the thread that started it ends (so a test binary
// killed by its ctest timeout leaves no server behind): start background
// processes from the test's own thread, not from a short-lived one.
pid_t StartProcess(const std::vector<std::string>& argv,
                   const std::string& log_path);

// Waits up to `timeout_seconds` (0: just looks) for `pid` to end and reaps
// it; its exit code, or -1 while it still runs (or when a signal ended it).
int WaitProcess(pid_t pid, double timeout_seconds);

// SIGTERM, then waits up to `timeout_seconds`; if the process is still
// there, SIGKILL and reap. The exit code after SIGTERM, or -1 when it had to
// be killed.
int StopProcess(pid_t pid, double timeout_seconds);

// The whole file, or "" when it cannot be read.
std::string ReadFileOrEmpty(const std::string& path);

// A TCP port on 127.0.0.1 that nobody listens on right now (bound to port 0
// and released), never one this process was given before. Another process may
// take it before the caller binds it:
// prefer letting the program bind port 0 and report its port (the server's
// --port-file) where it can.
int FreeTcpPort();

// `a` followed by `b`: argument lists built from parts.
std::vector<std::string> Cat(std::vector<std::string> a,
                             const std::vector<std::string>& b);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_PROCESS_H_
