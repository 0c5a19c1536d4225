// The HTTP listener's routes (server/net/http/status_page.h): a handler
// serves every request under a path prefix, so that a door above net/http
// (STOW-RS, server/net/dicomweb/stow.h) is served by the one listener while
// net/http includes nothing of it. server/app/ wires the handlers in. This
// header is all a door needs of net/http (no library to link: it has no
// code of its own).
//
// Contract, for a route with prefix P ("/dicomweb"):
// - The listener gives the route the path P and every path under P + "/"
//   (the first route that takes a path wins; paths no route takes are the
//   status page's).
// - Screen(method, path) first, before the caller is authenticated: the
//   answer to a request the handler refuses by its method and path alone
//   (404, 405; so an unauthenticated caller learns only those), or nullopt
//   to go on.
// - Then the listener authenticates the caller as it does for the status
//   page: the token as "Authorization: Bearer TOKEN" or as the password of
//   HTTP Basic (any user name). No or a wrong token: 401 with a Basic
//   challenge, and an "auth.refused" audit record with the detail
//   "<name()>: missing or wrong token"; the handler sees nothing more of it.
// - Serve(request) with the authenticated identity ("" for the anonymous
//   user of a server without tokens): the handler reads the body through
//   `read` (or not) and returns the answer, which the listener writes with
//   its Content-Length (and no caching, nosniff, a Content-Security-Policy
//   that forbids scripts, Connection: close). A HEAD request's answer goes
//   without its body.
// - Called on the listener's threads (at most its max_connections at once,
//   each request on one thread): Screen and Serve must be thread-safe; they
//   may block (a body is read as it arrives). The handler must outlive the
//   listener.
#ifndef INTERSLICE_SERVER_NET_HTTP_HTTP_HANDLER_H_
#define INTERSLICE_SERVER_NET_HTTP_HTTP_HANDLER_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>

namespace interslice::server {

// A request the listener received, its caller authenticated.
struct HttpServerRequest {
  std::string method;    // "POST"
  std::string path;      // decoded, without the query: "/dicomweb/studies"
  std::string identity;  // the authenticated caller ("" = anonymous)
  std::string source;    // its address "HOST:PORT", for the audit trail
  int64_t content_length = -1;  // -1: not given (chunked)
  // A request header's value by name (case-insensitive); "" when absent.
  std::function<std::string(const std::string& name)> header;
  // Reads up to `size` body bytes: > 0 read, 0 at the end, < 0 an error (a
  // timeout, the client gone).
  std::function<int64_t(char* buffer, size_t size)> read;
};

// The answer. The reason phrase follows from the status.
struct HttpServerResponse {
  int status = 500;
  std::string content_type = "text/plain";
  std::string body;
  // More header lines, each ending in CRLF ("Allow: POST\r\n").
  std::string extra_headers;
};

class HttpRequestHandler {
 public:
  virtual ~HttpRequestHandler() = default;
  // What the route serves, in the audit trail ("STOW-RS").
  virtual std::string_view name() const = 0;
  virtual std::optional<HttpServerResponse> Screen(
      std::string_view method, std::string_view path) const = 0;
  virtual HttpServerResponse Serve(const HttpServerRequest& request) const = 0;
};

struct HttpRoute {
  std::string prefix;  // "/dicomweb": that path and every path under it
  const HttpRequestHandler* handler = nullptr;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_HTTP_HTTP_HANDLER_H_
