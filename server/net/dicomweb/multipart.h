// A streaming parser of multipart/related bodies (RFC 2387, framing of RFC
// 2046 5.1.1), as DICOMweb uses them for WADO-RS responses and STOW-RS
// requests (PS3.18 8.6.1.2). Bytes go in as they arrive, in chunks of any
// size; each part's data comes out through callbacks as it is found, so a
// body of any length never sits in memory (only up to one boundary's
// length of look-ahead and one part's headers are held).
//
//   MultipartParser parser(boundary, limits, callbacks);
//   while (...) RETURN_IF_ERROR(parser.Feed(chunk));
//   RETURN_IF_ERROR(parser.Finish());
//
// Contract:
// - The body is an optional preamble, then "--boundary" parts separated by
//   CRLF "--boundary" and ended by CRLF "--boundary--"; transport padding
//   (spaces, tabs) after a delimiter is allowed, the epilogue ignored.
// - Each part's header lines ("Name: value") are given to on_part_begin
//   with lower-case names; a Content-Length header, when present, must be a
//   number within the limits and must equal the part's data length (a part
//   that lies about its size is an error, found at the latest when the
//   part ends).
// - Limits (all errors are INVALID_ARGUMENT for malformed input and
//   RESOURCE_EXHAUSTED for limits, one line, never quoting the body): a
//   part longer than max_part_bytes, more than max_parts parts, more than
//   max_total_bytes fed, a header section longer than max_header_bytes.
// - A callback that returns an error stops the parser with that error; the
//   parser is then unusable (every later Feed returns it again).
// - Finish(): INVALID_ARGUMENT when the closing delimiter was not seen
//   (a truncated body: the last part is cut short).
// Not thread-safe; one parser per body.
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_MULTIPART_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_MULTIPART_H_

#include <cstdint>
#include <functional>
#include <map>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace interslice::server::dicomweb {

struct MultipartLimits {
  int64_t max_part_bytes = int64_t{1} << 30;
  int64_t max_total_bytes = int64_t{4} << 30;
  int64_t max_parts = 100000;
  size_t max_header_bytes = 16384;
};

struct MultipartCallbacks {
  // A part starts; its headers, names lower-cased ("content-type").
  std::function<absl::Status(const std::map<std::string, std::string>&)>
      on_part_begin;
  // The next bytes of the current part's data.
  std::function<absl::Status(absl::string_view)> on_part_data;
  // The current part is complete (its closing delimiter was seen).
  std::function<absl::Status()> on_part_end;
};

// The boundary parameter of a multipart Content-Type header value
// ('multipart/related; type="application/dicom"; boundary=abc'), unquoted;
// INVALID_ARGUMENT when the type is not multipart/related or the boundary
// is missing, empty or longer than 70 characters (RFC 2046).
absl::StatusOr<std::string> MultipartBoundary(absl::string_view content_type);

// The value of the `type` parameter ("application/dicom"), or empty.
std::string MultipartRootType(absl::string_view content_type);

class MultipartParser {
 public:
  MultipartParser(std::string boundary, MultipartLimits limits,
                  MultipartCallbacks callbacks);

  absl::Status Feed(absl::string_view data);
  absl::Status Finish();

  int64_t parts() const { return parts_; }  // parts begun so far
  bool done() const { return state_ == State::kDone; }

 private:
  enum class State { kPreamble, kAfterDelimiter, kHeaders, kBody, kDone };
  absl::Status Step(bool* progressed);
  absl::Status Fail(absl::Status status);
  absl::Status EmitData(size_t n);
  absl::Status EndPart();

  const std::string delimiter_;  // "\r\n--" + boundary
  const MultipartLimits limits_;
  const MultipartCallbacks callbacks_;
  State state_ = State::kPreamble;
  std::string pending_;  // bytes fed and not yet consumed
  int64_t total_bytes_ = 0;
  int64_t parts_ = 0;
  int64_t part_bytes_ = 0;
  int64_t part_declared_length_ = -1;  // the part's Content-Length, if any
  absl::Status error_;
};

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_MULTIPART_H_
