// The one streaming parser of multipart/related bodies (RFC 2387, framing
// of RFC 2046 5.1.1) as DICOMweb uses them (PS3.18 8.6.1.2): WADO-RS
// responses a peer sends (pull.cc) and STOW-RS request bodies a client sends
// (stow.cc). Bytes go in as they arrive, in pieces of any size (a delimiter
// may be split across pieces anywhere); each part goes to a sink as it is
// found, so a body of any length never sits in memory (only up to one
// delimiter's length of look-ahead and one part's headers are held).
//
//   MultipartParser parser(boundary, StowRequestMultipart(), &sink);
//   for each piece read: if (!parser.Feed(piece).ok()) stop;
//   then parser.Finish()
//
// The two doors differ in what they accept and how they report, and
// MultipartOptions says which (WadoResponseMultipart(), StowRequestMultipart()
// are the two dialects):
//
// | option                  | WADO-RS responses      | STOW-RS requests       |
// |-------------------------|------------------------|------------------------|
// | line_breaks             | CRLF only              | CRLF or a bare LF      |
// | header_syntax           | kSimple                | kFolded (64 lines max) |
// | check_content_length    | yes                    | no                     |
// | check_transfer_encoding | no                     | binary, 8bit, 7bit     |
// | errors                  | kByKind                | kAtByteOffset          |
// | limits                  | part, body, part count | part count             |
// | limits.max_header_*     | 16 KiB                 | 16 KiB, 64 lines       |
//
// Contract:
// - The body is an optional preamble, then "--boundary" parts separated by
//   a line break and "--boundary", ended by a line break and
//   "--boundary--"; transport padding (spaces, tabs; at most 256) after a
//   delimiter is allowed, the epilogue ignored. A delimiter's line break
//   belongs to the delimiter, never to the part before it; with kCrlfOrLf a
//   part that ends in CR before a bare-LF delimiter loses that CR (CRLF is
//   what PS3.18 senders use, and a CR there is taken as theirs). The first
//   delimiter may open the body (a line break is assumed before it).
// - A part's header lines ("Name: value") end at an empty line; the sink's
//   BeginPart gets them with lower-cased names and trimmed values (the last
//   of repeated names wins). kSimple: one header per line, its name
//   whatever precedes the first colon. kFolded (RFC 5322): a line that
//   starts with a space or tab continues the header before it; names are
//   non-empty and of visible ASCII.
// - check_content_length: a part's Content-Length, when present, must be a
//   number within max_part_bytes and equal the part's data length (a part
//   that lies is found at the latest when it ends, a longer one as soon as
//   its data passes the number). check_transfer_encoding: a part's
//   Content-Transfer-Encoding may only be binary, 8bit or 7bit.
// - Limits: max_part_bytes of data per part, max_total_bytes fed in all
//   (bytes within the bound are parsed before the bound is reported, so the
//   first fault of a body is the one reported however it was cut into
//   pieces), max_parts parts, max_header_bytes of header lines per part
//   (each with its line break; the empty line that ends them not counted),
//   max_header_lines lines per part (kFolded; 0: any number).
// - Errors, one line that never quotes the body. kByKind: INVALID_ARGUMENT
//   "malformed multipart body: ..." for malformed input, RESOURCE_EXHAUSTED
//   for a limit passed. kAtByteOffset: INVALID_ARGUMENT for everything,
//   "malformed multipart body at byte N: ...". A sink's error stops the
//   parser and is returned as it is. After an error the parser takes
//   nothing more: every later Feed and Finish returns that error again.
// - Finish() after the last piece: OK only when the close delimiter
//   ("--boundary--") was seen. A body that ends earlier (a client or peer
//   that stops, a missing close delimiter) is INVALID_ARGUMENT: the caller
//   must treat every part as unconfirmed. Bytes fed after the close
//   delimiter (the epilogue) are ignored, but count towards max_total_bytes.
// - Memory: O(boundary + max_header_bytes), whatever the body size.
// Not thread-safe; one parser per body.
//
// The Content-Type helpers below read the request's or response's header:
// MultipartBoundary and MultipartRootType for WADO-RS responses,
// ParseStowContentType for STOW-RS requests (stricter, with the status
// codes the STOW-RS door answers).
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_MULTIPART_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_MULTIPART_H_

#include <cstdint>
#include <limits>
#include <map>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace interslice::server::dicomweb {

// A part's headers: lower-cased names, values trimmed (the last of repeated
// names wins).
using PartHeaders = std::map<std::string, std::string>;

// Where the parts go, in order: BeginPart, PartBytes (never empty; any
// number of times), EndPart (the part's closing delimiter was seen). A part
// cut off by the end of the body or an error gets no EndPart. An error
// returned stops the parser with that error.
class MultipartSink {
 public:
  virtual ~MultipartSink() = default;
  virtual absl::Status BeginPart(const PartHeaders& headers) = 0;
  virtual absl::Status PartBytes(std::string_view bytes) = 0;
  virtual absl::Status EndPart() = 0;
};

inline constexpr int64_t kMultipartUnbounded =
    std::numeric_limits<int64_t>::max();

struct MultipartLimits {
  int64_t max_part_bytes = int64_t{1} << 30;
  int64_t max_total_bytes = int64_t{4} << 30;
  int64_t max_parts = 100000;
  int64_t max_header_bytes = 16384;
  int max_header_lines = 0;  // 0: any number (within max_header_bytes)
};

enum class MultipartLineBreaks { kCrlf, kCrlfOrLf };
enum class MultipartHeaderSyntax { kSimple, kFolded };
enum class MultipartErrors { kByKind, kAtByteOffset };

struct MultipartOptions {
  MultipartLineBreaks line_breaks = MultipartLineBreaks::kCrlf;
  MultipartHeaderSyntax header_syntax = MultipartHeaderSyntax::kSimple;
  bool check_content_length = true;
  bool check_transfer_encoding = false;
  MultipartErrors errors = MultipartErrors::kByKind;
  MultipartLimits limits;
};

// WADO-RS responses (pull.cc): strict CRLF, simple headers, Content-Length
// checked, errors by kind; `limits` as the caller sets them.
MultipartOptions WadoResponseMultipart(const MultipartLimits& limits = {});

// STOW-RS request bodies (stow.cc): CRLF or bare LF, folded headers (at
// most 16 KiB and 64 lines per part), Content-Transfer-Encoding checked,
// every error INVALID_ARGUMENT with its byte offset (-> 400), at most
// `max_parts` parts; no bound on part or body bytes here (the receiver
// counts the body against its own limit, the staging sink each part).
MultipartOptions StowRequestMultipart(int64_t max_parts = 100000);

class MultipartParser {
 public:
  // `sink` must outlive the parser.
  MultipartParser(std::string_view boundary, const MultipartOptions& options,
                  MultipartSink* sink);

  absl::Status Feed(std::string_view bytes);
  absl::Status Finish();

  int64_t parts() const { return parts_; }              // parts begun so far
  bool done() const { return state_ == State::kDone; }  // close seen

 private:
  enum class State {
    kPreamble,      // looking for the first delimiter
    kBoundaryLine,  // after a delimiter: "--", or padding and a line break
    kHeaders,       // a part's header lines
    kBody,          // a part's bytes, up to the next delimiter
    kDone,          // after the close delimiter: the epilogue
  };
  enum class Fault { kMalformed, kLimit };
  absl::Status Error(Fault fault, std::string_view what) const;
  absl::Status Fail(absl::Status status);
  void Drop(size_t n);
  // One step over pending_; sets *progressed when it consumed something.
  absl::Status Step(bool* progressed);
  absl::Status StepBoundaryLine(bool* progressed);
  absl::Status StepHeaders(bool* progressed);
  absl::Status StepBody(bool* progressed);
  absl::Status ParseHeaderLines(std::string_view block, PartHeaders* headers);
  absl::Status AddHeader(std::string name, std::string_view value,
                         PartHeaders* headers);
  absl::Status EmitData(size_t n);
  absl::Status EndPart();

  const MultipartOptions options_;
  const bool lenient_;           // line_breaks == kCrlfOrLf
  const std::string delimiter_;  // "\r\n--" + boundary, or "\n--" + boundary
  MultipartSink* const sink_;
  State state_ = State::kPreamble;
  std::string pending_;   // bytes fed and not yet consumed
  int64_t consumed_ = 0;  // body bytes before pending_ (for error offsets)
  int64_t total_bytes_ = 0;
  int64_t parts_ = 0;
  int64_t part_bytes_ = 0;
  int64_t part_declared_length_ = -1;  // the part's Content-Length, if any
  absl::Status error_;
};

// The longest multipart boundary taken. RFC 2046 5.1.1 says at most 70
// characters, but real DICOMweb clients send longer ones (Orthanc's
// DICOMweb plugin: 73; issue 39): a receiver is liberal in what it accepts
// up to a bound that still caps what a delimiter search holds.
inline constexpr size_t kMaxBoundaryChars = 256;

// The boundary parameter of a multipart Content-Type header value
// ('multipart/related; type="application/dicom"; boundary=abc'), unquoted;
// INVALID_ARGUMENT when the type is not multipart/related or the boundary
// is missing, empty or longer than kMaxBoundaryChars.
absl::StatusOr<std::string> MultipartBoundary(absl::string_view content_type);

// The value of the `type` parameter ("application/dicom"), or empty.
std::string MultipartRootType(absl::string_view content_type);

struct StowContentType {
  bool single_part = false;  // Content-Type: application/dicom
  std::string boundary;      // multipart only
  std::string type;  // the `type` parameter, lower case ("" when absent)
};

// A STOW-RS request's Content-Type: multipart/related with a boundary (1 to
// kMaxBoundaryChars characters of RFC 2046's set) and, when it has a `type`
// parameter, type="application/dicom" (PS3.18 10.5.1.1: only Part 10
// instances are accepted here, no metadata+bulk data); or application/dicom
// alone: a single-part body, one Part 10 instance (`single_part`; Orthanc's
// and dcm4che's clients send one instance so, PS3.18 8.7.3.5 names the
// media type). INVALID_ARGUMENT for a malformed value (-> 400),
// UNIMPLEMENTED for another media type (-> 415).
absl::StatusOr<StowContentType> ParseStowContentType(
    std::string_view content_type);

// The media type of a part (lower case, parameters dropped): its
// Content-Type, else `fallback` (the request's `type` parameter: RFC 2387's
// type of the root, which PS3.18 makes every part's).
std::string PartMediaType(const PartHeaders& headers,
                          const std::string& fallback);

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_MULTIPART_H_
