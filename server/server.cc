#include "server/server.h"

#include <dlfcn.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <sys/stat.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <memory>
#include <sstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/health_check_service_interface.h"
#include "server/auth.h"
#include "server/executor.h"
#include "server/forwarding.h"
#include "server/job_manager.h"
#include "server/log_safe.h"
#include "server/metrics.h"
#include "server/service.h"
#include "server/spool.h"
#include "spdlog/pattern_formatter.h"
#include "spdlog/sinks/stdout_sinks.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace {

// %* in a pattern: the message, LogSafe (the call sites escape client text;
// this is the backstop), so that one entry is always one line.
class SafeMessageFlag : public spdlog::custom_flag_formatter {
 public:
  void format(const spdlog::details::log_msg& msg, const std::tm&,
              spdlog::memory_buf_t& dest) override {
    const std::string safe =
        LogSafe(absl::string_view(msg.payload.data(), msg.payload.size()));
    dest.append(safe.data(), safe.data() + safe.size());
  }
  std::unique_ptr<custom_flag_formatter> clone() const override {
    return std::make_unique<SafeMessageFlag>();
  }
};

// %* in a pattern: the message, LogSafe and escaped for a JSON string.
class JsonMessageFlag : public spdlog::custom_flag_formatter {
 public:
  void format(const spdlog::details::log_msg& msg, const std::tm&,
              spdlog::memory_buf_t& dest) override {
    static constexpr char kHex[] = "0123456789abcdef";
    for (char c :
         LogSafe(absl::string_view(msg.payload.data(), msg.payload.size()))) {
      switch (c) {
        case '"':
          dest.append(std::string_view("\\\""));
          break;
        case '\\':
          dest.append(std::string_view("\\\\"));
          break;
        case '\n':
          dest.append(std::string_view("\\n"));
          break;
        default:
          if (static_cast<unsigned char>(c) < 0x20) {
            const char esc[] = {'\\',        'u', '0', '0', kHex[(c >> 4) & 15],
                                kHex[c & 15]};
            dest.append(esc, esc + 6);
          } else {
            dest.push_back(c);
          }
      }
    }
  }
  std::unique_ptr<custom_flag_formatter> clone() const override {
    return std::make_unique<JsonMessageFlag>();
  }
};

absl::Status SetUpLogging(const ServerOptions& options) {
  auto logger = spdlog::stderr_logger_mt("interslice-server");
  if (options.log_format == "json") {
    auto formatter = std::make_unique<spdlog::pattern_formatter>();
    formatter->add_flag<JsonMessageFlag>('*').set_pattern(
        R"({"time":"%Y-%m-%dT%H:%M:%S.%e%z","level":"%l","msg":"%*"})");
    logger->set_formatter(std::move(formatter));
  } else if (options.log_format == "text") {
    auto formatter = std::make_unique<spdlog::pattern_formatter>();
    formatter->add_flag<SafeMessageFlag>('*').set_pattern(
        "%Y-%m-%dT%H:%M:%S.%e%z %l %*");
    logger->set_formatter(std::move(formatter));
  } else {
    return absl::InvalidArgumentError("--log-format must be text or json");
  }
  const spdlog::level::level_enum level =
      spdlog::level::from_str(options.log_level);
  if (level == spdlog::level::off && options.log_level != "off") {
    return absl::InvalidArgumentError(
        "--log-level must be trace, debug, info, warn, error or off");
  }
  logger->set_level(level);
  logger->flush_on(spdlog::level::trace);
  spdlog::set_default_logger(logger);
  return absl::OkStatus();
}

absl::StatusOr<std::string> ReadFile(const std::string& path,
                                     const std::string& what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return absl::NotFoundError(absl::StrCat("cannot read ", what, " ", path));
  }
  std::stringstream buffer;
  buffer << in.rdbuf();
  return buffer.str();
}

int ReadCgroupCpuLimit() {
  // cgroup v2
  std::ifstream v2("/sys/fs/cgroup/cpu.max");
  std::string quota;
  double period = 0;
  if (v2 >> quota >> period && quota != "max" && period > 0) {
    return std::max(1, static_cast<int>(std::ceil(std::stod(quota) / period)));
  }
  // cgroup v1
  std::ifstream q("/sys/fs/cgroup/cpu/cpu.cfs_quota_us");
  std::ifstream p("/sys/fs/cgroup/cpu/cpu.cfs_period_us");
  double qv = -1, pv = 0;
  if (q >> qv && p >> pv && qv > 0 && pv > 0) {
    return std::max(1, static_cast<int>(std::ceil(qv / pv)));
  }
  return 0;
}

}  // namespace

int AvailableCpus() {
  int cpus = static_cast<int>(std::thread::hardware_concurrency());
  cpu_set_t set;
  if (sched_getaffinity(0, sizeof(set), &set) == 0) cpus = CPU_COUNT(&set);
  const int limit = ReadCgroupCpuLimit();
  if (limit > 0) cpus = std::min(cpus, limit);
  return std::max(1, cpus);
}

int RunServer(ServerOptions options) {
  // Only the signal thread takes SIGTERM/SIGINT: every thread started from
  // here on inherits this mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  // Uploads, records and the artifacts the core writes: owner only.
  ::umask(077);

  if (absl::Status s = SetUpLogging(options); !s.ok()) {
    std::fprintf(stderr, "interslice-server: error: %s\n",
                 std::string(s.message()).c_str());
    return 1;
  }
  auto fail = [](const absl::Status& s) {
    spdlog::critical("{}", std::string(s.message()));
    std::fprintf(stderr, "interslice-server: error: %s\n",
                 std::string(s.message()).c_str());
    return 1;
  };
  if (options.spool.empty()) {
    return fail(absl::InvalidArgumentError("--spool is required"));
  }
  const int cpus = AvailableCpus();
  if (options.workers <= 0) options.workers = std::max(1, cpus / 4);
  if (options.threads_per_job <= 0) {
    options.threads_per_job = std::max(1, cpus / options.workers);
  }
  if (options.max_queued_jobs < 0 || options.max_chunk_bytes < 1024 ||
      options.max_chunk_bytes > (4 << 20) - 1024) {
    return fail(absl::InvalidArgumentError(
        "--max-queued must be >= 0 and --max-chunk-bytes in [1 KiB, 4 MiB)"));
  }
  if (options.max_concurrent_uploads <= 0) {
    options.max_concurrent_uploads = std::max(1, 2 * options.max_queued_jobs);
  }
  if (options.max_uploads_per_peer < 1 ||
      !(options.upload_idle_timeout_seconds >= 0) ||
      !(options.upload_timeout_seconds >= 0)) {
    return fail(absl::InvalidArgumentError(
        "--max-uploads-per-peer must be >= 1, --upload-idle-timeout and "
        "--upload-timeout >= 0"));
  }

  if (!options.advertise.empty() && !IsReplicaAddress(options.advertise)) {
    return fail(absl::InvalidArgumentError(
        absl::StrCat("--advertise ", LogSafe(options.advertise),
                     " is not HOST:PORT (a DNS name, IPv4 address or "
                     "[IPv6] address, and a port)")));
  }
  std::vector<NamedToken> tokens;
  if (!options.auth_token_file.empty()) {
    absl::StatusOr<std::string> t =
        ReadFile(options.auth_token_file, "the token file");
    if (!t.ok()) return fail(t.status());
    absl::StatusOr<std::vector<NamedToken>> parsed = ParseTokenFile(*t);
    if (!parsed.ok()) return fail(parsed.status());
    tokens = *std::move(parsed);
  }
  for (const std::string& admin : options.admin_identities) {
    if (tokens.empty() && options.tls_client_ca.empty()) {
      return fail(absl::InvalidArgumentError(
          "--admin-identity needs --auth-token-file or --tls-client-ca"));
    }
    // With tokens the identity is always a token's name: catch typos.
    const bool known =
        std::any_of(tokens.begin(), tokens.end(),
                    [&](const NamedToken& t) { return t.name == admin; });
    if (!tokens.empty() && !known) {
      return fail(absl::InvalidArgumentError(
          absl::StrCat("--admin-identity ", LogSafe(admin),
                       " is not a name in the token file")));
    }
  }
  std::shared_ptr<grpc::ServerCredentials> credentials;
  std::shared_ptr<grpc::ChannelCredentials> peer_credentials =
      grpc::InsecureChannelCredentials();
  if (!options.tls_cert.empty() || !options.tls_key.empty()) {
    absl::StatusOr<std::string> cert = ReadFile(options.tls_cert, "--tls-cert");
    if (!cert.ok()) return fail(cert.status());
    absl::StatusOr<std::string> key = ReadFile(options.tls_key, "--tls-key");
    if (!key.ok()) return fail(key.status());
    grpc::SslServerCredentialsOptions ssl(
        GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
    ssl.pem_key_cert_pairs.push_back({*key, *cert});
    if (!options.tls_client_ca.empty()) {
      absl::StatusOr<std::string> ca =
          ReadFile(options.tls_client_ca, "--tls-client-ca");
      if (!ca.ok()) return fail(ca.status());
      ssl.pem_root_certs = *ca;
      ssl.client_certificate_request =
          GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY;
    }
    credentials = grpc::SslServerCredentials(ssl);
    grpc::SslCredentialsOptions peer_ssl;
    if (!options.peer_tls_ca.empty()) {
      absl::StatusOr<std::string> ca =
          ReadFile(options.peer_tls_ca, "--peer-tls-ca");
      if (!ca.ok()) return fail(ca.status());
      peer_ssl.pem_root_certs = *ca;
    }
    if (!options.tls_client_ca.empty()) {
      peer_ssl.pem_cert_chain = *cert;
      peer_ssl.pem_private_key = *key;
    }
    peer_credentials = grpc::SslCredentials(peer_ssl);
  } else if (!options.tls_client_ca.empty()) {
    return fail(absl::InvalidArgumentError(
        "--tls-client-ca needs --tls-cert and --tls-key"));
  } else {
    credentials = grpc::InsecureServerCredentials();
  }

  QuietDicomToolkitLogging();
  Metrics metrics;
  if (!options.metrics_listen.empty()) {
    if (absl::Status s = metrics.Serve(options.metrics_listen); !s.ok()) {
      return fail(s);
    }
  }
  absl::StatusOr<std::unique_ptr<Spool>> spool =
      Spool::Open(options.spool, options.spool_quota_bytes);
  if (!spool.ok()) return fail(spool.status());

  ManagerOptions manager_options;
  manager_options.workers = options.workers;
  manager_options.threads_per_job = options.threads_per_job;
  manager_options.max_queued_jobs = options.max_queued_jobs;
  manager_options.max_upload_bytes = options.max_upload_bytes;
  manager_options.max_output_voxels = options.max_output_voxels;
  manager_options.retention_seconds = options.retention_seconds;
  manager_options.isolate_jobs = options.isolation == "process";
  manager_options.max_attempts = options.max_attempts;
  JobManager manager(manager_options, spool->get(), &metrics);
  if (absl::Status s = manager.Recover(); !s.ok()) return fail(s);
  manager.Start();

  Executor io(options.io_threads);
  ServiceOptions service_options;
  service_options.tokens = std::move(tokens);
  service_options.admin_identities = options.admin_identities;
  service_options.max_chunk_bytes = options.max_chunk_bytes;
  service_options.uploads.max_concurrent = options.max_concurrent_uploads;
  service_options.uploads.max_per_peer = options.max_uploads_per_peer;
  service_options.uploads.idle_timeout_seconds =
      options.upload_idle_timeout_seconds;
  service_options.uploads.total_timeout_seconds =
      options.upload_timeout_seconds;
  InterSliceService service(service_options, &manager, spool->get(), &io,
                            &metrics);
  Forwarder forwarder(peer_credentials);
  service.set_forwarder(&forwarder);

  if (options.reflection) {
    // Linking gRPC's reflection library registers the service in every
    // server through a static initialiser, so it is loaded only on request.
    if (dlopen("libgrpc++_reflection.so.1.51", RTLD_NOW | RTLD_GLOBAL) ==
        nullptr) {
      return fail(absl::UnavailableError(
          absl::StrCat("cannot load gRPC reflection: ", dlerror())));
    }
  }
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort(options.listen, credentials, &port);
  builder.RegisterService(&service);
  builder.SetMaxReceiveMessageSize(4 << 20);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (!server || port == 0) {
    manager.Shutdown(std::chrono::milliseconds(0));
    return fail(absl::UnavailableError(
        absl::StrCat("cannot listen on ", options.listen)));
  }
  if (options.advertise.empty()) {
    options.advertise = absl::StrCat(
        options.listen.substr(0, options.listen.rfind(':')), ":", port);
  }
  forwarder.SetAdvertise(options.advertise);
  manager.SetJobIdSuffix(JobIdSuffix(options.advertise));
  spdlog::info("advertised as {}: jobs accepted here are named for it",
               LogSafe(options.advertise));
  grpc::HealthCheckServiceInterface* health = server->GetHealthCheckService();
  health->SetServingStatus(true);
  health->SetServingStatus("interslice.v1.InterSlice", true);
  spdlog::info(
      "listening on {} (port {}, {}{}); {} worker(s) x {} thread(s), queue "
      "{}, spool {}{}",
      options.listen, port, options.tls_cert.empty() ? "plaintext" : "TLS",
      options.tls_client_ca.empty() ? "" : ", client certificates required",
      options.workers, options.threads_per_job, options.max_queued_jobs,
      options.spool, options.reflection ? ", reflection on" : "");
  if (!options.metrics_listen.empty()) {
    spdlog::info("metrics on {} (port {})", options.metrics_listen,
                 metrics.port());
  }
  if (!options.port_file.empty()) {
    if (absl::Status s = WriteFileAtomically(
            options.port_file, absl::StrCat(port, "\n", metrics.port(), "\n"));
        !s.ok()) {
      spdlog::error("cannot write the port file: {}", std::string(s.message()));
    }
  }

  // The drain runs here, on an ordinary thread, never in a signal handler.
  std::thread signal_thread([&] {
    int signal_number = 0;
    sigwait(&signals, &signal_number);
    spdlog::info("{}: draining (grace {} s): health NOT_SERVING, no new jobs",
                 signal_number == SIGTERM ? "SIGTERM" : "SIGINT",
                 options.drain_grace_seconds);
    health->SetServingStatus(false);
    health->SetServingStatus("interslice.v1.InterSlice", false);
    manager.BeginDrain();
    manager.Shutdown(std::chrono::milliseconds(
        static_cast<int64_t>(options.drain_grace_seconds * 1000)));
    spdlog::info("jobs stopped; closing connections");
    server->Shutdown(std::chrono::system_clock::now() +
                     std::chrono::seconds(2));
  });
  server->Wait();
  signal_thread.join();
  spdlog::info("stopped");
  return 0;
}

}  // namespace interslice::server
