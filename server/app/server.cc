#include "server/app/server.h"

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
#include <string_view>
#include <thread>
#include <utility>

#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/health_check_service_interface.h"
#include "server/app/logging.h"
#include "server/app/node_config.h"
#include "server/base/audit.h"
#include "server/base/executor.h"
#include "server/base/identity.h"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "server/engine/job_manager.h"
#include "server/engine/spool.h"
#include "server/net/dicomweb/stow.h"
#include "server/net/dimse/pending_moves.h"
#include "server/net/dimse/storage_scp.h"
#include "server/net/grpc/forwarding.h"
#include "server/net/grpc/service.h"
#include "server/net/http/http_handler.h"
#include "server/net/http/status_page.h"
#include "server/node/outbox.h"
#include "server/node/peer_registry.h"
#include "server/node/series_assembler.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace {

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

// /dicomweb on a server without a DICOM node: 404 before authentication,
// saying what would serve STOW-RS.
class StowNotServed : public HttpRequestHandler {
 public:
  std::string_view name() const override { return "STOW-RS"; }
  std::optional<HttpServerResponse> Screen(std::string_view,
                                           std::string_view) const override {
    return Answer();
  }
  HttpServerResponse Serve(const HttpServerRequest&) const override {
    return Answer();
  }

 private:
  static HttpServerResponse Answer() {
    return {.status = 404,
            .body =
                "not found: STOW-RS is served with the DICOM node "
                "(--dicom-listen)\n"};
  }
};

// The running daemon: every part, started in order by Start() and stopped
// in reverse by the drain and the destructor. The members are declared in
// the order they start, so that each outlives what uses it (the audit trail
// outlives everything it records; the outbox stops before the manager whose
// jobs it reports to; the HTTP listener stops before what it reads).
class ServerRuntime {
 public:
  ServerRuntime(ServerOptions options, sigset_t signals)
      : options_(std::move(options)), signals_(signals) {}

  // Every part, in order; the first error stops the start (and what was
  // started stops as the runtime is destroyed).
  absl::Status Start();
  // Until SIGTERM or SIGINT (SIGHUP reloads the DICOM node's files), then
  // the drain.
  void ServeUntilStopped();

 private:
  absl::Status CheckOptions();
  absl::Status LoadAuthentication();
  absl::Status OpenStorage();
  void MakeManager();
  absl::Status StartPeers();
  void CheckPeersInBackground();
  absl::Status StartDicomNode();
  absl::Status StartGrpc();
  absl::Status StartHttp();
  StatusSnapshot Snapshot();
  void WritePortFile();
  // SIGHUP: the DICOM node's files again (ReloadDicomConfig).
  void Reload(int* generation);
  // SIGTERM/SIGINT: no new jobs from any door, running jobs get the grace
  // period, then everything stops.
  void Drain(int signal_number);

  ServerOptions options_;
  const sigset_t signals_;
  std::vector<NamedToken> tokens_;
  std::shared_ptr<grpc::ServerCredentials> credentials_;
  std::shared_ptr<grpc::ChannelCredentials> peer_credentials_ =
      grpc::InsecureChannelCredentials();
  Metrics metrics_;
  std::unique_ptr<Spool> spool_;
  // Opened before anything it records starts, and destroyed (its queue
  // written) after everything has stopped.
  std::unique_ptr<AuditLog> audit_;
  // The C-MOVEs in progress: before the manager and the listener, which
  // use it, so it outlives both.
  dimse::PendingMoves pending_moves_;
  std::unique_ptr<JobManager> manager_;
  // The DICOM peers, read once (the registry, replaced on SIGHUP), and the
  // outbox for their results (after the manager, so stopped before it).
  node::PeersConfig peers_config_;
  std::unique_ptr<node::PeerRegistry> peers_;
  std::unique_ptr<node::DeliveryQueue> outbox_;
  // Joined before the metrics go.
  std::jthread peer_check_;
  std::unique_ptr<node::SeriesAssembler> assembler_;
  std::unique_ptr<dimse::StorageScp> dicom_scp_;
  std::unique_ptr<Executor> io_;
  ServiceOptions service_options_;
  std::unique_ptr<Authenticator> page_auth_;
  std::unique_ptr<InterSliceService> service_;
  std::unique_ptr<Forwarder> forwarder_;
  std::unique_ptr<grpc::Server> grpc_server_;
  int grpc_port_ = 0;
  // The status page and the handler of its /dicomweb route (STOW-RS, or
  // a 404 without a DICOM node): stopped before what they read.
  std::unique_ptr<dicomweb::StowReceiver> stow_;
  std::unique_ptr<HttpRequestHandler> stow_not_served_;
  std::unique_ptr<StatusServer> status_page_;
};

absl::Status ServerRuntime::Start() {
  if (absl::Status s = CheckOptions(); !s.ok()) return s;
  if (absl::Status s = LoadAuthentication(); !s.ok()) return s;
  QuietDicomToolkitLogging();
  if (absl::Status s = OpenStorage(); !s.ok()) return s;
  MakeManager();
  if (absl::Status s = StartPeers(); !s.ok()) return s;
  if (absl::Status s = manager_->Recover(); !s.ok()) return s;
  // The workers start after the DICOM listener (below): a recovered job
  // that pulls by C-MOVE needs the listener as its move destination.
  if (outbox_ != nullptr) outbox_->Start();
  CheckPeersInBackground();
  if (absl::Status s = StartDicomNode(); !s.ok()) return s;
  manager_->Start();
  if (absl::Status s = StartGrpc(); !s.ok()) return s;
  if (absl::Status s = StartHttp(); !s.ok()) return s;
  if (audit_ != nullptr) {
    audit_->Record({.event = "server.started",
                    .source = options_.advertise,
                    .detail = "listening; audit trail open"});
  }
  WritePortFile();
  return absl::OkStatus();
}

absl::Status ServerRuntime::CheckOptions() {
  ServerOptions& o = options_;
  if (o.spool.empty()) return absl::InvalidArgumentError("--spool is required");
  const int cpus = AvailableCpus();
  if (o.workers <= 0) o.workers = std::max(1, cpus / 4);
  if (o.threads_per_job <= 0) o.threads_per_job = std::max(1, cpus / o.workers);
  if (o.max_queued_jobs < 0 || o.max_chunk_bytes < 1024 ||
      o.max_chunk_bytes > (4 << 20) - 1024) {
    return absl::InvalidArgumentError(
        "--max-queued must be >= 0 and --max-chunk-bytes in [1 KiB, 4 MiB)");
  }
  if (o.max_concurrent_uploads <= 0) {
    o.max_concurrent_uploads = std::max(1, 2 * o.max_queued_jobs);
  }
  if (o.max_uploads_per_peer < 1 || !(o.upload_idle_timeout_seconds >= 0) ||
      !(o.upload_timeout_seconds >= 0)) {
    return absl::InvalidArgumentError(
        "--max-uploads-per-peer must be >= 1, --upload-idle-timeout and "
        "--upload-timeout >= 0");
  }
  if (!o.advertise.empty() && !IsReplicaAddress(o.advertise)) {
    return absl::InvalidArgumentError(
        absl::StrCat("--advertise ", LogSafe(o.advertise),
                     " is not HOST:PORT (a DNS name, IPv4 address or "
                     "[IPv6] address, and a port)"));
  }
  return absl::OkStatus();
}

// Tokens, admin identities and the TLS credentials of the gRPC port and of
// the calls to other replicas.
absl::Status ServerRuntime::LoadAuthentication() {
  const ServerOptions& o = options_;
  if (!o.auth_token_file.empty()) {
    absl::StatusOr<std::string> t =
        ReadFile(o.auth_token_file, "the token file");
    if (!t.ok()) return t.status();
    absl::StatusOr<std::vector<NamedToken>> parsed = ParseTokenFile(*t);
    if (!parsed.ok()) return parsed.status();
    tokens_ = *std::move(parsed);
  }
  for (const std::string& admin : o.admin_identities) {
    if (tokens_.empty() && o.tls_client_ca.empty()) {
      return absl::InvalidArgumentError(
          "--admin-identity needs --auth-token-file or --tls-client-ca");
    }
    // With tokens the identity is always a token's name: catch typos.
    const bool known =
        std::any_of(tokens_.begin(), tokens_.end(),
                    [&](const NamedToken& t) { return t.name == admin; });
    if (!tokens_.empty() && !known) {
      return absl::InvalidArgumentError(
          absl::StrCat("--admin-identity ", LogSafe(admin),
                       " is not a name in the token file"));
    }
  }
  if (o.tls_cert.empty() && o.tls_key.empty()) {
    if (!o.tls_client_ca.empty()) {
      return absl::InvalidArgumentError(
          "--tls-client-ca needs --tls-cert and --tls-key");
    }
    credentials_ = grpc::InsecureServerCredentials();
    return absl::OkStatus();
  }
  absl::StatusOr<std::string> cert = ReadFile(o.tls_cert, "--tls-cert");
  if (!cert.ok()) return cert.status();
  absl::StatusOr<std::string> key = ReadFile(o.tls_key, "--tls-key");
  if (!key.ok()) return key.status();
  grpc::SslServerCredentialsOptions ssl(
      GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
  ssl.pem_key_cert_pairs.push_back({*key, *cert});
  if (!o.tls_client_ca.empty()) {
    absl::StatusOr<std::string> ca =
        ReadFile(o.tls_client_ca, "--tls-client-ca");
    if (!ca.ok()) return ca.status();
    ssl.pem_root_certs = *ca;
    ssl.client_certificate_request =
        GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  credentials_ = grpc::SslServerCredentials(ssl);
  grpc::SslCredentialsOptions peer_ssl;
  if (!o.peer_tls_ca.empty()) {
    absl::StatusOr<std::string> ca = ReadFile(o.peer_tls_ca, "--peer-tls-ca");
    if (!ca.ok()) return ca.status();
    peer_ssl.pem_root_certs = *ca;
  }
  if (!o.tls_client_ca.empty()) {
    peer_ssl.pem_cert_chain = *cert;
    peer_ssl.pem_private_key = *key;
  }
  peer_credentials_ = grpc::SslCredentials(peer_ssl);
  return absl::OkStatus();
}

// The metrics endpoint, the spool and the audit trail.
absl::Status ServerRuntime::OpenStorage() {
  if (!options_.metrics_listen.empty()) {
    if (absl::Status s = metrics_.Serve(options_.metrics_listen); !s.ok()) {
      return s;
    }
  }
  absl::StatusOr<std::unique_ptr<Spool>> spool =
      Spool::Open(options_.spool, options_.spool_quota_bytes);
  if (!spool.ok()) return spool.status();
  spool_ = *std::move(spool);
  if (!options_.audit_log.empty()) {
    absl::StatusOr<std::unique_ptr<AuditLog>> opened =
        AuditLog::Open({.path = options_.audit_log,
                        .max_bytes = options_.audit_max_bytes,
                        .keep = options_.audit_keep});
    if (!opened.ok()) return opened.status();
    audit_ = *std::move(opened);
  }
  return absl::OkStatus();
}

void ServerRuntime::MakeManager() {
  ManagerOptions m;
  m.workers = options_.workers;
  m.threads_per_job = options_.threads_per_job;
  m.max_queued_jobs = options_.max_queued_jobs;
  m.max_upload_bytes = options_.max_upload_bytes;
  m.max_output_voxels = options_.max_output_voxels;
  m.retention_seconds = options_.retention_seconds;
  m.isolate_jobs = options_.isolation == "process";
  m.max_attempts = options_.max_attempts;
  m.audit = audit_.get();
  manager_ = std::make_unique<JobManager>(m, spool_.get(), &metrics_);
}

// The peers file, read once: the peer registry (each peer's client) and the
// outbox, handed to the manager for JobSpec.send_to and pacs_source.
absl::Status ServerRuntime::StartPeers() {
  absl::StatusOr<node::PeersConfig> loaded = LoadPeers(options_);
  if (!loaded.ok()) return loaded.status();
  peers_config_ = *std::move(loaded);
  if (absl::Status s =
          CheckMoveDestination(options_.dicom_listen, peers_config_.peers);
      !s.ok()) {
    return s;
  }
  if (options_.dicom_peers_file.empty()) return absl::OkStatus();
  if (!options_.dicom_ae_titles.empty()) {
    absl::StatusOr<std::string> ae =
        node::NormalizeAeTitle(options_.dicom_ae_titles.front());
    if (!ae.ok()) return ae.status();
  }
  dimse::MoveDestination move_destination;
  if (!options_.dicom_listen.empty()) {
    move_destination = {.ae_title = CallingAeTitle(options_),
                        .pending_moves = &pending_moves_};
  }
  peers_ = std::make_unique<node::PeerRegistry>(
      MakePeerClientFactory(PeerSettings(options_), move_destination),
      peers_config_);
  node::DeliveryOptions delivery;
  auto ms = [](double seconds) {
    return std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000));
  };
  delivery.initial_backoff = ms(options_.delivery_retry_seconds);
  delivery.max_backoff = ms(options_.delivery_retry_max_seconds);
  delivery.give_up_after = ms(options_.delivery_give_up_seconds);
  node::DeliveryCounters counters;
  counters.sent = [this](const std::string& peer, int n) {
    metrics_.DicomInstancesSent(peer, n);
  };
  counters.failed = [this](const std::string& peer, int n) {
    metrics_.DicomInstancesFailed(peer, n);
  };
  outbox_ = std::make_unique<node::DeliveryQueue>(
      peers_.get(), delivery,
      [this](const std::string& job_id, const v1::Delivery& d) {
        manager_->UpdateDelivery(job_id, d);
      },
      counters);
  manager_->SetPeerServices(outbox_.get(), peers_.get());
  return absl::OkStatus();
}

// A wrong host, port or AE title of a peer shows at start (a warning and
// interslice_dicom_peer_reachable{peer} 0), not after a day of delivery
// retries. Off the start-up path: a silent peer costs its timeout here only.
void ServerRuntime::CheckPeersInBackground() {
  if (peers_ == nullptr) return;
  peer_check_ = std::jthread([clients = peers_->clients(),
                              this](std::stop_token stop) {
    for (const std::shared_ptr<node::PeerClient>& peer : clients) {
      if (stop.stop_requested()) return;
      absl::Status echo = peer->Echo();
      metrics_.DicomPeerReachable(peer->name(), echo.ok());
      if (echo.ok()) {
        spdlog::info("dicom: {} answered {}",
                     LogSafe(node::PeerLabel(peer->peer())), peer->EchoName());
      } else {
        spdlog::warn(
            "dicom: {} did not answer {} at start-up ({}); deliveries to it "
            "will be retried",
            LogSafe(node::PeerLabel(peer->peer())), peer->EchoName(),
            LogSafe(std::string(echo.message())));
      }
    }
  });
}

// The DICOM listener and its series assembler: configuration errors stop
// the start-up with the file's one-line message.
absl::Status ServerRuntime::StartDicomNode() {
  if (options_.dicom_listen.empty()) return absl::OkStatus();
  absl::StatusOr<DicomConfig> config = LoadDicomConfig(options_, peers_config_);
  if (!config.ok()) return config.status();
  absl::StatusOr<std::unique_ptr<node::SeriesAssembler>> assembler =
      StartDicomAssembler(options_, std::move(config->rules), spool_.get(),
                          &metrics_, manager_.get());
  if (!assembler.ok()) return assembler.status();
  assembler_ = *std::move(assembler);
  absl::StatusOr<std::unique_ptr<dimse::StorageScp>> scp =
      StartDicomListener(options_, std::move(config->peers), assembler_.get(),
                         &metrics_, audit_.get(), &pending_moves_);
  if (!scp.ok()) return scp.status();
  dicom_scp_ = *std::move(scp);
  assembler_->Start();
  return absl::OkStatus();
}

absl::Status ServerRuntime::StartGrpc() {
  const ServerOptions& o = options_;
  io_ = std::make_unique<Executor>(o.io_threads);
  // The status page authenticates by the same tokens and admin identities.
  page_auth_ = std::make_unique<Authenticator>(tokens_, o.admin_identities);
  service_options_.tokens = tokens_;
  service_options_.admin_identities = o.admin_identities;
  service_options_.max_chunk_bytes = o.max_chunk_bytes;
  service_options_.uploads.max_concurrent = o.max_concurrent_uploads;
  service_options_.uploads.max_per_peer = o.max_uploads_per_peer;
  service_options_.uploads.idle_timeout_seconds = o.upload_idle_timeout_seconds;
  service_options_.uploads.total_timeout_seconds = o.upload_timeout_seconds;
  service_options_.audit = audit_.get();
  service_ = std::make_unique<InterSliceService>(
      service_options_, manager_.get(), spool_.get(), io_.get(), &metrics_);
  forwarder_ = std::make_unique<Forwarder>(peer_credentials_);
  service_->set_forwarder(forwarder_.get());
  service_->set_assembler(assembler_.get());
  service_->set_peers(peers_.get());
  if (o.reflection) {
    // Linking gRPC's reflection library registers the service in every
    // server through a static initialiser, so it is loaded only on request.
    if (dlopen("libgrpc++_reflection.so.1.51", RTLD_NOW | RTLD_GLOBAL) ==
        nullptr) {
      return absl::UnavailableError(
          absl::StrCat("cannot load gRPC reflection: ", dlerror()));
    }
  }
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  builder.AddListeningPort(o.listen, credentials_, &grpc_port_);
  builder.RegisterService(service_.get());
  builder.SetMaxReceiveMessageSize(4 << 20);
  grpc_server_ = builder.BuildAndStart();
  if (!grpc_server_ || grpc_port_ == 0) {
    return absl::UnavailableError(absl::StrCat("cannot listen on ", o.listen));
  }
  if (options_.advertise.empty()) {
    options_.advertise =
        absl::StrCat(o.listen.substr(0, o.listen.rfind(':')), ":", grpc_port_);
  }
  forwarder_->SetAdvertise(options_.advertise);
  manager_->SetJobIdSuffix(JobIdSuffix(options_.advertise));
  spdlog::info("advertised as {}: jobs accepted here are named for it",
               LogSafe(options_.advertise));
  grpc::HealthCheckServiceInterface* health =
      grpc_server_->GetHealthCheckService();
  health->SetServingStatus(true);
  health->SetServingStatus("interslice.v1.InterSlice", true);
  spdlog::info(
      "listening on {} (port {}, {}{}); {} worker(s) x {} thread(s), queue "
      "{}, spool {}{}",
      o.listen, grpc_port_, o.tls_cert.empty() ? "plaintext" : "TLS",
      o.tls_client_ca.empty() ? "" : ", client certificates required",
      o.workers, o.threads_per_job, o.max_queued_jobs, o.spool,
      o.reflection ? ", reflection on" : "");
  if (!o.metrics_listen.empty()) {
    spdlog::info("metrics on {} (port {})", o.metrics_listen, metrics_.port());
  }
  return absl::OkStatus();
}

// What the status page shows, read when a request comes.
StatusSnapshot ServerRuntime::Snapshot() {
  StatusSnapshot s;
  s.version = service_options_.version;
  s.now_unix_ms = std::chrono::duration_cast<std::chrono::milliseconds>(
                      std::chrono::system_clock::now().time_since_epoch())
                      .count();
  s.jobs = manager_->List(true, nullptr);
  s.queued = manager_->queued();
  s.running = manager_->running();
  s.spool_used_bytes = spool_->used_bytes();
  s.spool_quota_bytes = spool_->quota_bytes();
  if (peers_ != nullptr) {
    for (const std::shared_ptr<node::PeerClient>& p : peers_->clients()) {
      const node::PeerSummary summary = p->Summary();
      s.peers.push_back({.name = summary.name,
                         .ae_title = summary.ae_title,
                         .address = summary.address,
                         .tls = summary.tls});
    }
  }
  if (assembler_ != nullptr) {
    // The generation live now (SIGHUP may replace it).
    const std::shared_ptr<const node::RuleSet> rules = assembler_->rules();
    s.rules_file = rules->path;
    for (const node::Rule& r : rules->rules) {
      s.rules.push_back(
          {.name = r.name, .match = r.match.Describe(), .send_to = r.send_to});
    }
    for (const node::KeptSeries& k : assembler_->WaitingSeries()) {
      s.series.push_back({.state = k.state,
                          .calling_ae = k.calling_ae,
                          .called_ae = k.called_ae,
                          .instances = k.instances,
                          .since_unix_ms = k.kept_since_unix_ms,
                          .why = k.why});
    }
  }
  return s;
}

// The status page (docs/status-page.md) and STOW-RS (docs/dicomweb.md).
absl::Status ServerRuntime::StartHttp() {
  const ServerOptions& o = options_;
  if (assembler_ != nullptr && !o.status_listen.empty()) {
    stow_ = std::make_unique<dicomweb::StowReceiver>(
        dicomweb::StowOptions{
            .called_ae = CallingAeTitle(o),
            .max_body_bytes = o.stow_max_body_bytes,
            .refuse_anonymous =
                !page_auth_->tokens_required() && !o.tls_client_ca.empty(),
            .metrics = &metrics_},
        assembler_.get(), spool_.get(), audit_.get());
  }
  if (o.status_listen.empty()) {
    if (!o.http_tls_cert.empty() || !o.http_tls_key.empty()) {
      return absl::InvalidArgumentError(
          "--http-tls-cert and --http-tls-key need --http-listen");
    }
    return absl::OkStatus();
  }
  const HttpRequestHandler* dicomweb = stow_.get();
  if (dicomweb == nullptr) {
    stow_not_served_ = std::make_unique<StowNotServed>();
    dicomweb = stow_not_served_.get();
  }
  absl::StatusOr<std::unique_ptr<StatusServer>> started = StatusServer::Start(
      {.listen = o.status_listen,
       .max_connections = o.http_max_connections,
       .request_timeout_seconds = o.http_request_timeout_seconds,
       .tls_certificate = o.http_tls_cert,
       .tls_private_key = o.http_tls_key,
       .metrics = &metrics_},
      [this] { return Snapshot(); }, page_auth_.get(), audit_.get(),
      {{.prefix = "/dicomweb", .handler = dicomweb}});
  if (!started.ok()) return started.status();
  status_page_ = *std::move(started);
  spdlog::info("status page on {} (port {}, {}){}{}", o.status_listen,
               status_page_->port(), status_page_->tls() ? "HTTPS" : "HTTP",
               page_auth_->tokens_required()
                   ? ": admin identities only"
                   : ": open to anyone who reaches it (no tokens)",
               stow_ != nullptr
                   ? absl::StrCat("; STOW-RS at /dicomweb/studies as ",
                                  CallingAeTitle(o), ", bodies up to ",
                                  stow_->max_body_bytes(), " bytes")
                   : "");
  return absl::OkStatus();
}

// "<grpc port>\n<metrics port>\n", then the DICOM port (0 without a
// listener when the HTTP port follows) and the HTTP port.
void ServerRuntime::WritePortFile() {
  if (options_.port_file.empty()) return;
  std::string ports = absl::StrCat(grpc_port_, "\n", metrics_.port(), "\n");
  if (dicom_scp_) absl::StrAppend(&ports, dicom_scp_->port(), "\n");
  if (status_page_) {
    if (!dicom_scp_) ports += "0\n";
    absl::StrAppend(&ports, status_page_->port(), "\n");
  }
  if (absl::Status s = WriteFileAtomically(options_.port_file, ports);
      !s.ok()) {
    spdlog::error("cannot write the port file: {}", std::string(s.message()));
  }
}

void ServerRuntime::Reload(int* generation) {
  if (assembler_ == nullptr) {
    spdlog::info("SIGHUP: no DICOM listener, nothing to reload");
    return;
  }
  absl::Status reloaded = ReloadDicomConfig(options_, assembler_.get(),
                                            dicom_scp_.get(), peers_.get());
  if (reloaded.ok()) {
    ++*generation;
    metrics_.DicomConfigGeneration(*generation);
    spdlog::info(
        "SIGHUP: dicom: peers and rules reloaded; configuration generation {} "
        "is live",
        *generation);
    if (audit_ != nullptr) {
      audit_->Record({.event = "config.reloaded",
                      .count = *generation,
                      .detail = "peers and rules reloaded (SIGHUP)"});
    }
    return;
  }
  metrics_.DicomEvent("config_reload_refused");
  spdlog::error(
      "SIGHUP: dicom: reload refused, configuration generation {} stays live: "
      "{}",
      *generation, LogSafe(std::string(reloaded.message())));
  if (audit_ != nullptr) {
    audit_->Record(
        {.event = "config.reloaded",
         .outcome = AuditOutcome::kMinorFailure,
         .count = *generation,
         .detail = absl::StrCat("reload refused, generation ", *generation,
                                " stays live: ", reloaded.message())});
  }
}

void ServerRuntime::Drain(int signal_number) {
  spdlog::info("{}: draining (grace {} s): health NOT_SERVING, no new jobs",
               signal_number == SIGTERM ? "SIGTERM" : "SIGINT",
               options_.drain_grace_seconds);
  grpc::HealthCheckServiceInterface* health =
      grpc_server_->GetHealthCheckService();
  health->SetServingStatus(false);
  health->SetServingStatus("interslice.v1.InterSlice", false);
  // No new jobs from here on, from DICOM either: the manager refuses them
  // and the assembler stops completing series before the listener waits
  // for the associations in progress (bounded by the DIMSE timeout); what
  // they store is kept and completed after a restart.
  manager_->BeginDrain();
  if (assembler_) assembler_->Stop();
  if (dicom_scp_) dicom_scp_->Stop();
  manager_->Shutdown(std::chrono::milliseconds(
      static_cast<int64_t>(options_.drain_grace_seconds * 1000)));
  // Deliveries still PENDING stay in the spool records for the restart.
  if (outbox_ != nullptr) outbox_->Stop();
  spdlog::info("jobs stopped; closing connections");
  grpc_server_->Shutdown(std::chrono::system_clock::now() +
                         std::chrono::seconds(2));
}

void ServerRuntime::ServeUntilStopped() {
  // The drain runs here, on an ordinary thread, never in a signal handler.
  std::thread signal_thread([this] {
    int signal_number = 0;
    int generation = 1;
    metrics_.DicomConfigGeneration(generation);
    while (sigwait(&signals_, &signal_number) == 0 && signal_number == SIGHUP) {
      Reload(&generation);
    }
    Drain(signal_number);
  });
  grpc_server_->Wait();
  signal_thread.join();
  spdlog::info("stopped");
  if (audit_ != nullptr) {
    audit_->Record({.event = "server.stopped",
                    .source = options_.advertise,
                    .detail = "drained and stopped"});
  }
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
  sigaddset(&signals, SIGHUP);  // reloads the DICOM node's files
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  // Uploads, records and the artifacts the core writes: owner only.
  ::umask(077);
  if (absl::Status s = SetUpLogging(options); !s.ok()) {
    std::fprintf(stderr, "interslice-server: error: %s\n",
                 std::string(s.message()).c_str());
    return 1;
  }
  ServerRuntime server(std::move(options), signals);
  if (absl::Status s = server.Start(); !s.ok()) {
    spdlog::critical("{}", std::string(s.message()));
    std::fprintf(stderr, "interslice-server: error: %s\n",
                 std::string(s.message()).c_str());
    return 1;
  }
  server.ServeUntilStopped();
  return 0;
}

}  // namespace interslice::server
