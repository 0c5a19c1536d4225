#include "tests/testing/process.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <mutex>
#include <set>
#include <sstream>
#include <thread>

namespace interslice::testing {
namespace {

// fork + execv with stdin from /dev/null and stdout/stderr to files. The
// child gets SIGKILL when the thread that started it ends (PR_SET_PDEATHSIG):
// a test binary killed by ctest's timeout leaves no server behind holding
// ports and cores for the tests after it.
pid_t Spawn(const std::vector<std::string>& argv, const std::string& out,
            const std::string& err, bool append) {
  std::vector<char*> args;
  for (const std::string& a : argv) {
    args.push_back(const_cast<char*>(a.c_str()));
  }
  args.push_back(nullptr);
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(127);  // the parent already ended
    const int flags = O_WRONLY | O_CREAT | (append ? O_APPEND : O_TRUNC);
    const int in = ::open("/dev/null", O_RDONLY);
    const int o = ::open(out.c_str(), flags, 0644);
    const int e = err == out ? o : ::open(err.c_str(), flags, 0644);
    if (in < 0 || o < 0 || e < 0) ::_exit(127);
    ::dup2(in, 0);
    ::dup2(o, 1);
    ::dup2(e, 2);
    ::execv(args[0], args.data());
    // Only async-signal-safe calls between fork and exec (the test process
    // has threads): write(2), not stdio.
    constexpr char kFailed[] = "cannot execute: ";
    (void)!::write(2, kFailed, sizeof(kFailed) - 1);
    (void)!::write(2, args[0], std::strlen(args[0]));
    (void)!::write(2, "\n", 1);
    ::_exit(127);
  }
  return pid;
}

std::string TempFile(const char* what) {
  std::string name = std::string("/tmp/interslice-") + what + "-XXXXXX";
  const int fd = ::mkstemp(name.data());
  if (fd >= 0) ::close(fd);
  return name;
}

CommandResult Run(const std::vector<std::string>& argv, bool merge,
                  double timeout_seconds) {
  const std::string out = TempFile("out");
  const std::string err = merge ? out : TempFile("err");
  const pid_t pid = Spawn(argv, out, err, false);
  CommandResult result;
  result.exit_code = WaitProcess(pid, timeout_seconds);
  if (result.exit_code == -1 && ::waitpid(pid, nullptr, WNOHANG) == 0) {
    result.timed_out = true;
    ::kill(pid, SIGKILL);
    ::waitpid(pid, nullptr, 0);
  }
  result.out = ReadFileOrEmpty(out);
  if (!merge) result.err = ReadFileOrEmpty(err);
  if (result.timed_out) {
    result.err += "\n[killed: still running after " +
                  std::to_string(timeout_seconds) + " s]\n";
  }
  ::unlink(out.c_str());
  if (!merge) ::unlink(err.c_str());
  return result;
}

}  // namespace

std::string ReadFileOrEmpty(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

int WaitProcess(pid_t pid, double timeout_seconds) {
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::duration<double>(timeout_seconds);
  for (;;) {
    int status = 0;
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid) return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    if (r < 0) return -1;  // not our child (already reaped)
    if (std::chrono::steady_clock::now() >= end) return -1;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

int StopProcess(pid_t pid, double timeout_seconds) {
  if (pid <= 0) return -1;
  ::kill(pid, SIGTERM);
  const int rc = WaitProcess(pid, timeout_seconds);
  if (rc == -1 && ::waitpid(pid, nullptr, WNOHANG) == 0) {
    ::kill(pid, SIGKILL);
    ::waitpid(pid, nullptr, 0);
  }
  return rc;
}

CommandResult RunCommand(const std::vector<std::string>& argv,
                         double timeout_seconds) {
  return Run(argv, /*merge=*/false, timeout_seconds);
}

CommandResult RunShell(const std::string& command_line,
                       double timeout_seconds) {
  return Run({"/bin/sh", "-c", command_line}, /*merge=*/true, timeout_seconds);
}

pid_t StartProcess(const std::vector<std::string>& argv,
                   const std::string& log_path) {
  return Spawn(argv, log_path, log_path, true);
}

int FreeTcpPort() {
  // The kernel may give bind(port 0) the same port twice in a row once the
  // first socket is closed: remember what this process handed out, so two
  // ports asked for together (Orthanc's HTTP and DICOM ports) differ. CI saw
  // Orthanc refuse to start with both on one port.
  static std::mutex mutex;
  static std::set<int> handed_out;
  std::lock_guard<std::mutex> lock(mutex);
  for (int attempt = 0; attempt < 64; ++attempt) {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    if (fd < 0) return 0;
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    addr.sin_port = 0;
    socklen_t len = sizeof(addr);
    int port = 0;
    if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0 &&
        ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0) {
      port = ntohs(addr.sin_port);
    }
    ::close(fd);
    if (port == 0) return 0;
    if (handed_out.insert(port).second) return port;
  }
  return 0;
}

std::vector<std::string> Cat(std::vector<std::string> a,
                             const std::vector<std::string>& b) {
  a.insert(a.end(), b.begin(), b.end());
  return a;
}

}  // namespace interslice::testing
