#include "server/net/http/status_page.h"

#include <dlfcn.h>

#include <algorithm>
#include <cstring>
#include <ctime>
#include <map>
#include <optional>
#include <string_view>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "civetweb.h"
#include "nlohmann/json.hpp"
#include "openssl/err.h"
#include "openssl/ssl.h"
#include "server/base/audit.h"
#include "server/base/identity.h"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace {

void AppendEscaped(std::string& out, std::string_view text) {
  for (const char c : text) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      case '\'':
        out += "&#39;";
        break;
      default:
        out += c;
    }
  }
}

std::string Html(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  AppendEscaped(out, LogSafe(text));
  return out;
}

std::string FormatTime(int64_t unix_ms) {
  if (unix_ms <= 0) return "";
  const std::time_t seconds = static_cast<std::time_t>(unix_ms / 1000);
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  return absl::StrFormat("%04d-%02d-%02d %02d:%02d:%02d", utc.tm_year + 1900,
                         utc.tm_mon + 1, utc.tm_mday, utc.tm_hour, utc.tm_min,
                         utc.tm_sec);
}

std::string FormatBytes(int64_t bytes) {
  if (bytes >= (int64_t{1} << 30)) {
    return absl::StrFormat("%.1f GiB", bytes / double(int64_t{1} << 30));
  }
  return absl::StrFormat("%.1f MiB", bytes / double(1 << 20));
}

std::string StateName(v1::JobState state) {
  std::string name = v1::JobState_Name(state);
  constexpr std::string_view kPrefix = "JOB_STATE_";
  if (name.rfind(kPrefix, 0) == 0) name.erase(0, kPrefix.size());
  return absl::AsciiStrToLower(name);
}

std::string DeliveryStateName(v1::Delivery::State state) {
  return absl::AsciiStrToLower(v1::Delivery::State_Name(state));
}

std::vector<const v1::JobStatus*> NewestFirst(const StatusSnapshot& s) {
  std::vector<const v1::JobStatus*> jobs;
  jobs.reserve(s.jobs.size());
  for (const v1::JobStatus& j : s.jobs) jobs.push_back(&j);
  std::sort(jobs.begin(), jobs.end(), [](const auto* a, const auto* b) {
    if (a->created_unix_ms() != b->created_unix_ms()) {
      return a->created_unix_ms() > b->created_unix_ms();
    }
    return a->job_id() < b->job_id();
  });
  if (jobs.size() > static_cast<size_t>(kMaxJobsShown)) {
    jobs.resize(kMaxJobsShown);
  }
  return jobs;
}

struct PeerLoad {
  int pending = 0, failed = 0, delivered = 0;
};

std::map<std::string, PeerLoad> LoadPerPeer(const StatusSnapshot& s) {
  std::map<std::string, PeerLoad> load;
  for (const v1::JobStatus& j : s.jobs) {
    for (const v1::Delivery& d : j.deliveries()) {
      PeerLoad& l = load[d.peer()];
      if (d.state() == v1::Delivery::PENDING) ++l.pending;
      if (d.state() == v1::Delivery::FAILED) ++l.failed;
      if (d.state() == v1::Delivery::DELIVERED) ++l.delivered;
    }
  }
  return load;
}

constexpr char kStyle[] =
    "body{font-family:sans-serif;margin:1.5em;color:#111}"
    "table{border-collapse:collapse;margin-bottom:1.5em}"
    "th,td{border:1px solid #bbb;padding:.25em .5em;text-align:left;"
    "vertical-align:top;font-size:.9em}"
    "th{background:#eee}.failed{background:#fdd}.cancelled{background:#eee}"
    ".running{background:#def}.queued,.uploading{background:#ffd}"
    ".succeeded{background:#dfd}.muted{color:#666}";

}  // namespace

std::string RenderStatusHtml(const StatusSnapshot& s) {
  std::string out;
  out.reserve(4096 + s.jobs.size() * 400);
  absl::StrAppend(&out,
                  "<!DOCTYPE html><html lang=\"en\"><head><meta "
                  "charset=\"utf-8\"><title>interslice status</title><style>",
                  kStyle, "</style></head><body><h1>interslice</h1><p>",
                  "version ", Html(s.version), " &middot; ",
                  FormatTime(s.now_unix_ms), " UTC &middot; ", s.queued,
                  " queued, ", s.running, " running &middot; spool ",
                  FormatBytes(s.spool_used_bytes), " of ",
                  FormatBytes(s.spool_quota_bytes), "</p>");

  int failed = 0;
  for (const v1::JobStatus& j : s.jobs) {
    if (j.state() == v1::JOB_STATE_FAILED) ++failed;
  }
  const std::vector<const v1::JobStatus*> jobs = NewestFirst(s);
  absl::StrAppend(&out, "<h2 id=\"jobs\">Jobs (", s.jobs.size(), ", ", failed,
                  " failed",
                  jobs.size() < s.jobs.size()
                      ? absl::StrCat("; the newest ", jobs.size(), " shown")
                      : "",
                  ")</h2>");
  absl::StrAppend(&out,
                  "<table><tr><th>job</th><th>state</th><th>origin</"
                  "th><th>label</th><th>created</th><th>started</"
                  "th><th>finished</th><th>stage</th><th>deliveries</"
                  "th><th>error</th></tr>");
  for (const v1::JobStatus* j : jobs) {
    const std::string state = StateName(j->state());
    absl::StrAppend(
        &out, "<tr class=\"", state, "\"><td>", Html(j->job_id()), "</td><td>",
        state, j->cancel_requested() ? " (cancel requested)" : "", "</td><td>",
        Html(j->origin()), "</td><td>", Html(j->label()), "</td><td>",
        FormatTime(j->created_unix_ms()), "</td><td>",
        FormatTime(j->started_unix_ms()), "</td><td>",
        FormatTime(j->finished_unix_ms()), "</td><td>",
        Html(j->progress().stage()), "</td><td>");
    for (const v1::Delivery& d : j->deliveries()) {
      absl::StrAppend(&out, Html(d.peer()), ": ", DeliveryStateName(d.state()),
                      " ", d.instances_sent(), "/", d.instances_total());
      if (d.attempts() > 1) absl::StrAppend(&out, ", ", d.attempts(), " tries");
      if (!d.last_error().empty()) {
        absl::StrAppend(&out, " <span class=\"muted\">(", Html(d.last_error()),
                        ")</span>");
      }
      out += "<br>";
    }
    absl::StrAppend(&out, "</td><td>", Html(j->error_message()), "</td></tr>");
  }
  out += "</table>";

  int incomplete = 0;
  for (const StatusSeries& x : s.series) {
    if (x.state != "receiving") ++incomplete;
  }
  absl::StrAppend(&out, "<h2 id=\"series\">Series arriving (", s.series.size(),
                  ", ", incomplete,
                  " incomplete or dropped)</h2><table><tr><th>state</th><th>"
                  "from</th><th>to</th><th>instances</th><th>since</th><th>"
                  "why</th></tr>");
  for (const StatusSeries& x : s.series) {
    absl::StrAppend(
        &out, "<tr class=\"", x.state == "receiving" ? "queued" : "failed",
        "\"><td>", Html(x.state), "</td><td>", Html(x.calling_ae), "</td><td>",
        Html(x.called_ae), "</td><td>", x.instances, "</td><td>",
        FormatTime(x.since_unix_ms), "</td><td>", Html(x.why), "</td></tr>");
  }
  out += "</table>";

  const std::map<std::string, PeerLoad> load = LoadPerPeer(s);
  absl::StrAppend(&out, "<h2 id=\"peers\">DICOM peers (", s.peers.size(),
                  ")</h2><table><tr><th>name</th><th>AE title</th><th>address"
                  "</th><th>deliveries pending</th><th>failed</th><th>"
                  "delivered</th></tr>");
  for (const StatusPeer& p : s.peers) {
    const auto it = load.find(p.name);
    const PeerLoad l = it == load.end() ? PeerLoad{} : it->second;
    absl::StrAppend(&out, "<tr><td>", Html(p.name), "</td><td>",
                    Html(p.ae_title), "</td><td>", Html(p.address),
                    p.tls ? " (TLS)" : "", "</td><td>", l.pending, "</td><td>",
                    l.failed, "</td><td>", l.delivered, "</td></tr>");
  }
  out += "</table>";

  absl::StrAppend(&out, "<h2 id=\"rules\">Rules (", s.rules.size(),
                  ")</h2><p class=\"muted\">", Html(s.rules_file),
                  "</p><table><tr><th>name</th><th>matches</th><th>sends to"
                  "</th></tr>");
  for (const StatusRule& r : s.rules) {
    absl::StrAppend(&out, "<tr><td>", Html(r.name), "</td><td>", Html(r.match),
                    "</td><td>", Html(absl::StrJoin(r.send_to, ", ")),
                    "</td></tr>");
  }
  out += "</table></body></html>\n";
  return out;
}

std::string RenderStatusJson(const StatusSnapshot& s) {
  nlohmann::ordered_json j;
  j["version"] = s.version;
  j["now_unix_ms"] = s.now_unix_ms;
  j["queued"] = s.queued;
  j["running"] = s.running;
  j["spool"] = {{"used_bytes", s.spool_used_bytes},
                {"quota_bytes", s.spool_quota_bytes}};
  nlohmann::ordered_json jobs = nlohmann::ordered_json::array();
  for (const v1::JobStatus* job : NewestFirst(s)) {
    nlohmann::ordered_json d = nlohmann::ordered_json::array();
    for (const v1::Delivery& x : job->deliveries()) {
      d.push_back({{"peer", LogSafe(x.peer())},
                   {"state", DeliveryStateName(x.state())},
                   {"instances_sent", x.instances_sent()},
                   {"instances_total", x.instances_total()},
                   {"attempts", x.attempts()},
                   {"last_error", LogSafe(x.last_error())}});
    }
    jobs.push_back({{"job_id", LogSafe(job->job_id())},
                    {"state", StateName(job->state())},
                    {"origin", LogSafe(job->origin())},
                    {"label", LogSafe(job->label())},
                    {"created_unix_ms", job->created_unix_ms()},
                    {"started_unix_ms", job->started_unix_ms()},
                    {"finished_unix_ms", job->finished_unix_ms()},
                    {"stage", LogSafe(job->progress().stage())},
                    {"error", LogSafe(job->error_message())},
                    {"deliveries", std::move(d)}});
  }
  j["jobs"] = std::move(jobs);
  nlohmann::ordered_json series = nlohmann::ordered_json::array();
  for (const StatusSeries& x : s.series) {
    series.push_back({{"state", x.state},
                      {"calling_ae", LogSafe(x.calling_ae)},
                      {"called_ae", LogSafe(x.called_ae)},
                      {"instances", x.instances},
                      {"since_unix_ms", x.since_unix_ms},
                      {"why", LogSafe(x.why)}});
  }
  j["series"] = std::move(series);
  nlohmann::ordered_json peers = nlohmann::ordered_json::array();
  for (const StatusPeer& p : s.peers) {
    peers.push_back({{"name", p.name},
                     {"ae_title", p.ae_title},
                     {"address", p.address},
                     {"tls", p.tls}});
  }
  j["peers"] = std::move(peers);
  nlohmann::ordered_json rules = nlohmann::ordered_json::array();
  for (const StatusRule& r : s.rules) {
    rules.push_back(
        {{"name", r.name}, {"match", r.match}, {"send_to", r.send_to}});
  }
  j["rules"] = std::move(rules);
  return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace) +
         "\n";
}

struct StatusServer::Impl {
  std::function<StatusSnapshot()> snapshot;
  Metrics* metrics = nullptr;
  const Authenticator* auth = nullptr;
  AuditLog* audit = nullptr;
  std::vector<HttpRoute> routes;
  std::string tls_certificate, tls_private_key;
  std::string tls_error;  // why init_ssl failed
  mg_context* context = nullptr;
};

namespace {

void Reply(mg_connection* connection, int code, const char* reason,
           const char* content_type, const std::string& body, bool head,
           const char* extra_headers = "") {
  std::string header = absl::StrCat(
      "HTTP/1.1 ", code, " ", reason, "\r\nContent-Type: ", content_type,
      "\r\nContent-Length: ", body.size(),
      "\r\nCache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\n"
      "Content-Security-Policy: default-src 'none'; style-src "
      "'unsafe-inline'\r\nConnection: close\r\n",
      extra_headers, "\r\n");
  mg_write(connection, header.data(), header.size());
  if (!head) mg_write(connection, body.data(), body.size());
}

// The identity the request proves, "" for the anonymous user of a server
// without tokens, or nullopt when it proves none.
std::optional<std::string> Identify(const Authenticator& auth,
                                    mg_connection* connection) {
  if (!auth.tokens_required()) return std::string();
  const char* header = mg_get_header(connection, "Authorization");
  if (header == nullptr) return std::nullopt;
  const std::string_view value(header);
  constexpr std::string_view kBasic = "Basic ";
  if (value.substr(0, kBasic.size()) == kBasic) {
    std::string decoded;
    const std::string_view encoded = value.substr(kBasic.size());
    if (!absl::Base64Unescape(absl::string_view(encoded.data(), encoded.size()),
                              &decoded)) {
      return std::nullopt;
    }
    const size_t colon = decoded.find(':');
    if (colon == std::string::npos) return std::nullopt;
    return auth.MatchBearer("Bearer " + decoded.substr(colon + 1));
  }
  return auth.MatchBearer(value);
}

const char* ReasonPhrase(int code) {
  switch (code) {
    case 200:
      return "OK";
    case 202:
      return "Accepted";
    case 400:
      return "Bad Request";
    case 401:
      return "Unauthorized";
    case 403:
      return "Forbidden";
    case 404:
      return "Not Found";
    case 405:
      return "Method Not Allowed";
    case 409:
      return "Conflict";
    case 413:
      return "Payload Too Large";
    case 415:
      return "Unsupported Media Type";
    case 507:
      return "Insufficient Storage";
    default:
      return "Internal Server Error";
  }
}

void Reply(mg_connection* connection, const HttpServerResponse& response,
           bool head) {
  Reply(connection, response.status, ReasonPhrase(response.status),
        response.content_type.c_str(), response.body, head,
        response.extra_headers.c_str());
}

// Whether `route` takes `path`: its prefix, or a path under it.
bool RouteTakes(const HttpRoute& route, const std::string& path) {
  return path.compare(0, route.prefix.size(), route.prefix) == 0 &&
         (path.size() == route.prefix.size() ||
          path[route.prefix.size()] == '/');
}

// A request for a route's handler (http_handler.h): screened, then
// authenticated, then served.
int HandleRoute(StatusServer::Impl& impl, const HttpRoute& route,
                mg_connection* connection, const std::string& method,
                const std::string& uri, const std::string& source) {
  const bool head = method == "HEAD";
  if (std::optional<HttpServerResponse> early =
          route.handler->Screen(method, uri);
      early.has_value()) {
    Reply(connection, *early, head);
    return early->status;
  }
  const std::optional<std::string> identity = Identify(*impl.auth, connection);
  if (!identity.has_value()) {
    Reply(connection, 401, "Unauthorized", "text/plain",
          "a token is needed: Authorization: Bearer TOKEN, or HTTP Basic "
          "with the token as password\n",
          head, "WWW-Authenticate: Basic realm=\"interslice\"\r\n");
    if (impl.audit != nullptr) {
      impl.audit->Record({.event = "auth.refused",
                          .outcome = AuditOutcome::kMinorFailure,
                          .source = source,
                          .detail = std::string(route.handler->name()) +
                                    ": missing or wrong token"});
    }
    return 401;
  }
  const mg_request_info* request = mg_get_request_info(connection);
  const HttpServerResponse response = route.handler->Serve(
      {.method = method,
       .path = uri,
       .identity = *identity,
       .source = source,
       .content_length = request->content_length,
       .header = [connection](const std::string& name) -> std::string {
         const char* value = mg_get_header(connection, name.c_str());
         return value != nullptr ? value : "";
       },
       .read = [connection](char* buffer, size_t size) -> int64_t {
         return mg_read(connection, buffer, size);
       }});
  Reply(connection, response, head);
  return response.status;
}

int ServeStatusPage(StatusServer::Impl* impl, mg_connection* connection,
                    const std::string& method, const std::string& uri,
                    const std::string& source);

// civetweb's handler for every path: a route's, or the status page's;
// counted by route and status (issue 39: HTTP traffic was not in /metrics).
int HandleRequest(mg_connection* connection, void* data) {
  auto* impl = static_cast<StatusServer::Impl*>(data);
  const mg_request_info* request = mg_get_request_info(connection);
  const std::string method =
      request->request_method != nullptr ? request->request_method : "";
  const std::string uri =
      request->local_uri != nullptr ? request->local_uri : "";
  const std::string source =
      absl::StrCat(request->remote_addr, ":", request->remote_port);
  for (const HttpRoute& route : impl->routes) {
    if (RouteTakes(route, uri)) {
      const int code =
          HandleRoute(*impl, route, connection, method, uri, source);
      if (impl->metrics != nullptr) {
        impl->metrics->HttpRequest(std::string(route.handler->name()), code);
      }
      return code;
    }
  }
  const int code = ServeStatusPage(impl, connection, method, uri, source);
  if (impl->metrics != nullptr) impl->metrics->HttpRequest("status", code);
  return code;
}

int ServeStatusPage(StatusServer::Impl* impl, mg_connection* connection,
                    const std::string& method, const std::string& uri,
                    const std::string& source) {
  const bool head = method == "HEAD";
  const bool json = uri == "/status.json";
  if (uri != "/" && uri != "/status" && !json) {
    Reply(connection, 404, "Not Found", "text/plain",
          "not found: the status page is /status\n", head);
    return 404;
  }
  if (method != "GET" && !head) {
    Reply(connection, 405, "Method Not Allowed", "text/plain",
          "only GET and HEAD\n", false, "Allow: GET, HEAD\r\n");
    return 405;
  }
  const std::optional<std::string> identity = Identify(*impl->auth, connection);
  if (!identity.has_value()) {
    Reply(connection, 401, "Unauthorized", "text/plain",
          "an admin's token is needed: Authorization: Bearer TOKEN, or "
          "HTTP Basic with the token as password\n",
          head, "WWW-Authenticate: Basic realm=\"interslice\"\r\n");
    if (impl->audit != nullptr) {
      impl->audit->Record({.event = "auth.refused",
                           .outcome = AuditOutcome::kMinorFailure,
                           .source = source,
                           .detail = "status page: missing or wrong token"});
    }
    return 401;
  }
  if (impl->auth->tokens_required() && !impl->auth->IsAdmin(*identity)) {
    Reply(connection, 403, "Forbidden", "text/plain",
          "the status page shows every job: admin identities only "
          "(--admin-identity)\n",
          head);
    // A known caller asking for what it may not see (issue 39: it left no
    // trace).
    if (impl->audit != nullptr) {
      impl->audit->Record({.event = "status.viewed",
                           .outcome = AuditOutcome::kMinorFailure,
                           .identity = *identity,
                           .source = source,
                           .detail = "refused: not an admin identity"});
    }
    return 403;
  }
  const StatusSnapshot snapshot = impl->snapshot();
  if (impl->audit != nullptr) {
    impl->audit->Record({.event = "status.viewed",
                         .identity = *identity,
                         .source = source,
                         .count = static_cast<int64_t>(snapshot.jobs.size())});
  }
  if (json) {
    Reply(connection, 200, "OK", "application/json", RenderStatusJson(snapshot),
          head);
  } else {
    Reply(connection, 200, "OK", "text/html; charset=utf-8",
          RenderStatusHtml(snapshot), head);
  }
  return 200;
}

// civetweb's init_ssl callback: the certificate (chain) and the key from
// their own PEM files (civetweb's ssl_certificate option wants both in one
// file), TLS 1.2 or newer.
int InitTls(void* ssl_context, void* user_data) {
  auto* impl = static_cast<StatusServer::Impl*>(user_data);
  auto* context = static_cast<SSL_CTX*>(ssl_context);
  auto fail = [&](const char* what) {
    const unsigned long code = ERR_peek_last_error();
    const char* reason = code != 0 ? ERR_reason_error_string(code) : nullptr;
    impl->tls_error = absl::StrCat(
        what, reason != nullptr ? absl::StrCat(" (", reason, ")") : "");
    ERR_clear_error();
    return -1;
  };
  if (SSL_CTX_set_min_proto_version(context, TLS1_2_VERSION) != 1) {
    return fail("cannot require TLS 1.2");
  }
  if (SSL_CTX_use_certificate_chain_file(context,
                                         impl->tls_certificate.c_str()) != 1) {
    return fail("--http-tls-cert: cannot load the certificate");
  }
  if (SSL_CTX_use_PrivateKey_file(context, impl->tls_private_key.c_str(),
                                  SSL_FILETYPE_PEM) != 1) {
    return fail("--http-tls-key: cannot load the private key");
  }
  if (SSL_CTX_check_private_key(context) != 1) {
    return fail("--http-tls-key does not match --http-tls-cert");
  }
  return 1;  // set up here: civetweb loads nothing itself
}

int LogMessage(const mg_connection*, const char* message) {
  spdlog::debug("status page: {}", LogSafe(message));
  return 1;  // handled: civetweb prints nothing
}

}  // namespace

absl::Status HttpTlsAvailable() {
  if (mg_check_feature(MG_FEATURES_SSL) == 0) {
    return absl::UnimplementedError(
        "this civetweb library is built without TLS: no HTTPS");
  }
  // civetweb loads OpenSSL at run time by these names (its default
  // SSL_LIB), and takes every function by name.
  void* ssl = ::dlopen("libssl.so", RTLD_NOW | RTLD_LOCAL);
  if (ssl == nullptr) {
    return absl::UnimplementedError(
        "civetweb loads TLS from libssl.so, which is not installed (Debian: "
        "libssl-dev): no HTTPS");
  }
  // Debian bookworm's civetweb 1.15 calls SSL_get_peer_certificate after
  // every TLS handshake; OpenSSL 3 exports it only as
  // SSL_get1_peer_certificate, so the call goes to a null pointer and the
  // process dies at the first HTTPS client. No civetweb option avoids it:
  // the call is in the accept path whatever the configuration, and it
  // crashes the same with an SSL_CTX the application makes itself (the
  // external_ssl_ctx callback), with mg_init_library(MG_FEATURES_TLS), and
  // with the ssl_protocol_version/ssl_cipher_list options (checked with a
  // plain civetweb program; the API level is fixed when civetweb is built).
  const bool usable = ::dlsym(ssl, "SSL_get_peer_certificate") != nullptr;
  ::dlclose(ssl);
  if (!usable) {
    return absl::UnimplementedError(
        "this civetweb cannot serve TLS with this OpenSSL (it needs "
        "SSL_get_peer_certificate, which OpenSSL 3 no longer exports; "
        "Debian bookworm's civetweb 1.15 crashes at the first handshake): "
        "serve HTTPS through a TLS-terminating proxy in front of "
        "--http-listen on loopback instead (docs/dicomweb.md, \"HTTPS\"; "
        "example: docs/examples/stunnel-https.conf)");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<StatusServer>> StatusServer::Start(
    const StatusServerOptions& options,
    std::function<StatusSnapshot()> snapshot, const Authenticator* auth,
    AuditLog* audit, std::vector<HttpRoute> routes) {
  if (options.listen.empty() || options.listen.find(':') == std::string::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat("--status-listen: expected HOST:PORT, got '",
                     LogSafe(options.listen), "'"));
  }
  if (options.max_connections < 1 || options.max_connections > 64 ||
      !(options.request_timeout_seconds > 0)) {
    return absl::InvalidArgumentError(
        "the status page needs 1-64 connections and a positive timeout");
  }
  for (const HttpRoute& route : routes) {
    if (route.handler == nullptr || route.prefix.size() < 2 ||
        route.prefix.front() != '/' || route.prefix.back() == '/') {
      return absl::InvalidArgumentError(
          "an HTTP route needs a handler and a prefix \"/name\"");
    }
  }
  std::unique_ptr<StatusServer> server(new StatusServer());
  server->impl_ = std::make_unique<Impl>();
  Impl& impl = *server->impl_;
  impl.snapshot = std::move(snapshot);
  impl.metrics = options.metrics;
  impl.auth = auth;
  impl.audit = audit;
  impl.routes = std::move(routes);
  const bool tls = !options.tls_certificate.empty();
  if (tls != !options.tls_private_key.empty()) {
    return absl::InvalidArgumentError(
        "HTTPS needs both --http-tls-cert and --http-tls-key");
  }
  if (tls) {
    if (absl::Status usable = HttpTlsAvailable(); !usable.ok()) {
      return usable;
    }
  }
  impl.tls_certificate = options.tls_certificate;
  impl.tls_private_key = options.tls_private_key;
  // civetweb marks a TLS port with a trailing "s".
  const std::string listening_ports =
      tls ? options.listen + "s" : options.listen;
  const std::string threads = std::to_string(options.max_connections);
  const std::string timeout_ms = std::to_string(
      static_cast<int64_t>(options.request_timeout_seconds * 1000));
  // A slow client holds one of max_connections threads for at most the
  // request timeout; nothing is served from disk (no document_root).
  const char* config[] = {"listening_ports",
                          listening_ports.c_str(),
                          "num_threads",
                          threads.c_str(),
                          "request_timeout_ms",
                          timeout_ms.c_str(),
                          "enable_keep_alive",
                          "no",
                          nullptr};
  mg_callbacks callbacks{};
  callbacks.log_message = LogMessage;
  if (tls) callbacks.init_ssl = InitTls;
  impl.context = mg_start(&callbacks, &impl, config);
  if (impl.context == nullptr && !impl.tls_error.empty()) {
    return absl::InvalidArgumentError(impl.tls_error);
  }
  if (impl.context == nullptr) {
    return absl::UnavailableError(absl::StrCat(
        "cannot listen on ", LogSafe(options.listen), " for the status page"));
  }
  mg_set_request_handler(impl.context, "/", HandleRequest, &impl);
  mg_server_port ports[4] = {};
  const int n = mg_get_server_ports(impl.context, 4, ports);
  server->port_ = n > 0 ? ports[0].port : 0;
  server->tls_ = tls;
  return server;
}

StatusServer::~StatusServer() {
  if (impl_ != nullptr && impl_->context != nullptr) mg_stop(impl_->context);
}

}  // namespace interslice::server
