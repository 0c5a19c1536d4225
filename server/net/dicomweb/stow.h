// The STOW-RS origin server (DICOM PS3.18 10.5, "Store Instances"): one
// request is one transfer into the node's intake (server/node/intake.h,
// Door::kStowRequest), so that the rules, limits, quota, SOP classes and
// completeness model of the DIMSE listener apply to instances that arrive
// by HTTP too; a series is grouped across requests (a rule's
// complete_on_request makes one job per request). docs/dicomweb.md
// describes it.
//
// As a route of the HTTP listener (HttpRequestHandler of
// server/net/http/http_handler.h; server/app/ gives it the prefix
// /dicomweb):
// - Screen, before authentication: POST /dicomweb/studies and
//   /dicomweb/studies/{study} (a UID, IsUidPathSegment) go on; any other
//   path under /dicomweb is 404 (traversal, a malformed UID, /series, ...),
//   any other method on these 405 (Allow: POST).
// - Serve, once the listener authenticated the caller: any identity that
//   may submit jobs may store (every token's; the anonymous user of a
//   server without tokens, unless refuse_anonymous: a server that
//   authenticates gRPC callers by client certificate only answers 403, since
//   the HTTP listener checks no client certificates; neither logged nor
//   audited). Then Handle() with the request's identity, source,
//   Content-Type, Content-Length, study and body.
//
// Contract of Handle():
// - Before a byte of the body is read: Content-Type neither
//   multipart/related (with no `type` or type application/dicom) nor
//   application/dicom (a single-part body: one instance) -> 415; a
//   malformed one (e.g. a boundary longer than kMaxBoundaryChars, 256) ->
//   400; Content-Length above max_body_bytes -> 413; the spool quota has no
//   room for Content-Length (or none at all) -> 507. Nothing is stored.
// - Otherwise BeginTransfer(calling = "STOW:" + identity ("STOW" for the
//   anonymous user of a server without tokens), called = called_ae): the
//   rules see those AE titles. Each part is written straight to a staging
//   file as it arrives (never the whole body in memory), then checked (the
//   bounded scan, its header's UIDs; with a study in the path, an instance
//   of another study is refused with 0xA900, PS3.4 B.2.3 "does not match")
//   and handed to AddInstance. A part refused gets a Failure Reason: 0xA700
//   out of resources (quota, per-series or per-instance limit, full disk),
//   0x0122 SOP class not supported (not one of node::StorableSopClasses,
//   which the DIMSE listener negotiates), 0xC000 cannot understand (not
//   application/dicom, not Part 10 DICOM, no UIDs), 0x0110 processing
//   failure (anything else): node::StoreStatusOfRefusal.
// - EndTransfer(whole) with whole = the body was parsed to its close
//   delimiter (a single-part body: to its end), within max_body_bytes, held
//   every byte its Content-Length promised, and no part was refused: so a
//   malformed, short or cut-off body, or one refused instance, leaves every
//   series the request stored into INCOMPLETE (it makes no job until the
//   missing part arrives; series_assembler.h). A body shorter than its
//   Content-Length is 400 whatever the parser made of it.
// - The answer (PS3.18 10.5.3, application/dicom+json: one data set with
//   ReferencedSOPSequence (0008,1199) and FailedSOPSequence (0008,1198)):
//   200 every part stored; 202 some stored, some failed; 409 none stored
//   (at least one part); 507 none stored and the spool quota refused one;
//   400 a malformed body (with the parser's reason) or no part at all; 413
//   a body that passed max_body_bytes while it arrived (chunked).
// - Audit "stow.received" (identity, source, count = instances stored,
//   detail = stored/refused counts and whether the body was complete); no
//   UIDs in logs, audit or error texts (the response names the instances'
//   SOP UIDs to the caller who sent them).
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_STOW_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_STOW_H_

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>

#include "server/net/http/http_handler.h"
#include "server/node/outcome.h"

namespace interslice::server {
class AuditLog;
class Metrics;
class Spool;
namespace node {
class Intake;
}  // namespace node
}  // namespace interslice::server

namespace interslice::server::dicomweb {

// PS3.18 10.5.3 / PS3.4 B.2.3 failure reasons used here (node/outcome.h).
inline constexpr int kFailureOutOfResources = node::kStoreOutOfResources;
inline constexpr int kFailureDoesNotMatch = node::kStoreDoesNotMatch;
inline constexpr int kFailureCannotUnderstand = node::kStoreCannotUnderstand;
inline constexpr int kFailureProcessing = node::kStoreProcessingFailure;
inline constexpr int kFailureSopClassNotSupported =
    node::kStoreSopClassNotSupported;

struct StowOptions {
  std::string called_ae = "INTERSLICE";  // the AE title rules see as called
  // The largest body taken (0: the assembler's bytes per series).
  int64_t max_body_bytes = 0;
  // Bytes read from the connection at a time.
  size_t read_chunk_bytes = 64 * 1024;
  // The anonymous user (a server without tokens) gets 403: set when the
  // server authenticates gRPC callers by client certificate only.
  bool refuse_anonymous = false;
  // Counts instances stored and refused, and body bytes
  // (Metrics::StowInstances, StowBodyBytes); may be null.
  Metrics* metrics = nullptr;
};

struct StowRequest {
  std::string identity;  // the authenticated caller ("" = anonymous)
  std::string source;    // its address, for the audit trail
  std::string content_type;
  std::string study_uid;        // from /studies/{study}; "" for /studies
  int64_t content_length = -1;  // -1: not given (chunked)
  // Reads up to `size` body bytes: > 0 read, 0 at the end, < 0 an error
  // (a timeout, the client gone).
  std::function<int64_t(char* buffer, size_t size)> read;
};

struct StowResponse {
  int status = 500;
  std::string content_type = "text/plain";
  std::string body;
  int64_t stored = 0, failed = 0;
  bool released = false;  // what EndTransfer was told
};

class StowReceiver : public HttpRequestHandler {
 public:
  // All must outlive the receiver; `spool` and `audit` may be null.
  StowReceiver(StowOptions options, node::Intake* assembler, Spool* spool,
               AuditLog* audit);
  StowResponse Handle(const StowRequest& request) const;
  int64_t max_body_bytes() const { return max_body_bytes_; }

  // HttpRequestHandler, for the prefix /dicomweb.
  std::string_view name() const override { return "STOW-RS"; }
  std::optional<HttpServerResponse> Screen(
      std::string_view method, std::string_view path) const override;
  HttpServerResponse Serve(const HttpServerRequest& request) const override;

 private:
  const StowOptions options_;
  node::Intake* const assembler_;
  Spool* const spool_;
  AuditLog* const audit_;
  int64_t max_body_bytes_;
};

// Whether `uid` may be a UID in a path (PS3.5 9.1: digits and dots, at most
// 64 characters, no empty component).
bool IsUidPathSegment(std::string_view uid);

// The study of a STOW-RS path: "" for /dicomweb/studies, the UID of
// /dicomweb/studies/{study}; nullopt for any other path.
std::optional<std::string> StowStudyOfPath(std::string_view path);

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_STOW_H_
