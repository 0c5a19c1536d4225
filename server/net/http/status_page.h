// The status page: one read-only HTML page for the people who run the node
// ("which series failed tonight and why"), served by its own small HTTP
// listener (civetweb, the HTTP server prometheus-cpp already brings; see
// docs/DESIGN.md). docs/status-page.md describes it.
//
// Contract:
// - GET /status (and /): plain server-rendered HTML, no script, no external
//   resource; GET /status.json: the same facts as JSON. Anything else: 404;
//   a method other than GET/HEAD: 405.
// - Authenticated like gRPC: with --auth-token-file, an admin identity's
//   token as "Authorization: Bearer TOKEN" or as the password of HTTP Basic
//   (any user name; what a browser asks for). No or a wrong token: 401 with
//   a Basic challenge; a token that is not an admin's: 403. Without tokens
//   the server has one anonymous user (as for gRPC) and the page is open:
//   bind it to loopback or a management network.
// - What it shows: jobs (state, origin: DICOM peer, called AE and
//   rule; label; created, started, finished; deliveries per peer with the
//   last error; the error text of a failed job), peers (AE title, address,
//   deliveries pending and failed), rules, spool use. The same data an admin
//   sees through `interslice list --all`: no UIDs, no patient names (error
//   texts are redacted when jobs fail).
// - Bounded: at most kMaxJobsShown jobs (the newest), each string escaped;
//   requests time out after request_timeout_seconds; at most
//   max_connections requests are served at once.
// - The same listener serves the routes Start() is given (http_handler.h):
//   each handler serves its path prefix (server/app/ gives STOW-RS,
//   server/net/dicomweb/stow.h, the prefix /dicomweb). The listener screens
//   and authenticates those requests (any valid token, or the anonymous user
//   of a server without tokens: the handler decides what an identity may do)
//   and writes the handler's answers.
// - HTTPS when tls_certificate (PEM, the chain) and tls_private_key (PEM)
//   are given: civetweb with OpenSSL, TLS 1.2 or newer; the same port then
//   speaks TLS only. INVALID_ARGUMENT names a file that cannot be loaded or
//   a key that does not match; UNIMPLEMENTED when HttpTlsAvailable() is
//   not OK (on Debian bookworm it is not: see there).
#ifndef INTERSLICE_SERVER_NET_HTTP_STATUS_PAGE_H_
#define INTERSLICE_SERVER_NET_HTTP_STATUS_PAGE_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "interslice/v1/interslice.pb.h"
#include "server/net/http/http_handler.h"

namespace interslice::server {

class Authenticator;
class Metrics;
class AuditLog;

inline constexpr int kMaxJobsShown = 5000;

struct StatusPeer {
  std::string name, ae_title, address;
  bool tls = false;
};

struct StatusRule {
  std::string name;
  std::string match;  // e.g. "modality CT, called AE INTERSLICE"
  std::vector<std::string> send_to;
};

// A series the DICOM node is receiving, holds incomplete, or dropped as
// incomplete lately (issue 39: an operator saw none of them). No UIDs.
struct StatusSeries {
  std::string state;  // receiving | incomplete | dropped
  std::string calling_ae, called_ae;
  int64_t instances = 0;
  int64_t since_unix_ms = 0;
  std::string why;
};

// What one page shows, taken at one moment.
struct StatusSnapshot {
  std::string version;
  int64_t now_unix_ms = 0;
  std::vector<v1::JobStatus> jobs;  // any order; shown newest first
  std::vector<StatusPeer> peers;
  std::vector<StatusRule> rules;
  std::vector<StatusSeries> series;  // oldest first
  std::string rules_file;
  int64_t spool_used_bytes = 0, spool_quota_bytes = 0;
  int queued = 0, running = 0;
};

// The page's HTML / JSON (pure: tests and the benchmark call them).
std::string RenderStatusHtml(const StatusSnapshot& snapshot);
std::string RenderStatusJson(const StatusSnapshot& snapshot);

// Whether the civetweb and OpenSSL libraries found at run time can serve
// HTTPS: civetweb built with TLS, libssl.so loadable, and every function
// civetweb takes from it by name present. UNIMPLEMENTED with the reason
// otherwise (Debian bookworm: civetweb 1.15 wants SSL_get_peer_certificate,
// which OpenSSL 3 does not export, and would crash at the first handshake).
absl::Status HttpTlsAvailable();

struct StatusServerOptions {
  std::string listen;  // HOST:PORT; port 0 picks one
  int max_connections = 4;
  // Headers that take longer than this in all, or a body that sends
  // nothing for this long, are cut off (civetweb's request_timeout_ms: the
  // slow-loris bound for headers, which arrive before any authentication).
  // A body that trickles (a byte within every timeout) is not cut by
  // civetweb's blocking reads: only an authenticated client of a route
  // that reads bodies (STOW-RS) can hold a connection that way, and at most
  // max_connections are served.
  double request_timeout_seconds = 10;
  // HTTPS: both, or neither.
  std::string tls_certificate, tls_private_key;
  // Counts every request answered (Metrics::HttpRequest); may be null.
  Metrics* metrics = nullptr;
};

class StatusServer {
 public:
  // Starts listening. `snapshot` is called per request (on civetweb's
  // threads, never a gRPC reactor); `auth` decides who may see the page and
  // authenticates the routes' callers; `audit` (may be null) records each
  // view and each refused token; `routes` serve their paths (each prefix
  // "/name" without a trailing slash, each handler not null; the first
  // route that takes a path serves it). All must outlive the server.
  // UNAVAILABLE when the address cannot be bound, INVALID_ARGUMENT for bad
  // options or routes.
  static absl::StatusOr<std::unique_ptr<StatusServer>> Start(
      const StatusServerOptions& options,
      std::function<StatusSnapshot()> snapshot, const Authenticator* auth,
      AuditLog* audit, std::vector<HttpRoute> routes = {});
  ~StatusServer();
  StatusServer(const StatusServer&) = delete;
  StatusServer& operator=(const StatusServer&) = delete;

  int port() const { return port_; }
  bool tls() const { return tls_; }

  struct Impl;  // the request handler's state (status_page.cc)

 private:
  StatusServer() = default;
  std::unique_ptr<Impl> impl_;
  int port_ = 0;
  bool tls_ = false;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_HTTP_STATUS_PAGE_H_
