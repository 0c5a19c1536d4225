#include "server/app/flags.h"

namespace interslice::server {

namespace {

constexpr ServerFlag kServerFlags[] = {
    {.names = "--listen",
     .field = &ServerOptions::listen,
     .help = "HOST:PORT to listen on (port 0 picks one)",
     .show_default = true},
    {.names = "--advertise",
     .field = &ServerOptions::advertise,
     .help =
         "HOST:PORT other replicas and balanced clients reach this server at "
         "(default: the listen address); job ids name it, and calls for "
         "another replica's job are forwarded to the replica its id names"},
    {.names = "--peer-tls-ca",
     .field = &ServerOptions::peer_tls_ca,
     .help = "With TLS: CA certificate that verifies other replicas "
             "(default: the system's roots)"},
    {.names = "--spool",
     .field = &ServerOptions::spool,
     .help = "Folder for uploads and results (created if missing)",
     .required = true},
    {.names = "--workers",
     .field = &ServerOptions::workers,
     .help = "Jobs run at once (0 = max(1, CPUs/4); cgroup limits count)",
     .show_default = true},
    {.names = "--threads-per-job",
     .field = &ServerOptions::threads_per_job,
     .help = "Solver threads per job (0 = CPUs / workers)",
     .show_default = true},
    {.names = "--max-queued",
     .field = &ServerOptions::max_queued_jobs,
     .help = "Jobs queued (upload complete, waiting for a worker); beyond: "
             "RESOURCE_EXHAUSTED",
     .show_default = true},
    {.names = "--max-concurrent-uploads",
     .field = &ServerOptions::max_concurrent_uploads,
     .help = "Uploads in progress at once, in all (0 = 2 x --max-queued)",
     .show_default = true},
    {.names = "--max-uploads-per-peer",
     .field = &ServerOptions::max_uploads_per_peer,
     .help = "Uploads in progress at once from one client (its authenticated "
             "identity, else its IP address)",
     .show_default = true},
    {.names = "--upload-idle-timeout",
     .field = &ServerOptions::upload_idle_timeout_seconds,
     .help = "Cancel an upload that sends no data for this many seconds (0 = "
             "never)",
     .show_default = true},
    {.names = "--upload-timeout",
     .field = &ServerOptions::upload_timeout_seconds,
     .help =
         "Cancel an upload not complete after this many seconds (0 = never)",
     .show_default = true},
    {.names = "--max-upload-bytes",
     .field = &ServerOptions::max_upload_bytes,
     .help = "Largest upload per job, bytes",
     .show_default = true},
    {.names = "--max-voxels",
     .field = &ServerOptions::max_output_voxels,
     .help = "Largest refined output grid per job, voxels",
     .show_default = true},
    {.names = "--spool-quota-bytes",
     .field = &ServerOptions::spool_quota_bytes,
     .help = "Disk space for uploads and results, bytes",
     .show_default = true},
    {.names = "--retention",
     .field = &ServerOptions::retention_seconds,
     .help = "Seconds finished detached jobs stay fetchable",
     .show_default = true},
    {.names = "--max-chunk-bytes",
     .field = &ServerOptions::max_chunk_bytes,
     .help = "Largest upload chunk accepted, bytes",
     .show_default = true},
    {.names = "--io-threads",
     .field = &ServerOptions::io_threads,
     .help = "Threads for spool reads and writes",
     .show_default = true},
    {.names = "--tls-cert",
     .field = &ServerOptions::tls_cert,
     .help = "Server certificate (PEM)"},
    {.names = "--tls-key",
     .field = &ServerOptions::tls_key,
     .help = "Server private key (PEM)"},
    {.names = "--tls-client-ca",
     .field = &ServerOptions::tls_client_ca,
     .help = "Require client certificates signed by this CA (mutual TLS)"},
    {.names = "--auth-token-file",
     .field = &ServerOptions::auth_token_file,
     .help = "Require 'authorization: Bearer <token>' with a token from this "
             "file: one token alone (identity 'default'), or lines "
             "NAME:TOKEN ('#' comments); jobs belong to the NAME"},
    {.names = "--admin-identity",
     .field = &ServerOptions::admin_identities,
     .help = "An identity (token NAME, or client certificate subject such as "
             "CN=ops) that sees and may cancel every job; repeatable"},
    {.names = "--metrics-listen",
     .field = &ServerOptions::metrics_listen,
     .help = "HOST:PORT for Prometheus /metrics (off when empty)"},
    {.names = "--status-listen,--http-listen",
     .field = &ServerOptions::status_listen,
     .help = "HOST:PORT of the HTTP server: the status page (/status: jobs, "
             "peers, rules, spool; admin identities only when tokens are "
             "used) and, with --dicom-listen, STOW-RS (POST "
             "/dicomweb/studies); off when empty"},
    {.names = "--http-max-connections",
     .field = &ServerOptions::http_max_connections,
     .help = "HTTP requests served at once (1-64)",
     .show_default = true},
    {.names = "--http-request-timeout",
     .field = &ServerOptions::http_request_timeout_seconds,
     .help = "Seconds an HTTP client may send nothing before it is cut off",
     .show_default = true},
    {.names = "--http-tls-cert",
     .field = &ServerOptions::http_tls_cert,
     .help = "HTTPS for --http-listen: certificate chain (PEM)"},
    {.names = "--http-tls-key",
     .field = &ServerOptions::http_tls_key,
     .help = "HTTPS for --http-listen: its private key (PEM)"},
    {.names = "--stow-max-body-bytes",
     .field = &ServerOptions::stow_max_body_bytes,
     .help = "Largest STOW-RS request body (0: --dicom-max-series-bytes)",
     .show_default = true},
    {.names = "--audit-log",
     .field = &ServerOptions::audit_log,
     .help = "Append an audit trail here: JSON lines of job, delivery, DICOM "
             "association and authentication events, no patient data "
             "(docs/audit.md); off when empty"},
    {.names = "--audit-max-bytes",
     .field = &ServerOptions::audit_max_bytes,
     .help = "Rotate the audit log at this size (PATH.1, PATH.2, ...)",
     .show_default = true},
    {.names = "--audit-keep",
     .field = &ServerOptions::audit_keep,
     .help = "Rotated audit logs kept",
     .show_default = true},
    {.names = "--reflection",
     .field = &ServerOptions::reflection,
     .help = "Enable gRPC server reflection"},
    {.names = "--log-format",
     .field = &ServerOptions::log_format,
     .help = "text or json (JSON lines)",
     .show_default = true},
    {.names = "--log-level",
     .field = &ServerOptions::log_level,
     .help = "trace, debug, info, warn, error or off",
     .show_default = true},
    {.names = "--drain-grace",
     .field = &ServerOptions::drain_grace_seconds,
     .help = "Seconds running jobs may finish after SIGTERM before they are "
             "cancelled",
     .show_default = true},
    {.names = "--isolation",
     .field = &ServerOptions::isolation,
     .help = "process: each job computes in a supervised worker process (a "
             "crash fails that job only); thread: in the server process",
     .show_default = true,
     .one_of = {"process", "thread"}},
    {.names = "--max-attempts",
     .field = &ServerOptions::max_attempts,
     .help = "Starts of a detached job interrupted by a server stop (kill, "
             "power cut) before it fails for good",
     .show_default = true,
     .int_range = {{1, 100}}},
    {.names = "--delivery-retry",
     .field = &ServerOptions::delivery_retry_seconds,
     .help = "Seconds before a failed DICOM delivery (send_to) is tried "
             "again; doubled per failure up to --delivery-retry-max",
     .show_default = true,
     .float_range = {{0.01, 3600.0}}},
    {.names = "--delivery-retry-max",
     .field = &ServerOptions::delivery_retry_max_seconds,
     .help = "Longest wait between tries of a DICOM delivery, seconds",
     .show_default = true,
     .float_range = {{0.01, 86400.0}}},
    {.names = "--delivery-give-up",
     .field = &ServerOptions::delivery_give_up_seconds,
     .help = "A DICOM delivery not accepted after this many seconds is "
             "FAILED (its results then expire with the job)",
     .show_default = true,
     .float_range = {{1.0, 30 * 86400.0}}},
    {.names = "--port-file",
     .field = &ServerOptions::port_file,
     .help = "Write the bound gRPC and metrics ports (and the DICOM port "
             "with --dicom-listen) here after start-up, one a line"},
    {.names = "--dicom-listen",
     .field = &ServerOptions::dicom_listen,
     .help = "Receive series as a DICOM Storage SCP on HOST:PORT, exactly "
             "that address (numeric IPv4 or [IPv6]; * or 0.0.0.0 for every "
             "IPv4 interface, [::] for every interface; port 0 picks one); "
             "see docs/dicom-node.md"},
    {.names = "--dicom-ae",
     .field = &ServerOptions::dicom_ae_titles,
     .help = "AE title(s) the DICOM listener answers to (repeatable; default "
             "INTERSLICE); rules bind to them with match.called_ae"},
    {.names = "--dicom-peers",
     .field = &ServerOptions::dicom_peers_file,
     .help = "Peers file (YAML or JSON): the DICOM nodes allowed to "
             "associate and to receive results"},
    {.names = "--rules",
     .field = &ServerOptions::rules_file,
     .help = "Rules file (YAML or JSON): which received series make which job"},
    {.names = "--dicom-max-associations",
     .field = &ServerOptions::dicom_max_associations,
     .help = "Simultaneous DICOM associations",
     .show_default = true,
     .int_range = {{1, 1000}}},
    {.names = "--dicom-max-associations-per-source",
     .field = &ServerOptions::dicom_max_associations_per_source,
     .help = "Simultaneous DICOM associations from one address (0 = half of "
             "--dicom-max-associations)",
     .show_default = true,
     .int_range = {{0, 1000}}},
    {.names = "--dicom-max-pending",
     .field = &ServerOptions::dicom_max_pending,
     .help = "Connections waiting for their association request; beyond, the "
             "oldest waiting one is closed",
     .show_default = true,
     .int_range = {{1, 100000}}},
    {.names = "--dicom-max-pending-per-source",
     .field = &ServerOptions::dicom_max_pending_per_source,
     .help = "Connections from one address waiting for their association "
             "request; beyond, its oldest waiting one is closed",
     .show_default = true,
     .int_range = {{1, 100000}}},
    {.names = "--dicom-max-pdu",
     .field = &ServerOptions::dicom_max_pdu,
     .help = "Largest PDU the listener receives, bytes",
     .show_default = true,
     .int_range = {{4096, 131072}}},
    {.names = "--dicom-acse-timeout",
     .field = &ServerOptions::dicom_acse_timeout_seconds,
     .help = "Seconds from a connection until its association request has "
             "arrived whole (and for a release)",
     .show_default = true,
     .float_range = {{0.1, 3600.0}}},
    {.names = "--dicom-pdu-timeout",
     .field = &ServerOptions::dicom_pdu_timeout_seconds,
     .help = "Seconds a PDU may take to arrive whole from its first byte "
             "(slower senders are cut off)",
     .show_default = true,
     .float_range = {{0.1, 3600.0}}},
    {.names = "--dicom-dimse-timeout",
     .field = &ServerOptions::dicom_dimse_timeout_seconds,
     .help = "Seconds a peer may stay silent within an association",
     .show_default = true},
    {.names = "--dicom-max-series-instances",
     .field = &ServerOptions::dicom_max_series_instances,
     .help = "Instances one received series may hold",
     .show_default = true},
    {.names = "--dicom-max-series-bytes",
     .field = &ServerOptions::dicom_max_series_bytes,
     .help = "Bytes one received series may hold",
     .show_default = true},
    {.names = "--dicom-tls-cert",
     .field = &ServerOptions::dicom_tls_cert,
     .help = "DICOM TLS: our certificate (PEM)"},
    {.names = "--dicom-tls-key",
     .field = &ServerOptions::dicom_tls_key,
     .help = "DICOM TLS: its private key (PEM)"},
    {.names = "--dicom-tls-ca",
     .field = &ServerOptions::dicom_tls_ca,
     .help = "DICOM TLS: CA certificates (PEM) that sign peer certificates; "
             "peers without one are refused"},
};

}  // namespace

std::span<const ServerFlag> ServerFlags() { return kServerFlags; }

void AddServerFlags(CLI::App& app, ServerOptions& options) {
  for (const ServerFlag& flag : ServerFlags()) {
    CLI::Option* option = std::visit(
        [&](auto field) -> CLI::Option* {
          auto& value = options.*field;
          if constexpr (std::is_same_v<std::decay_t<decltype(value)>, bool>) {
            return app.add_flag(flag.names, value, flag.help);
          } else {
            return app.add_option(flag.names, value, flag.help);
          }
        },
        flag.field);
    if (flag.required) option->required();
    if (flag.int_range) {
      option->check(CLI::Range(flag.int_range->first, flag.int_range->second));
    }
    if (flag.float_range) {
      option->check(
          CLI::Range(flag.float_range->first, flag.float_range->second));
    }
    std::vector<std::string> one_of;
    for (const char* value : flag.one_of) {
      if (value != nullptr) one_of.push_back(value);
    }
    if (!one_of.empty()) option->check(CLI::IsMember(one_of));
    if (flag.show_default) option->capture_default_str();
  }
}

}  // namespace interslice::server
