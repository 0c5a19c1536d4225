// An interslice-server process for the end-to-end tests: started on free
// loopback ports, ready when its health check answers, stopped with SIGTERM
// and reaped.
//
//   ServerProcess server({.spool = dir / "spool",
//                         .extra = {"--dicom-listen", "127.0.0.1:0"}});
//   ASSERT_TRUE(server.Start());  // on failure: why, and the log's end
//   RunCommand(Cat({kCli, "submit", ...}, server.ServerFlag()));
//   EXPECT_EQ(server.Stop(), 0) << server.Log();  // or let it go out of scope
//
// Start() passes --listen (default 127.0.0.1:0, so the kernel picks a free
// port: no race with other tests) and --port-file, then polls until the port
// file names the ports (the server writes it once its listeners are up and
// its health is SERVING) and a grpc.health.v1 Check answers SERVING, with a
// deadline. The destructor stops a running server with SIGTERM, as an
// operator would, and EXPECTs exit code 0: the server leaves through main, so
// an instrumented build runs its exit-time leak check and a sanitizer report
// (exit code 86, scripts/test-sanitizers.sh) fails the test.
#ifndef INTERSLICE_TESTS_TESTING_SERVER_PROCESS_H_
#define INTERSLICE_TESTS_TESTING_SERVER_PROCESS_H_

#include <sys/types.h>

#include <string>
#include <vector>

#include "gtest/gtest.h"

namespace interslice::testing {

struct ServerOptions {
  // The server binary; default: the build tree's interslice-server
  // (ServerPath(), tests/testing/paths.h).
  std::string binary;
  // --spool: where the server keeps its jobs (created by the server).
  // Required.
  std::string spool;
  // Where stdout and stderr go (appended across restarts). Default:
  // "<spool>.log".
  std::string log;
  // --listen. A fixed "127.0.0.1:<FreeTcpPort()>" for servers that must know
  // their address before they start (replicas advertise it).
  std::string listen = "127.0.0.1:0";
  // A command the server is started under (its argv is appended), e.g.
  // unshare(1) to give it a mount namespace of its own. It must exec the
  // server, so that the pid is the server's.
  std::vector<std::string> command_prefix;
  // More flags, after the defaults. Each default below is passed only when
  // `extra` does not name the flag itself.
  std::vector<std::string> extra;
  int workers = 1;          // --workers
  int threads_per_job = 2;  // --threads-per-job
  // --drain-grace: 0 cancels what still runs at SIGTERM at once.
  double drain_grace_seconds = 0;
  // For the health check of a server with --tls-cert: the CA that signed its
  // certificate (PEM file), and a client certificate and key when it
  // requires one (--tls-client-ca). Empty: plaintext.
  std::string tls_ca_file;
  std::string tls_client_cert_file;
  std::string tls_client_key_file;
  // How long Start() waits for the port file and a SERVING health check.
  double start_timeout_seconds = 120;
};

class ServerProcess {
 public:
  explicit ServerProcess(ServerOptions options);  // does not start it
  // Stop() when it runs, EXPECTing exit code 0 (the log is in the message).
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  // Starts the server and waits until it is ready (see the file comment).
  // Fails (a gtest AssertionResult, for ASSERT_TRUE) when the process ended
  // during start-up (its exit code is then exit_code(); a bad configuration
  // ends with 1) or was not ready within start_timeout_seconds (it is then
  // killed); the message says which and ends with the tail of the log. Also
  // a restart: the same spool, log and options (with a fixed --listen, the
  // same address).
  ::testing::AssertionResult Start();
  // SIGTERM, then waits up to `timeout_seconds` and reaps it: its exit code,
  // or -1 when it had to be killed (SIGKILL). No-op (-1) when not running.
  int Stop(double timeout_seconds = 60);
  // SIGKILL and reap: a crash, for tests of what survives one.
  void Kill();

  bool running() const { return pid_ > 0; }
  pid_t pid() const { return pid_; }
  // The exit code once the process ended (Start failed, Stop), else -1.
  int exit_code() const { return exit_code_; }
  // Waits up to `timeout_seconds` for the process to end by itself (e.g.
  // after refusing its configuration): its exit code, or -1 while it runs.
  int WaitExit(double timeout_seconds);

  // 127.0.0.1:<gRPC port>, and the ports from the port file (0 when the
  // server has none: metrics without --metrics-listen, DICOM without
  // --dicom-listen). Valid after Start() succeeded.
  const std::string& address() const { return address_; }
  int grpc_port() const { return grpc_port_; }
  int metrics_port() const { return metrics_port_; }
  int dicom_port() const { return dicom_port_; }
  // {"--server", address()}: the client's flag.
  std::vector<std::string> ServerFlag() const { return {"--server", address_}; }
  const std::string& spool() const { return options_.spool; }
  // The whole log so far.
  std::string Log() const;

 private:
  std::string LogTail() const;
  bool HealthServing() const;

  ServerOptions options_;
  std::string port_file_;
  pid_t pid_ = -1;
  int exit_code_ = -1;
  std::string address_;
  int grpc_port_ = 0, metrics_port_ = 0, dicom_port_ = 0;
};

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_SERVER_PROCESS_H_
