// A streaming parser of the body of a STOW-RS request (DICOM PS3.18 10.5):
// multipart/related (RFC 2387) with the boundary rules of RFC 2046 5.1.1,
// each part handed to a sink as its bytes arrive, so that no body is ever
// held in memory whole (a part goes straight to a staging file; see
// server/net/dicomweb/stow.h).
//
// Contract:
// - ParseStowContentType: the request's Content-Type must be
//   multipart/related with a boundary (1-70 characters, RFC 2046) and, when
//   it has a `type` parameter, type="application/dicom" (PS3.18 10.5.1.1:
//   only Part 10 instances are accepted here, no metadata+bulk data).
//   INVALID_ARGUMENT for a malformed value (-> 400), UNIMPLEMENTED for
//   another media type (-> 415).
// - StowBodyParser::Feed takes the body in pieces of any size (a delimiter
//   may be split across pieces anywhere). Line breaks may be CRLF (the
//   standard) or a bare LF (lenient senders); a delimiter's line break
//   belongs to the delimiter, never to the part before it (so a part that
//   ends in CR before a bare-LF delimiter loses that CR: CRLF is what PS3.18
//   senders use, and a CR there is taken as theirs). The preamble
//   before the first delimiter and the epilogue after the close delimiter
//   are skipped. Transport padding (spaces, tabs) after a boundary is
//   allowed.
// - Part headers are bounded (max_part_header_bytes in all per part, at
//   most 64 header lines) and parsed into lower-cased names; a part may not
//   have a Content-Transfer-Encoding other than binary, 8bit or 7bit.
// - Finish() after the last piece: OK only when the close delimiter
//   ("--boundary--") was seen. A body that ends earlier (a client that
//   stops, a missing final boundary) is INVALID_ARGUMENT: the caller must
//   treat every part as unconfirmed (the series is then incomplete).
// - Every error is INVALID_ARGUMENT with the byte offset and what is wrong;
//   no body bytes are quoted. A sink's error stops the parse and is
//   returned as it is. After an error the parser takes nothing more.
// - Memory: O(boundary + max_part_header_bytes), whatever the body size.
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_STOW_BODY_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_STOW_BODY_H_

#include <cstdint>
#include <map>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace interslice::server::dicomweb {

struct StowContentType {
  std::string boundary;
  std::string type;  // the `type` parameter, lower case ("" when absent)
};

absl::StatusOr<StowContentType> ParseStowContentType(
    std::string_view content_type);

// A part's headers: lower-cased names, values trimmed (the last of repeated
// names wins).
using PartHeaders = std::map<std::string, std::string>;

// The media type of a part (lower case, parameters dropped): its
// Content-Type, else `fallback` (the request's `type` parameter: RFC 2387's
// type of the root, which PS3.18 makes every part's).
std::string PartMediaType(const PartHeaders& headers,
                          const std::string& fallback);

class StowPartSink {
 public:
  virtual ~StowPartSink() = default;
  virtual absl::Status BeginPart(const PartHeaders& headers) = 0;
  virtual absl::Status PartBytes(std::string_view bytes) = 0;
  virtual absl::Status EndPart() = 0;
};

struct StowBodyLimits {
  int64_t max_part_header_bytes = 16 * 1024;
  int64_t max_parts = 100000;
};

class StowBodyParser {
 public:
  StowBodyParser(std::string boundary, StowPartSink* sink,
                 StowBodyLimits limits = {});

  absl::Status Feed(std::string_view bytes);
  absl::Status Finish();

  int64_t parts() const { return parts_; }
  bool complete() const { return state_ == State::kEpilogue; }

 private:
  enum class State {
    kPreamble,      // looking for the first delimiter
    kBoundaryLine,  // after a delimiter: "--", or padding and a line break
    kHeaders,       // a part's header lines
    kBody,          // a part's bytes, up to the next delimiter
    kEpilogue,      // after the close delimiter
    kFailed,
  };
  absl::Status Fail(absl::Status status);
  absl::Status Error(std::string_view what) const;
  // Steps over buffer_ until it needs more bytes (or is done).
  absl::Status Run(bool at_end);
  absl::Status ParseHeaders(std::string_view block);

  const std::string delimiter_;  // "\n--" + boundary
  StowPartSink* const sink_;
  const StowBodyLimits limits_;
  State state_ = State::kPreamble;
  std::string buffer_;
  int64_t consumed_ = 0;  // body bytes before buffer_ (for error offsets)
  int64_t parts_ = 0;
  bool in_part_ = false;
};

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_STOW_BODY_H_
