#include "server/server.h"

#include <dlfcn.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <sys/stat.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <optional>
#include <sstream>
#include <stop_token>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/dicom/series_reader.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/health_check_service_interface.h"
#include "server/audit.h"
#include "server/auth.h"
#include "server/dicom/config.h"
#include "server/dicom/delivery.h"
#include "server/dicom/echo.h"
#include "server/dicom/pending_moves.h"
#include "server/dicom/scu.h"
#include "server/dicom/series_assembler.h"
#include "server/dicom/storage_scp.h"
#include "server/dicomweb/stow.h"
#include "server/executor.h"
#include "server/forwarding.h"
#include "server/job_manager.h"
#include "server/log_safe.h"
#include "server/metrics.h"
#include "server/service.h"
#include "server/spool.h"
#include "server/status_page.h"
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

namespace {

// The DICOM node's configuration as a start would take it: the peers
// file, the rules file (send_to names checked against the peers), the
// listener's AE titles, and every rule's called_ae among them.
struct DicomConfig {
  dicom::PeersConfig peers;
  dicom::RuleSet rules;
  std::vector<std::string> ae_titles;  // normalized; never empty
};

absl::StatusOr<DicomConfig> LoadDicomConfig(const ServerOptions& options) {
  DicomConfig config;
  if (!options.dicom_peers_file.empty()) {
    absl::StatusOr<dicom::PeersConfig> loaded =
        dicom::LoadPeersConfig(options.dicom_peers_file);
    if (!loaded.ok()) return loaded.status();
    config.peers = *std::move(loaded);
  }
  if (!options.rules_file.empty()) {
    absl::StatusOr<dicom::RuleSet> loaded =
        dicom::LoadRulesFile(options.rules_file, config.peers.peers);
    if (!loaded.ok()) return loaded.status();
    config.rules = *std::move(loaded);
  } else {
    config.rules.path = "(none: --rules not given)";
  }
  config.ae_titles = options.dicom_ae_titles;
  if (config.ae_titles.empty()) config.ae_titles.push_back("INTERSLICE");
  for (std::string& ae : config.ae_titles) {
    absl::StatusOr<std::string> normal = dicom::NormalizeAeTitle(ae);
    if (!normal.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "--dicom-ae '", LogSafe(ae), "': ", normal.status().message()));
    }
    ae = *normal;
  }
  const std::vector<std::string>& titles = config.ae_titles;
  for (size_t i = 0; i < config.rules.rules.size(); ++i) {
    const auto& called = config.rules.rules[i].match.called_ae;
    if (called &&
        std::find(titles.begin(), titles.end(), *called) == titles.end()) {
      return absl::InvalidArgumentError(absl::StrCat(
          options.rules_file, ": rule '", config.rules.rules[i].name, "' (#",
          i + 1, "): match.called_ae: ", *called,
          " is not an AE title this server listens as (--dicom-ae ",
          absl::StrJoin(titles, ", --dicom-ae "), ")"));
    }
  }
  return config;
}

absl::StatusOr<std::unique_ptr<dicom::SeriesAssembler>> StartDicomAssembler(
    const ServerOptions& options, Spool* spool, Metrics* metrics,
    JobManager* manager) {
  absl::StatusOr<DicomConfig> config = LoadDicomConfig(options);
  if (!config.ok()) return config.status();
  dicom::RuleSet rules = std::move(config->rules);
  if (options.rules_file.empty()) {
    spdlog::warn("dicom: no --rules: received series make no jobs");
  }
  dicom::AssemblerOptions a;
  a.root = options.spool + "/dicom-in";
  a.max_instances_per_series = options.dicom_max_series_instances;
  a.max_bytes_per_series = options.dicom_max_series_bytes;
  a.unmatched_retention_seconds =
      static_cast<double>(options.retention_seconds);
  a.job_ended_without_results = [manager](const std::string& id) {
    std::shared_ptr<Job> job = manager->Find(id);
    if (job == nullptr) return false;
    const v1::JobState state = job->Snapshot(false).state();
    return state == v1::JOB_STATE_FAILED || state == v1::JOB_STATE_CANCELLED;
  };
  return dicom::SeriesAssembler::Open(
      a, std::move(rules), spool, metrics,
      [manager](const v1::JobSpec& spec, const std::string& dir,
                const std::string& origin,
                const std::string& segmentation_file) {
        // A fill rule's spec names the segmentation it takes (job/wire.h);
        // the node hands over the SEG or RTSTRUCT it received.
        std::map<std::string, std::string> named;
        if (!segmentation_file.empty()) {
          named[spec.fill().segmentation_file()] = segmentation_file;
        }
        return manager->SubmitLocalFiles(spec, dir, "dicom", origin, named);
      });
}

absl::StatusOr<std::unique_ptr<dicom::StorageScp>> StartDicomListener(
    const ServerOptions& options, dicom::SeriesAssembler* assembler,
    Metrics* metrics, AuditLog* audit, dicom::PendingMoves* pending_moves) {
  dicom::StorageScpOptions o;
  o.audit = audit;
  o.pending_moves = pending_moves;
  const size_t colon = options.dicom_listen.rfind(':');
  int port = -1;
  if (colon == std::string::npos ||
      !absl::SimpleAtoi(options.dicom_listen.substr(colon + 1), &port) ||
      port < 0 || port > 65535) {
    return absl::InvalidArgumentError(
        absl::StrCat("--dicom-listen: expected HOST:PORT, got '",
                     LogSafe(options.dicom_listen), "'"));
  }
  o.host = options.dicom_listen.substr(0, colon);
  o.port = port;
  o.ae_titles = options.dicom_ae_titles;
  if (o.ae_titles.empty()) o.ae_titles = {"INTERSLICE"};
  for (std::string& ae : o.ae_titles) {
    ae = *dicom::NormalizeAeTitle(ae);  // checked by StartDicomAssembler
  }
  if (!options.dicom_peers_file.empty()) {
    absl::StatusOr<dicom::PeersConfig> peers =
        dicom::LoadPeersConfig(options.dicom_peers_file);
    if (!peers.ok()) return peers.status();
    o.peers = *std::move(peers);
  }
  o.max_associations = options.dicom_max_associations;
  o.max_associations_per_source = options.dicom_max_associations_per_source;
  o.max_pending = options.dicom_max_pending;
  o.max_pending_per_source = options.dicom_max_pending_per_source;
  o.pdu_timeout_seconds = options.dicom_pdu_timeout_seconds;
  if (options.dicom_max_pdu < 4096 || options.dicom_max_pdu > 131072) {
    return absl::InvalidArgumentError(
        "--dicom-max-pdu must be between 4096 and 131072 bytes");
  }
  o.max_pdu_bytes = static_cast<uint32_t>(options.dicom_max_pdu);
  o.acse_timeout_seconds = options.dicom_acse_timeout_seconds;
  o.dimse_timeout_seconds = options.dicom_dimse_timeout_seconds;
  o.tls.certificate = options.dicom_tls_cert;
  o.tls.private_key = options.dicom_tls_key;
  o.tls.ca_certificates = options.dicom_tls_ca;
  return dicom::StorageScp::Start(o, assembler, metrics);
}

// A peer pulled from by C-MOVE sends to our listener: without one, no pull
// from it could ever succeed, so the start fails saying so.
absl::Status CheckMoveDestination(const std::string& dicom_listen,
                                  const std::vector<dicom::DicomPeer>& peers) {
  if (!dicom_listen.empty()) return absl::OkStatus();
  for (const dicom::DicomPeer& peer : peers) {
    if (peer.type == dicom::PeerType::kDimse &&
        peer.retrieve == dicom::RetrieveMethod::kMove) {
      return absl::InvalidArgumentError(absl::StrCat(
          "peer '", peer.name,
          "' has retrieve: move, which needs the DICOM listener "
          "(--dicom-listen): the server is its own C-MOVE destination"));
    }
  }
  return absl::OkStatus();
}

// Outgoing associations call as the first --dicom-ae (DeliveryOptions'
// default when none is given).
std::string CallingAeTitle(const ServerOptions& options) {
  if (options.dicom_ae_titles.empty()) return "INTERSLICE";
  absl::StatusOr<std::string> ae =
      dicom::NormalizeAeTitle(options.dicom_ae_titles.front());
  return ae.ok() ? *ae : options.dicom_ae_titles.front();
}

dicom::DicomTlsFiles DicomTls(const ServerOptions& options) {
  dicom::DicomTlsFiles tls;
  tls.certificate = options.dicom_tls_cert;
  tls.private_key = options.dicom_tls_key;
  tls.ca_certificates = options.dicom_tls_ca;
  return tls;
}

// Seconds a C-ECHO of a peer may take per step (connect, associate,
// answer): short, so that a check of several dead peers stays quick.
constexpr int kEchoTimeoutSeconds = 5;

// "a series with modality CT, called_ae INTERSLICE -> job (complete on
// release), send_to orthanc"
std::string DescribeRule(const dicom::Rule& rule) {
  std::string text = absl::StrCat(
      rule.job.has_fill() ? "a segmentation (SEG, RTSTRUCT) with "
                          : "a series with ",
      rule.match.Describe(), " -> ", rule.job.has_fill() ? "fill job" : "job");
  if (rule.complete_on_release)
    absl::StrAppend(&text, " (complete on release)");
  if (!rule.send_to.empty()) {
    absl::StrAppend(&text, ", send_to ", absl::StrJoin(rule.send_to, ", "));
  }
  return text;
}

// SIGHUP: the peers and rules files read again and checked exactly as at
// start-up; the listener's accepted callers and the assembler's rules are
// replaced only when all of it is valid. Deliveries keep the peers of the
// start (a delivery in flight must not change its destination), so a rule
// may send only to peers the outbox holds with the same address. Jobs
// already made keep their spec.
absl::Status ReloadDicomConfig(const ServerOptions& options,
                               dicom::SeriesAssembler* assembler,
                               dicom::StorageScp* listener,
                               const dicom::DeliveryQueue* outbox) {
  absl::StatusOr<DicomConfig> config = LoadDicomConfig(options);
  if (!config.ok()) return config.status();
  for (size_t i = 0; i < config->rules.rules.size(); ++i) {
    const dicom::Rule& rule = config->rules.rules[i];
    for (const std::string& name : rule.send_to) {
      const dicom::DicomPeer* now = nullptr;
      for (const dicom::DicomPeer& peer : config->peers.peers) {
        if (peer.name == name) now = &peer;
      }
      std::optional<dicom::DicomPeer> started;
      if (outbox != nullptr) started = outbox->FindPeer(name);
      if (now == nullptr || !started || started->ae_title != now->ae_title ||
          started->host != now->host || started->port != now->port ||
          started->tls != now->tls) {
        return absl::FailedPreconditionError(absl::StrCat(
            options.rules_file, ": rule '", rule.name, "' (#", i + 1,
            "): send_to: peer '", name,
            "' is new or changed since the start; deliveries use the peers "
            "of the start (restart the server to change them)"));
      }
    }
  }
  listener->SetPeers(std::move(config->peers));
  assembler->SetRules(std::move(config->rules));
  return absl::OkStatus();
}

}  // namespace

int RunServer(ServerOptions options) {
  // Only the signal thread takes SIGTERM/SIGINT: every thread started from
  // here on inherits this mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGHUP);  // reloads the DICOM node's files
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
  // The audit trail is opened before anything it records starts, and
  // destroyed (its queue written) after everything has stopped.
  std::unique_ptr<AuditLog> audit;
  if (!options.audit_log.empty()) {
    absl::StatusOr<std::unique_ptr<AuditLog>> opened =
        AuditLog::Open({.path = options.audit_log,
                        .max_bytes = options.audit_max_bytes,
                        .keep = options.audit_keep});
    if (!opened.ok()) return fail(opened.status());
    audit = *std::move(opened);
  }

  ManagerOptions manager_options;
  manager_options.workers = options.workers;
  manager_options.threads_per_job = options.threads_per_job;
  manager_options.max_queued_jobs = options.max_queued_jobs;
  manager_options.max_upload_bytes = options.max_upload_bytes;
  manager_options.max_output_voxels = options.max_output_voxels;
  manager_options.retention_seconds = options.retention_seconds;
  manager_options.isolate_jobs = options.isolation == "process";
  manager_options.max_attempts = options.max_attempts;
  manager_options.audit = audit.get();
  // The C-MOVEs in progress (declared before the manager and the listener,
  // which use it, so it outlives both).
  dicom::PendingMoves pending_moves;
  JobManager manager(manager_options, spool->get(), &metrics);
  // The outbox (declared after the manager, so stopped before it).
  std::unique_ptr<dicom::DeliveryQueue> outbox;
  if (!options.dicom_peers_file.empty()) {
    absl::StatusOr<std::vector<dicom::DicomPeer>> peers =
        dicom::LoadPeersFile(options.dicom_peers_file);
    if (!peers.ok()) return fail(peers.status());
    options.dicom_peers.insert(options.dicom_peers.end(), peers->begin(),
                               peers->end());
  }
  if (absl::Status s =
          CheckMoveDestination(options.dicom_listen, options.dicom_peers);
      !s.ok()) {
    return fail(s);
  }
  if (!options.dicom_listen.empty()) {
    manager.SetMoveDestination(&pending_moves, CallingAeTitle(options));
  }
  if (!options.dicom_peers.empty()) {
    dicom::DeliveryOptions delivery;
    if (!options.dicom_ae_titles.empty()) {
      absl::StatusOr<std::string> ae =
          dicom::NormalizeAeTitle(options.dicom_ae_titles.front());
      if (!ae.ok()) return fail(ae.status());
      delivery.calling_ae_title = *ae;
    }
    delivery.tls.certificate = options.dicom_tls_cert;
    delivery.tls.private_key = options.dicom_tls_key;
    delivery.tls.ca_certificates = options.dicom_tls_ca;
    auto ms = [](double seconds) {
      return std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000));
    };
    delivery.initial_backoff = ms(options.delivery_retry_seconds);
    delivery.max_backoff = ms(options.delivery_retry_max_seconds);
    delivery.give_up_after = ms(options.delivery_give_up_seconds);
    dicom::DeliveryCounters counters;
    counters.sent = [&metrics](const std::string& peer, int n) {
      metrics.DicomInstancesSent(peer, n);
    };
    counters.failed = [&metrics](const std::string& peer, int n) {
      metrics.DicomInstancesFailed(peer, n);
    };
    outbox = std::make_unique<dicom::DeliveryQueue>(
        options.dicom_peers, delivery,
        [&manager](const std::string& job_id, const v1::Delivery& d) {
          manager.UpdateDelivery(job_id, d);
        },
        counters);
    manager.SetDeliveryQueue(outbox.get());
  }
  if (absl::Status s = manager.Recover(); !s.ok()) return fail(s);
  // The workers start after the DICOM listener (below): a recovered job that
  // pulls by C-MOVE needs the listener as its move destination.
  if (outbox != nullptr) outbox->Start();
  // A wrong host, port or AE title of a peer shows at start (a warning and
  // interslice_dicom_peer_reachable{peer} 0), not after a day of delivery
  // retries. Off the start-up path: a silent peer costs its timeout here
  // only. Joined when RunServer returns (before the metrics go).
  std::jthread peer_check;
  if (!options.dicom_peers.empty()) {
    peer_check = std::jthread(
        [peers = options.dicom_peers, calling = CallingAeTitle(options),
         tls = DicomTls(options), &metrics](std::stop_token stop) {
          for (const dicom::DicomPeer& peer : peers) {
            if (stop.stop_requested()) return;
            absl::Status echo =
                dicom::EchoPeer(peer, calling, tls, kEchoTimeoutSeconds);
            metrics.DicomPeerReachable(peer.name, echo.ok());
            const char* probe = peer.type == dicom::PeerType::kDicomWeb
                                    ? "a QIDO-RS probe"
                                    : "a C-ECHO";
            if (echo.ok()) {
              spdlog::info("dicom: {} answered {}",
                           LogSafe(dicom::PeerLabel(peer)), probe);
            } else {
              spdlog::warn(
                  "dicom: {} did not answer {} at start-up ({}); "
                  "deliveries to it will be retried",
                  LogSafe(dicom::PeerLabel(peer)), probe,
                  LogSafe(std::string(echo.message())));
            }
          }
        });
  }

  // The DICOM listener: configuration errors stop the start-up with the
  // file's one-line message.
  std::unique_ptr<dicom::SeriesAssembler> assembler;
  std::unique_ptr<dicom::StorageScp> dicom_scp;
  if (!options.dicom_listen.empty()) {
    absl::StatusOr<std::unique_ptr<dicom::SeriesAssembler>> a =
        StartDicomAssembler(options, spool->get(), &metrics, &manager);
    if (!a.ok()) {
      manager.Shutdown(std::chrono::milliseconds(0));
      return fail(a.status());
    }
    assembler = *std::move(a);
    absl::StatusOr<std::unique_ptr<dicom::StorageScp>> scp = StartDicomListener(
        options, assembler.get(), &metrics, audit.get(), &pending_moves);
    if (!scp.ok()) {
      manager.Shutdown(std::chrono::milliseconds(0));
      return fail(scp.status());
    }
    dicom_scp = *std::move(scp);
    assembler->Start();
  }
  manager.Start();

  Executor io(options.io_threads);
  ServiceOptions service_options;
  // The status page authenticates by the same tokens and admin identities.
  const Authenticator page_auth(tokens, options.admin_identities);
  service_options.tokens = std::move(tokens);
  service_options.admin_identities = options.admin_identities;
  service_options.max_chunk_bytes = options.max_chunk_bytes;
  service_options.uploads.max_concurrent = options.max_concurrent_uploads;
  service_options.uploads.max_per_peer = options.max_uploads_per_peer;
  service_options.uploads.idle_timeout_seconds =
      options.upload_idle_timeout_seconds;
  service_options.uploads.total_timeout_seconds =
      options.upload_timeout_seconds;
  service_options.audit = audit.get();
  InterSliceService service(service_options, &manager, spool->get(), &io,
                            &metrics);
  Forwarder forwarder(peer_credentials);
  service.set_forwarder(&forwarder);
  service.set_assembler(assembler.get());

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
  // The status page (docs/status-page.md) and STOW-RS (docs/dicomweb.md):
  // stopped before what they read.
  std::unique_ptr<dicomweb::StowReceiver> stow;
  if (assembler != nullptr && !options.status_listen.empty()) {
    stow = std::make_unique<dicomweb::StowReceiver>(
        dicomweb::StowOptions{.called_ae = CallingAeTitle(options),
                              .max_body_bytes = options.stow_max_body_bytes},
        assembler.get(), spool->get(), audit.get());
  }
  std::unique_ptr<StatusServer> status_page;
  if (options.status_listen.empty() &&
      (!options.http_tls_cert.empty() || !options.http_tls_key.empty())) {
    manager.Shutdown(std::chrono::milliseconds(0));
    return fail(absl::InvalidArgumentError(
        "--http-tls-cert and --http-tls-key need --http-listen"));
  }
  if (!options.status_listen.empty()) {
    auto snapshot = [&]() {
      StatusSnapshot s;
      s.version = service_options.version;
      s.now_unix_ms = std::chrono::duration_cast<std::chrono::milliseconds>(
                          std::chrono::system_clock::now().time_since_epoch())
                          .count();
      s.jobs = manager.List(true, nullptr);
      s.queued = manager.queued();
      s.running = manager.running();
      s.spool_used_bytes = (*spool)->used_bytes();
      s.spool_quota_bytes = (*spool)->quota_bytes();
      for (const dicom::DicomPeer& p : options.dicom_peers) {
        const bool web = p.type == dicom::PeerType::kDicomWeb;
        // A DICOMweb peer's URL never holds credentials (the peers file
        // refuses them).
        s.peers.push_back(
            {.name = p.name,
             .ae_title = web ? "(DICOMweb)" : p.ae_title,
             .address = web ? p.web.url : absl::StrCat(p.host, ":", p.port),
             .tls = web ? absl::StartsWithIgnoreCase(p.web.url, "https://")
                        : p.tls});
      }
      if (assembler != nullptr) {
        // The generation live now (SIGHUP may replace it).
        const std::shared_ptr<const dicom::RuleSet> rules = assembler->rules();
        s.rules_file = rules->path;
        for (const dicom::Rule& r : rules->rules) {
          s.rules.push_back({.name = r.name,
                             .match = r.match.Describe(),
                             .send_to = r.send_to});
        }
      }
      return s;
    };
    absl::StatusOr<std::unique_ptr<StatusServer>> started = StatusServer::Start(
        {.listen = options.status_listen,
         .max_connections = options.http_max_connections,
         .request_timeout_seconds = options.http_request_timeout_seconds,
         .stow_token_required =
             !page_auth.tokens_required() && !options.tls_client_ca.empty(),
         .tls_certificate = options.http_tls_cert,
         .tls_private_key = options.http_tls_key},
        snapshot, &page_auth, audit.get(), stow.get());
    if (!started.ok()) {
      manager.Shutdown(std::chrono::milliseconds(0));
      return fail(started.status());
    }
    status_page = *std::move(started);
    spdlog::info("status page on {} (port {}, {}){}{}", options.status_listen,
                 status_page->port(), status_page->tls() ? "HTTPS" : "HTTP",
                 page_auth.tokens_required()
                     ? ": admin identities only"
                     : ": open to anyone who reaches it (no tokens)",
                 stow != nullptr
                     ? absl::StrCat("; STOW-RS at /dicomweb/studies as ",
                                    CallingAeTitle(options), ", bodies up to ",
                                    stow->max_body_bytes(), " bytes")
                     : "");
  }
  if (audit != nullptr) {
    audit->Record({.event = "server.started",
                   .source = options.advertise,
                   .detail = "listening; audit trail open"});
  }

  if (!options.port_file.empty()) {
    std::string ports = absl::StrCat(port, "\n", metrics.port(), "\n");
    if (dicom_scp) absl::StrAppend(&ports, dicom_scp->port(), "\n");
    if (status_page) {
      if (!dicom_scp) ports += "0\n";
      absl::StrAppend(&ports, status_page->port(), "\n");
    }
    if (absl::Status s = WriteFileAtomically(options.port_file, ports);
        !s.ok()) {
      spdlog::error("cannot write the port file: {}", std::string(s.message()));
    }
  }

  // The drain runs here, on an ordinary thread, never in a signal handler.
  std::thread signal_thread([&] {
    int signal_number = 0;
    int generation = 1;
    metrics.DicomConfigGeneration(generation);
    while (sigwait(&signals, &signal_number) == 0 && signal_number == SIGHUP) {
      if (assembler == nullptr) {
        spdlog::info("SIGHUP: no DICOM listener, nothing to reload");
        continue;
      }
      absl::Status reloaded = ReloadDicomConfig(options, assembler.get(),
                                                dicom_scp.get(), outbox.get());
      if (reloaded.ok()) {
        ++generation;
        metrics.DicomConfigGeneration(generation);
        spdlog::info(
            "SIGHUP: dicom: peers and rules reloaded; configuration "
            "generation {} is live",
            generation);
        if (audit != nullptr) {
          audit->Record({.event = "config.reloaded",
                         .count = generation,
                         .detail = "peers and rules reloaded (SIGHUP)"});
        }
      } else {
        metrics.DicomEvent("config_reload_refused");
        spdlog::error(
            "SIGHUP: dicom: reload refused, configuration generation {} stays "
            "live: {}",
            generation, LogSafe(std::string(reloaded.message())));
        if (audit != nullptr) {
          audit->Record(
              {.event = "config.reloaded",
               .outcome = AuditOutcome::kMinorFailure,
               .count = generation,
               .detail = absl::StrCat("reload refused, generation ", generation,
                                      " stays live: ", reloaded.message())});
        }
      }
    }
    spdlog::info("{}: draining (grace {} s): health NOT_SERVING, no new jobs",
                 signal_number == SIGTERM ? "SIGTERM" : "SIGINT",
                 options.drain_grace_seconds);
    health->SetServingStatus(false);
    health->SetServingStatus("interslice.v1.InterSlice", false);
    // No new jobs from here on, from DICOM either: the manager refuses them
    // and the assembler stops completing series before the listener waits
    // for the associations in progress (bounded by the DIMSE timeout); what
    // they store is kept and completed after a restart.
    manager.BeginDrain();
    if (assembler) assembler->Stop();
    if (dicom_scp) dicom_scp->Stop();
    manager.Shutdown(std::chrono::milliseconds(
        static_cast<int64_t>(options.drain_grace_seconds * 1000)));
    // Deliveries still PENDING stay in the spool records for the restart.
    if (outbox != nullptr) outbox->Stop();
    spdlog::info("jobs stopped; closing connections");
    server->Shutdown(std::chrono::system_clock::now() +
                     std::chrono::seconds(2));
  });
  server->Wait();
  signal_thread.join();
  spdlog::info("stopped");
  if (audit != nullptr) {
    audit->Record({.event = "server.stopped",
                   .source = options.advertise,
                   .detail = "drained and stopped"});
  }
  return 0;
}

int CheckConfig(const ServerOptions& options) {
  int problems = 0;
  auto problem = [&problems](const std::string& line) {
    ++problems;
    std::fprintf(stderr, "interslice-server: problem: %s\n", line.c_str());
  };
  QuietDicomToolkitLogging();
  absl::StatusOr<DicomConfig> config = LoadDicomConfig(options);
  std::vector<dicom::DicomPeer> peers = options.dicom_peers;
  if (!config.ok()) {
    problem(std::string(config.status().message()));
    // The peers are still worth an echo when their own file is valid.
    if (!options.dicom_peers_file.empty()) {
      absl::StatusOr<std::vector<dicom::DicomPeer>> file =
          dicom::LoadPeersFile(options.dicom_peers_file);
      if (file.ok()) peers.insert(peers.end(), file->begin(), file->end());
    }
  } else {
    if (!options.dicom_peers_file.empty()) {
      std::printf("peers file %s: %zu peer(s)%s\n",
                  options.dicom_peers_file.c_str(), config->peers.peers.size(),
                  config->peers.accept_unknown_callers
                      ? ", unknown callers accepted"
                      : "");
    }
    peers.insert(peers.end(), config->peers.peers.begin(),
                 config->peers.peers.end());
    if (!options.dicom_listen.empty()) {
      std::printf("listening for DICOM on %s as %s\n",
                  options.dicom_listen.c_str(),
                  absl::StrJoin(config->ae_titles, ", ").c_str());
    }
    if (options.rules_file.empty()) {
      std::printf("no --rules: received series make no jobs\n");
    } else {
      std::printf(
          "rules file %s: %zu rule(s), stable_seconds %g; the first "
          "that matches wins\n",
          options.rules_file.c_str(), config->rules.rules.size(),
          config->rules.stable_seconds);
      for (size_t i = 0; i < config->rules.rules.size(); ++i) {
        const dicom::Rule& rule = config->rules.rules[i];
        std::printf("  rule '%s' (#%zu): %s\n", rule.name.c_str(), i + 1,
                    DescribeRule(rule).c_str());
      }
    }
  }
  // What the start would refuse (server.cc's Run), said here too.
  if (absl::Status s = CheckMoveDestination(options.dicom_listen, peers);
      !s.ok()) {
    problem(std::string(s.message()));
  }
  const std::string calling = CallingAeTitle(options);
  for (const dicom::DicomPeer& peer : peers) {
    absl::Status echo =
        dicom::EchoPeer(peer, calling, DicomTls(options), kEchoTimeoutSeconds);
    if (echo.ok()) {
      if (peer.type == dicom::PeerType::kDicomWeb) {
        std::printf("  %s: QIDO-RS answered\n", dicom::PeerLabel(peer).c_str());
      } else {
        std::printf("  %s: C-ECHO answered (calling as %s)\n",
                    dicom::PeerLabel(peer).c_str(), calling.c_str());
      }
    } else {
      problem(std::string(echo.message()));
    }
  }
  if (problems > 0) {
    std::fprintf(stderr, "interslice-server: --check-config: %d problem(s)\n",
                 problems);
    return 1;
  }
  std::printf("configuration OK\n");
  return 0;
}

}  // namespace interslice::server
