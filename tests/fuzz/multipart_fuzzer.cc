// libFuzzer target for MultipartParser (server/net/dicomweb/multipart.h) in
// its WADO-RS response configuration (WadoResponseMultipart: strict CRLF,
// Content-Length checked, limits); stow_body_fuzzer.cc fuzzes the STOW-RS
// request configuration of the same parser.
//
// Input: one mode byte, one chunk-size byte, then the body (boundary
// "frontier"). Mode bit 0: tiny limits (parts of 64 bytes, 4 parts, 256
// bytes in all, 64 bytes of headers). The body is parsed twice: fed whole,
// and fed in chunks of 1 + (chunk byte % 64) bytes; then Finish().
//
// Checks, beyond "no crash, no hang, no unbounded allocation": both feeds
// give the same outcome (status code, parts, data of each part): chunking
// must not change what a body means; data only arrives inside a part; no
// part is longer than the limit nor than the body; every error is one line.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "server/net/dicomweb/multipart.h"

namespace {

using interslice::server::dicomweb::MultipartLimits;
using interslice::server::dicomweb::MultipartParser;
using interslice::server::dicomweb::MultipartSink;
using interslice::server::dicomweb::PartHeaders;
using interslice::server::dicomweb::WadoResponseMultipart;

void Check(bool condition) {
  if (!condition) __builtin_trap();
}

struct Outcome {
  absl::StatusCode code = absl::StatusCode::kOk;
  std::vector<std::string> parts;  // data of each part begun
  std::vector<bool> ended;
};

// Collects the parts into an Outcome, checking the sink's contract.
class CollectingSink : public MultipartSink {
 public:
  CollectingSink(Outcome* out, const MultipartLimits& limits)
      : out_(out), limits_(limits) {}
  absl::Status BeginPart(const PartHeaders&) override {
    Check(!in_part_);
    in_part_ = true;
    out_->parts.emplace_back();
    out_->ended.push_back(false);
    return absl::OkStatus();
  }
  absl::Status PartBytes(std::string_view data) override {
    Check(in_part_ && !data.empty());
    out_->parts.back().append(data.data(), data.size());
    Check(static_cast<int64_t>(out_->parts.back().size()) <=
          limits_.max_part_bytes);
    return absl::OkStatus();
  }
  absl::Status EndPart() override {
    Check(in_part_);
    in_part_ = false;
    out_->ended.back() = true;
    return absl::OkStatus();
  }

 private:
  Outcome* const out_;
  const MultipartLimits limits_;
  bool in_part_ = false;
};

Outcome Parse(const std::string& body, size_t chunk,
              const MultipartLimits& limits) {
  Outcome out;
  CollectingSink sink(&out, limits);
  MultipartParser parser("frontier", WadoResponseMultipart(limits), &sink);
  absl::Status status;
  for (size_t at = 0; at < body.size() && status.ok(); at += chunk) {
    status = parser.Feed(std::string_view(body).substr(at, chunk));
  }
  if (status.ok()) status = parser.Finish();
  if (!status.ok()) {
    Check(status.message().find('\n') == absl::string_view::npos);
    // An error after it is reported stays.
    Check(parser.Feed("x").code() == status.code());
  }
  out.code = status.code();
  Check(static_cast<int64_t>(out.parts.size()) <= limits.max_parts);
  size_t data = 0;
  for (const std::string& p : out.parts) data += p.size();
  Check(data <= body.size());
  return out;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 2) return 0;
  MultipartLimits limits;
  if ((data[0] & 1) != 0) {
    limits.max_part_bytes = 64;
    limits.max_parts = 4;
    limits.max_total_bytes = 256;
    limits.max_header_bytes = 64;
  } else {
    limits.max_part_bytes = 1 << 16;
    limits.max_parts = 256;
    limits.max_total_bytes = 1 << 20;
    limits.max_header_bytes = 1024;
  }
  const size_t chunk = 1 + data[1] % 64;
  const std::string body(reinterpret_cast<const char*>(data + 2), size - 2);
  const Outcome whole = Parse(body, body.size() + 1, limits);
  const Outcome pieces = Parse(body, chunk, limits);
  Check(whole.code == pieces.code);
  if (whole.code == absl::StatusCode::kOk) {
    Check(whole.parts == pieces.parts);
    Check(whole.ended == pieces.ended);
  }
  return 0;
}
