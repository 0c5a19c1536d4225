#include "tests/testing/server_process.h"

#include <signal.h>
#include <sys/wait.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "grpcpp/grpcpp.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/wait_for.h"

namespace interslice::testing {
namespace fs = std::filesystem;

ServerProcess::ServerProcess(ServerOptions options)
    : options_(std::move(options)) {
  if (options_.binary.empty())
    options_.binary = ::interslice::testing::ServerPath();
  if (options_.log.empty()) options_.log = options_.spool + ".log";
  port_file_ = options_.spool + ".port";
}

ServerProcess::~ServerProcess() {
  if (pid_ > 0) {
    const int rc = Stop();
    EXPECT_EQ(rc, 0) << "interslice-server did not exit cleanly after "
                        "SIGTERM; its log:\n"
                     << Log();
  }
}

::testing::AssertionResult ServerProcess::Start() {
  if (pid_ > 0) {
    return ::testing::AssertionFailure() << "interslice-server already runs";
  }
  std::error_code ec;
  fs::remove(port_file_, ec);  // a restart must not read the old ports
  const std::vector<std::string>& extra = options_.extra;
  auto named = [&](const std::string& flag) {
    return std::find(extra.begin(), extra.end(), flag) != extra.end();
  };
  std::vector<std::string> argv = {
      options_.binary, "--listen",    options_.listen, "--spool",
      options_.spool,  "--port-file", port_file_};
  if (!named("--workers")) {
    argv = Cat(argv, {"--workers", std::to_string(options_.workers)});
  }
  if (!named("--threads-per-job")) {
    argv = Cat(argv,
               {"--threads-per-job", std::to_string(options_.threads_per_job)});
  }
  if (!named("--drain-grace")) {
    argv = Cat(argv,
               {"--drain-grace", absl::StrCat(options_.drain_grace_seconds)});
  }
  argv = Cat(options_.command_prefix, Cat(argv, extra));
  exit_code_ = -1;
  grpc_port_ = metrics_port_ = dicom_port_ = 0;
  address_.clear();
  pid_ = StartProcess(argv, options_.log);

  // The port file first (it names the ports), then the health check.
  bool ended = false;
  const bool ready = WaitFor(
      [&] {
        const int rc = WaitProcess(pid_, 0);
        if (rc != -1 || ::waitpid(pid_, nullptr, WNOHANG) < 0) {
          exit_code_ = rc;
          ended = true;
          return true;
        }
        if (grpc_port_ == 0) {
          std::ifstream in(port_file_);
          int grpc = 0, metrics = 0, dicom = 0;
          if (!(in >> grpc)) return false;
          in >> metrics >> dicom;
          grpc_port_ = grpc;
          metrics_port_ = metrics;
          dicom_port_ = dicom;
          address_ = absl::StrCat("127.0.0.1:", grpc_port_);
        }
        return HealthServing();
      },
      std::chrono::duration<double>(options_.start_timeout_seconds),
      std::chrono::milliseconds(20));
  if (ended) {
    pid_ = -1;
    return ::testing::AssertionFailure()
           << "interslice-server ended during start-up with exit code "
           << exit_code_ << "; its log ends:\n"
           << LogTail();
  }
  if (!ready) {
    Kill();
    return ::testing::AssertionFailure()
           << "interslice-server was not ready (port file and SERVING "
              "health) within "
           << options_.start_timeout_seconds << " s; its log ends:\n"
           << LogTail();
  }
  return ::testing::AssertionSuccess();
}

bool ServerProcess::HealthServing() const {
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  if (options_.tls_ca_file.empty()) {
    credentials = grpc::InsecureChannelCredentials();
  } else {
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = ReadFileOrEmpty(options_.tls_ca_file);
    if (!options_.tls_client_cert_file.empty()) {
      ssl.pem_cert_chain = ReadFileOrEmpty(options_.tls_client_cert_file);
      ssl.pem_private_key = ReadFileOrEmpty(options_.tls_client_key_file);
    }
    credentials = grpc::SslCredentials(ssl);
  }
  auto stub = grpc::health::v1::Health::NewStub(
      grpc::CreateChannel(address_, credentials));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(5));
  grpc::health::v1::HealthCheckRequest request;
  grpc::health::v1::HealthCheckResponse response;
  return stub->Check(&context, request, &response).ok() &&
         response.status() == grpc::health::v1::HealthCheckResponse::SERVING;
}

int ServerProcess::Stop(double timeout_seconds) {
  if (pid_ <= 0) return -1;
  exit_code_ = StopProcess(pid_, timeout_seconds);
  pid_ = -1;
  return exit_code_;
}

void ServerProcess::Kill() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGKILL);
  ::waitpid(pid_, nullptr, 0);
  pid_ = -1;
  exit_code_ = -1;
}

int ServerProcess::WaitExit(double timeout_seconds) {
  if (pid_ <= 0) return exit_code_;
  const int rc = WaitProcess(pid_, timeout_seconds);
  if (rc != -1 || ::waitpid(pid_, nullptr, WNOHANG) < 0) {
    exit_code_ = rc;
    pid_ = -1;
  }
  return rc;
}

std::string ServerProcess::Log() const { return ReadFileOrEmpty(options_.log); }

std::string ServerProcess::LogTail() const {
  const std::string log = Log();
  constexpr size_t kTail = 4000;
  return log.size() <= kTail ? log : "..." + log.substr(log.size() - kTail);
}

}  // namespace interslice::testing
