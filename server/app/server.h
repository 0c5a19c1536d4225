// The daemon: options, start-up, and the SIGTERM drain.
#ifndef INTERSLICE_SERVER_APP_SERVER_H_
#define INTERSLICE_SERVER_APP_SERVER_H_

#include <cstdint>
#include <string>
#include <vector>

namespace interslice::server {

struct ServerOptions {
  std::string listen = "0.0.0.0:50051";  // HOST:PORT; port 0 picks one
  // HOST:PORT other replicas reach this one at; new job ids name it and
  // calls for other replicas' jobs are forwarded
  // (server/net/grpc/forwarding.h). Empty: the listen address with the bound
  // port.
  std::string advertise;
  // With TLS: the CA certificate(s) that verify other replicas (empty: the
  // system's roots). With --tls-client-ca, this server's own certificate is
  // presented to them.
  std::string peer_tls_ca;
  std::string spool;  // required
  // 0 = from the CPU count (cgroup limits honoured): workers = max(1,
  // cpus / 4), threads_per_job = max(1, cpus / workers).
  int workers = 0;
  int threads_per_job = 0;
  int max_queued_jobs = 16;
  // Uploads in progress (not queued yet): in all (0 = 2 x max_queued_jobs),
  // and from one client (identity, else IP address).
  int max_concurrent_uploads = 0;
  int max_uploads_per_peer = 4;
  // Cancel an upload after this long without data / this long in all;
  // 0 = never.
  double upload_idle_timeout_seconds = 30;
  double upload_timeout_seconds = 3600;
  int64_t max_upload_bytes = int64_t{2} << 30;
  int64_t max_output_voxels = int64_t{1} << 30;
  int64_t spool_quota_bytes = int64_t{20} << 30;
  int64_t retention_seconds = 24 * 3600;
  int max_chunk_bytes = 1 << 20;
  int io_threads = 2;
  std::string tls_cert, tls_key, tls_client_ca;
  std::string auth_token_file;  // "TOKEN", or lines "NAME:TOKEN"
  std::vector<std::string> admin_identities;
  std::string metrics_listen;  // empty = no metrics endpoint
  bool reflection = false;
  std::string log_format = "text";  // text | json
  std::string log_level = "info";
  double drain_grace_seconds = 30;
  // "process" (default): each job's compute runs in a supervised worker
  // process, so a crash inside a decoder fails that job only; "thread": in
  // this process (one crash takes every job down).
  std::string isolation = "process";
  // Starts of a detached job interrupted by a server stop, in all.
  int max_attempts = 3;
  // Outbox retries: the first wait, doubled per failure up to the cap; a
  // delivery fails for good after give-up seconds without success.
  double delivery_retry_seconds = 2;
  double delivery_retry_max_seconds = 300;
  double delivery_give_up_seconds = 24 * 3600;
  // After start-up, "<grpc port>\n<metrics port>\n" is written here
  // (atomically), for tests and scripts that listen on port 0; with a DICOM
  // listener, "<dicom port>\n" follows.
  std::string port_file;
  // The audit trail (server/base/audit.h, docs/audit.md): empty = none.
  std::string audit_log;
  // The status page (server/net/http/status_page.h): HOST:PORT, port 0 picks
  // one (written to the port file after the DICOM port, 0 when there is no
  // DICOM listener); empty = none.
  std::string status_listen;
  // That HTTP listener (--http-listen is the same flag): requests served at
  // once, and the timeout that cuts off a client sending nothing.
  int http_max_connections = 4;
  double http_request_timeout_seconds = 10;
  // STOW-RS on it (server/net/dicomweb/stow.h; with a DICOM listener only): the
  // largest request body, 0 = dicom_max_series_bytes.
  int64_t stow_max_body_bytes = 0;
  // HTTPS for that listener (PEM files): both or neither.
  std::string http_tls_cert, http_tls_key;
  int64_t audit_max_bytes = int64_t{64} << 20;
  int audit_keep = 10;

  // The DICOM node's receiving side (server/node/, server/net/dimse/;
  // docs/dicom-node.md).
  // Empty dicom_listen: no DICOM listener. "HOST:PORT"; port 0 picks one.
  std::string dicom_listen;
  std::vector<std::string> dicom_ae_titles;  // empty: {"INTERSLICE"}
  std::string dicom_peers_file;  // YAML/JSON; see server/node/config.h
  std::string rules_file;        // YAML/JSON; see server/node/config.h
  int dicom_max_associations = 8;
  int dicom_max_associations_per_source = 0;  // 0: half of the above
  int dicom_max_pending = 64;
  int dicom_max_pending_per_source = 16;
  int64_t dicom_max_pdu = 65536;
  double dicom_acse_timeout_seconds = 10;
  double dicom_dimse_timeout_seconds = 60;
  double dicom_pdu_timeout_seconds = 30;
  int64_t dicom_max_series_instances = 10000;
  int64_t dicom_max_series_bytes = int64_t{4} << 30;
  // DICOM TLS: all three, or none. Peers must present a certificate signed
  // by a CA in dicom_tls_ca.
  std::string dicom_tls_cert, dicom_tls_key, dicom_tls_ca;
};

// CPUs this process may use: the affinity mask, capped by a cgroup v2
// cpu.max or v1 cfs quota when one is set.
int AvailableCpus();

// Runs until SIGTERM or SIGINT, then drains. Returns the exit code. Must be
// called before any other thread is started (it blocks the signals so that
// only its signal thread receives them).
int RunServer(ServerOptions options);

// `interslice-server --check-config`: loads the peers and rules files and
// checks them with the AE titles exactly as a start would, C-ECHOes every
// peer (as the first --dicom-ae, with the --dicom-tls-* files for tls peers),
// and prints what each rule would match to stdout. Each problem (an invalid
// file, a peer that does not answer) is one line on stderr. Returns 0 when
// there is none, 1 otherwise. Starts nothing and writes nothing.
int CheckConfig(const ServerOptions& options);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_APP_SERVER_H_
