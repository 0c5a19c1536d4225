#include "tests/server/process.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <thread>

namespace interslice::testing {
namespace {

pid_t Spawn(const std::vector<std::string>& argv, const std::string& out,
            const std::string& err, bool append) {
  const pid_t pid = fork();
  if (pid == 0) {
    const int flags = O_WRONLY | O_CREAT | (append ? O_APPEND : O_TRUNC);
    const int o = open(out.c_str(), flags, 0644);
    const int e = err == out ? o : open(err.c_str(), flags, 0644);
    dup2(o, 1);
    dup2(e, 2);
    std::vector<char*> args;
    for (const std::string& a : argv)
      args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    execv(args[0], args.data());
    _exit(127);
  }
  return pid;
}

}  // namespace

std::string ReadFileOrEmpty(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

int WaitProcess(pid_t pid, double timeout_seconds) {
  const auto end =
      std::chrono::steady_clock::now() +
      std::chrono::milliseconds(static_cast<int>(timeout_seconds * 1000));
  for (;;) {
    int status = 0;
    const pid_t r = waitpid(pid, &status, WNOHANG);
    if (r == pid) return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    if (std::chrono::steady_clock::now() > end) return -1;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

CommandResult RunCommand(const std::vector<std::string>& argv,
                         double timeout_seconds) {
  char out_name[] = "/tmp/interslice-cmd-out-XXXXXX";
  char err_name[] = "/tmp/interslice-cmd-err-XXXXXX";
  close(mkstemp(out_name));
  close(mkstemp(err_name));
  const pid_t pid = Spawn(argv, out_name, err_name, false);
  CommandResult result;
  result.exit_code = WaitProcess(pid, timeout_seconds);
  if (result.exit_code == -1) {
    kill(pid, SIGKILL);
    waitpid(pid, nullptr, 0);
  }
  result.out = ReadFileOrEmpty(out_name);
  result.err = ReadFileOrEmpty(err_name);
  unlink(out_name);
  unlink(err_name);
  return result;
}

pid_t StartProcess(const std::vector<std::string>& argv,
                   const std::string& log_path) {
  return Spawn(argv, log_path, log_path, true);
}

}  // namespace interslice::testing
