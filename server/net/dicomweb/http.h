// One HTTP(S) request to a DICOMweb peer over libcurl, with the peer's
// credentials and TLS files applied (PS3.18 6.1: HTTP/1.1; auth by the
// peers file: bearer token RFC 6750, basic RFC 7617, or mutual TLS). For
// the server/net/dicomweb/ modules only: libcurl stays behind http.cc.
//
// Contract:
// - HttpRequest::Make reads the peer's secret files now (so a rotated token
//   is used by the next request) and never puts their contents in a
//   message; FAILED_PRECONDITION naming the peer and the key when a file
//   cannot be read.
// - Timeouts: `timeout_seconds` to connect, and a transfer that moves no
//   byte for `timeout_seconds` is aborted (a large upload may take longer
//   in total; a stalled one cannot hang us).
// - Perform(): transport failures (refused, reset, DNS, TLS handshake,
//   stall) are UNAVAILABLE naming the peer (PeerLabel) and curl's reason;
//   otherwise the HTTP status code (any, the caller interprets it).
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_HTTP_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_HTTP_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "nlohmann/json.hpp"
#include "server/node/peer.h"

namespace interslice::server::dicomweb {

class HttpRequest {
 public:
  // Returns at most `n` bytes into `buffer`; 0 at the end; -1 aborts the
  // request (Perform() then fails with `abort_reason`).
  using BodySource = std::function<int64_t(char* buffer, size_t n)>;
  // Takes the next response body bytes; false aborts the request.
  using BodySink = std::function<bool(const char* data, size_t n)>;

  // A request to `url` (the peer's base URL and a path).
  static absl::StatusOr<std::unique_ptr<HttpRequest>> Make(
      const node::DicomPeer& peer, const std::string& url, int timeout_seconds);
  ~HttpRequest();
  HttpRequest(const HttpRequest&) = delete;
  HttpRequest& operator=(const HttpRequest&) = delete;

  void AddHeader(const std::string& line);  // "Accept: application/dicom+json"
  // POST with a body of exactly `size` bytes, read from `source`.
  void SetPostBody(BodySource source, int64_t size);
  void SetSink(BodySink sink);

  // Runs the request: the HTTP status, or UNAVAILABLE for transport errors
  // (or the source's/sink's abort: then the status they set with
  // SetAbortStatus, if any).
  absl::StatusOr<long> Perform();
  // A source or sink that aborts says why here (e.g. "part larger than
  // the limit"): Perform() returns it instead of curl's generic error.
  void SetAbortStatus(absl::Status status);

  // The response's Content-Type header (empty if none).
  std::string content_type() const;

 private:
  HttpRequest();
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Collects a response body up to `limit` bytes; a peer that sends more is
// not believed: the request fails (FAILED_PRECONDITION naming `what`)
// instead of the memory growing.
class BoundedBody {
 public:
  BoundedBody(HttpRequest& request, size_t limit, std::string what);
  const std::string& text() const { return text_; }

 private:
  HttpRequest& request_;
  const size_t limit_;
  const std::string what_;
  std::string text_;
};

// application/dicom+json (or the application/json older servers send).
bool IsDicomJson(const std::string& content_type);

// The Value array of a DICOM JSON attribute ("00081199") of a dataset
// (PS3.18 F.2.2), or null when absent or empty-valued.
const nlohmann::json* DicomJsonValue(const nlohmann::json& dataset,
                                     const char* tag);
// The attribute's values as DICOM text: strings as they are, numbers (IS,
// DS, US in JSON) in decimal, person names' Alphabetic form, joined by '\'
// as a C-FIND answer would; "" when absent.
std::string DicomJsonText(const nlohmann::json& dataset, const char* tag);

// An HTTP status that is not the one expected, as one line naming the peer
// and what to do: 401/403 name the credentials (PERMISSION_DENIED), 5xx and
// 429 are UNAVAILABLE (worth retrying), the rest FAILED_PRECONDITION.
// `what` names the transaction ("STOW-RS", "QIDO-RS").
absl::Status HttpStatusError(const node::DicomPeer& peer,
                             const std::string& what, long http_status);

// Percent-encodes a path segment (a UID is safe; other text may not be).
std::string EscapePathSegment(const std::string& text);

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_HTTP_H_
