// interslice-server: the gRPC daemon. Everything but option parsing lives in
// server/server.cc.
#include <cstdio>
#include <string>

#include "CLI/CLI.hpp"
#include "server/dicom/scu.h"
#include "server/job_worker.h"
#include "server/server.h"

int main(int argc, char** argv) {
  // Before any thread starts (it sets an environment variable that DCMTK
  // reads at each outgoing connection): see server/dicom/scu.h.
  interslice::server::dicom::DisableNagleOnOutgoingAssociations();
  // A job's worker process (server/job_worker.h): the server starts this
  // executable again with this one argument.
  if (argc == 2 && std::string(argv[1]) == "--job-worker") {
    return interslice::server::RunJobWorker(0, 1);
  }
  interslice::server::ServerOptions o;
  CLI::App app{"interslice-server: the interslice gRPC daemon"};
  app.set_version_flag("--version", "interslice-server 0.1.0");
  app.add_option("--listen", o.listen,
                 "HOST:PORT to listen on (port 0 picks one)")
      ->capture_default_str();
  app.add_option("--advertise", o.advertise,
                 "HOST:PORT other replicas and balanced clients reach this "
                 "server at (default: the listen address); job ids name it, "
                 "and calls for another replica's job are forwarded to the "
                 "replica its id names");
  app.add_option("--peer-tls-ca", o.peer_tls_ca,
                 "With TLS: CA certificate that verifies other replicas "
                 "(default: the system's roots)");
  app.add_option("--spool", o.spool,
                 "Folder for uploads and results (created if missing)")
      ->required();
  app.add_option("--workers", o.workers,
                 "Jobs run at once (0 = max(1, CPUs/4); cgroup limits count)")
      ->capture_default_str();
  app.add_option("--threads-per-job", o.threads_per_job,
                 "Solver threads per job (0 = CPUs / workers)")
      ->capture_default_str();
  app.add_option("--max-queued", o.max_queued_jobs,
                 "Jobs queued (upload complete, waiting for a worker); "
                 "beyond: RESOURCE_EXHAUSTED")
      ->capture_default_str();
  app.add_option("--max-concurrent-uploads", o.max_concurrent_uploads,
                 "Uploads in progress at once, in all (0 = 2 x --max-queued)")
      ->capture_default_str();
  app.add_option("--max-uploads-per-peer", o.max_uploads_per_peer,
                 "Uploads in progress at once from one client (its "
                 "authenticated identity, else its IP address)")
      ->capture_default_str();
  app.add_option("--upload-idle-timeout", o.upload_idle_timeout_seconds,
                 "Cancel an upload that sends no data for this many seconds "
                 "(0 = never)")
      ->capture_default_str();
  app.add_option("--upload-timeout", o.upload_timeout_seconds,
                 "Cancel an upload not complete after this many seconds "
                 "(0 = never)")
      ->capture_default_str();
  app.add_option("--max-upload-bytes", o.max_upload_bytes,
                 "Largest upload per job, bytes")
      ->capture_default_str();
  app.add_option("--max-voxels", o.max_output_voxels,
                 "Largest refined output grid per job, voxels")
      ->capture_default_str();
  app.add_option("--spool-quota-bytes", o.spool_quota_bytes,
                 "Disk space for uploads and results, bytes")
      ->capture_default_str();
  app.add_option("--retention", o.retention_seconds,
                 "Seconds finished detached jobs stay fetchable")
      ->capture_default_str();
  app.add_option("--max-chunk-bytes", o.max_chunk_bytes,
                 "Largest upload chunk accepted, bytes")
      ->capture_default_str();
  app.add_option("--io-threads", o.io_threads,
                 "Threads for spool reads and writes")
      ->capture_default_str();
  app.add_option("--tls-cert", o.tls_cert, "Server certificate (PEM)");
  app.add_option("--tls-key", o.tls_key, "Server private key (PEM)");
  app.add_option("--tls-client-ca", o.tls_client_ca,
                 "Require client certificates signed by this CA (mutual TLS)");
  app.add_option("--auth-token-file", o.auth_token_file,
                 "Require 'authorization: Bearer <token>' with a token from "
                 "this file: one token alone (identity 'default'), or lines "
                 "NAME:TOKEN ('#' comments); jobs belong to the NAME");
  app.add_option("--admin-identity", o.admin_identities,
                 "An identity (token NAME, or client certificate subject "
                 "such as CN=ops) that sees and may cancel every job; "
                 "repeatable");
  app.add_option("--metrics-listen", o.metrics_listen,
                 "HOST:PORT for Prometheus /metrics (off when empty)");
  app.add_option("--status-listen,--http-listen", o.status_listen,
                 "HOST:PORT of the HTTP server: the status page (/status: "
                 "jobs, peers, rules, spool; admin identities only when "
                 "tokens are used) and, with --dicom-listen, STOW-RS (POST "
                 "/dicomweb/studies); off when empty");
  app.add_option("--http-max-connections", o.http_max_connections,
                 "HTTP requests served at once (1-64)")
      ->capture_default_str();
  app.add_option("--http-request-timeout", o.http_request_timeout_seconds,
                 "Seconds an HTTP client may send nothing before it is cut "
                 "off")
      ->capture_default_str();
  app.add_option("--http-tls-cert", o.http_tls_cert,
                 "HTTPS for --http-listen: certificate chain (PEM)");
  app.add_option("--http-tls-key", o.http_tls_key,
                 "HTTPS for --http-listen: its private key (PEM)");
  app.add_option("--stow-max-body-bytes", o.stow_max_body_bytes,
                 "Largest STOW-RS request body (0: --dicom-max-series-bytes)")
      ->capture_default_str();
  app.add_option("--audit-log", o.audit_log,
                 "Append an audit trail here: JSON lines of job, delivery, "
                 "DICOM association and authentication events, no patient "
                 "data (docs/audit.md); off when empty");
  app.add_option("--audit-max-bytes", o.audit_max_bytes,
                 "Rotate the audit log at this size (PATH.1, PATH.2, ...)")
      ->capture_default_str();
  app.add_option("--audit-keep", o.audit_keep, "Rotated audit logs kept")
      ->capture_default_str();
  app.add_flag("--reflection", o.reflection, "Enable gRPC server reflection");
  app.add_option("--log-format", o.log_format, "text or json (JSON lines)")
      ->capture_default_str();
  app.add_option("--log-level", o.log_level,
                 "trace, debug, info, warn, error or off")
      ->capture_default_str();
  app.add_option("--drain-grace", o.drain_grace_seconds,
                 "Seconds running jobs may finish after SIGTERM before they "
                 "are cancelled")
      ->capture_default_str();
  app.add_option("--isolation", o.isolation,
                 "process: each job computes in a supervised worker process "
                 "(a crash fails that job only); thread: in the server "
                 "process")
      ->check(CLI::IsMember({"process", "thread"}))
      ->capture_default_str();
  app.add_option("--max-attempts", o.max_attempts,
                 "Starts of a detached job interrupted by a server stop "
                 "(kill, power cut) before it fails for good")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--delivery-retry", o.delivery_retry_seconds,
                 "Seconds before a failed DICOM delivery (send_to) is tried "
                 "again; doubled per failure up to --delivery-retry-max")
      ->check(CLI::Range(0.01, 3600.0))
      ->capture_default_str();
  app.add_option("--delivery-retry-max", o.delivery_retry_max_seconds,
                 "Longest wait between tries of a DICOM delivery, seconds")
      ->check(CLI::Range(0.01, 86400.0))
      ->capture_default_str();
  app.add_option("--delivery-give-up", o.delivery_give_up_seconds,
                 "A DICOM delivery not accepted after this many seconds is "
                 "FAILED (its results then expire with the job)")
      ->check(CLI::Range(1.0, 30 * 86400.0))
      ->capture_default_str();
  app.add_option("--port-file", o.port_file,
                 "Write the bound gRPC and metrics ports (and the DICOM port "
                 "with --dicom-listen) here after start-up, one a line");
  app.add_option("--dicom-listen", o.dicom_listen,
                 "Receive series as a DICOM Storage SCP on HOST:PORT, exactly "
                 "that address (numeric IPv4 or [IPv6]; * or 0.0.0.0 for every "
                 "IPv4 interface, [::] for every interface; port 0 picks "
                 "one); see docs/dicom-node.md");
  app.add_option("--dicom-ae", o.dicom_ae_titles,
                 "AE title(s) the DICOM listener answers to (repeatable; "
                 "default INTERSLICE); rules bind to them with "
                 "match.called_ae");
  app.add_option("--dicom-peers", o.dicom_peers_file,
                 "Peers file (YAML or JSON): the DICOM nodes allowed to "
                 "associate and to receive results");
  app.add_option("--rules", o.rules_file,
                 "Rules file (YAML or JSON): which received series make "
                 "which job");
  app.add_option("--dicom-max-associations", o.dicom_max_associations,
                 "Simultaneous DICOM associations")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--dicom-max-associations-per-source",
                 o.dicom_max_associations_per_source,
                 "Simultaneous DICOM associations from one address (0 = half "
                 "of --dicom-max-associations)")
      ->check(CLI::Range(0, 1000))
      ->capture_default_str();
  app.add_option("--dicom-max-pending", o.dicom_max_pending,
                 "Connections waiting for their association request; beyond, "
                 "the oldest waiting one is closed")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--dicom-max-pending-per-source",
                 o.dicom_max_pending_per_source,
                 "Connections from one address waiting for their association "
                 "request; beyond, its oldest waiting one is closed")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--dicom-max-pdu", o.dicom_max_pdu,
                 "Largest PDU the listener receives, bytes")
      ->check(CLI::Range(4096, 131072))
      ->capture_default_str();
  app.add_option("--dicom-acse-timeout", o.dicom_acse_timeout_seconds,
                 "Seconds from a connection until its association request has "
                 "arrived whole (and for a release)")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  app.add_option("--dicom-pdu-timeout", o.dicom_pdu_timeout_seconds,
                 "Seconds a PDU may take to arrive whole from its first byte "
                 "(slower senders are cut off)")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  app.add_option("--dicom-dimse-timeout", o.dicom_dimse_timeout_seconds,
                 "Seconds a peer may stay silent within an association")
      ->capture_default_str();
  app.add_option("--dicom-max-series-instances", o.dicom_max_series_instances,
                 "Instances one received series may hold")
      ->capture_default_str();
  app.add_option("--dicom-max-series-bytes", o.dicom_max_series_bytes,
                 "Bytes one received series may hold")
      ->capture_default_str();
  app.add_option("--dicom-tls-cert", o.dicom_tls_cert,
                 "DICOM TLS: our certificate (PEM)");
  app.add_option("--dicom-tls-key", o.dicom_tls_key,
                 "DICOM TLS: its private key (PEM)");
  app.add_option("--dicom-tls-ca", o.dicom_tls_ca,
                 "DICOM TLS: CA certificates (PEM) that sign peer "
                 "certificates; peers without one are refused");
  bool check_config = false;
  app.add_flag("--check-config", check_config,
               "Check the DICOM configuration and exit: load the peers and "
               "rules files as a start would, C-ECHO every peer, print what "
               "each rule matches; exit code 0, or 1 with one line per "
               "problem");
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    std::fprintf(stderr, "interslice-server: error: %s (see --help)\n",
                 e.what());
    return 1;
  }
  if (check_config) return interslice::server::CheckConfig(o);
  return interslice::server::RunServer(o);
}
