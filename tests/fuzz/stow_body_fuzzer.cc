// libFuzzer target for MultipartParser (server/net/dicomweb/multipart.h) in
// its STOW-RS request configuration (StowRequestMultipart: CRLF or bare LF,
// folded headers, Content-Transfer-Encoding checked, errors with byte
// offsets) on arbitrary bytes; multipart_fuzzer.cc fuzzes the WADO-RS
// response configuration of the same parser. The first byte picks the
// boundary's length (1-70, taken from the next bytes, mapped into RFC 2046's
// characters), the next the size of each read; the rest is the body, parsed
// twice: fed whole and in reads of that size.
//
// Checks, beyond "no crash, no hang, no unbounded allocation": bytes arrive
// only inside a part, never empty; a part has at most 64 headers; both
// feeds give the same outcome (status, parts and their bytes); every error
// is one INVALID_ARGUMENT line and stays.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <string_view>
#include <vector>

#include "server/net/dicomweb/multipart.h"

namespace {

using interslice::server::dicomweb::MultipartOptions;
using interslice::server::dicomweb::MultipartParser;
using interslice::server::dicomweb::MultipartSink;
using interslice::server::dicomweb::PartHeaders;
using interslice::server::dicomweb::StowRequestMultipart;

struct Outcome {
  absl::Status status;
  std::vector<std::string> parts;  // bytes of each part begun
  std::vector<bool> ended;
};

class CheckingSink : public MultipartSink {
 public:
  explicit CheckingSink(Outcome* out) : out_(out) {}
  absl::Status BeginPart(const PartHeaders& headers) override {
    if (in_part_) std::abort();
    if (headers.size() > 64) std::abort();
    in_part_ = true;
    out_->parts.emplace_back();
    out_->ended.push_back(false);
    return absl::OkStatus();
  }
  absl::Status PartBytes(std::string_view bytes) override {
    if (!in_part_ || bytes.empty()) std::abort();
    out_->parts.back().append(bytes);
    return absl::OkStatus();
  }
  absl::Status EndPart() override {
    if (!in_part_) std::abort();
    in_part_ = false;
    out_->ended.back() = true;
    return absl::OkStatus();
  }

 private:
  Outcome* const out_;
  bool in_part_ = false;
};

Outcome Parse(const std::string& boundary, std::string_view body,
              size_t piece) {
  Outcome out;
  CheckingSink sink(&out);
  MultipartOptions options = StowRequestMultipart(/*max_parts=*/64);
  options.limits.max_header_bytes = 512;
  MultipartParser parser(boundary, options, &sink);
  for (size_t i = 0; i < body.size() && out.status.ok(); i += piece) {
    out.status = parser.Feed(body.substr(i, piece));
  }
  if (out.status.ok()) out.status = parser.Finish();
  if (!out.status.ok()) {
    if (out.status.code() != absl::StatusCode::kInvalidArgument) std::abort();
    if (out.status.message().find('\n') != absl::string_view::npos) {
      std::abort();
    }
    if (parser.Feed("x") != out.status) std::abort();  // the error stays
  }
  if (out.parts.size() > 64) std::abort();
  return out;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 2) return 0;
  static const char kChars[] =
      "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ'()+_,-./"
      ":=?";
  const size_t length = 1 + data[0] % 70;
  const size_t piece = 1 + data[1] % 64;
  data += 2;
  size -= 2;
  if (size < length) return 0;
  std::string boundary;
  for (size_t i = 0; i < length; ++i) {
    boundary += kChars[data[i] % (sizeof(kChars) - 1)];
  }
  data += length;
  size -= length;
  const std::string_view body(reinterpret_cast<const char*>(data), size);
  const Outcome whole = Parse(boundary, body, body.size() + 1);
  const Outcome pieces = Parse(boundary, body, piece);
  // Reads must not change what a body means.
  if (whole.status != pieces.status) std::abort();
  if (whole.status.ok() &&
      (whole.parts != pieces.parts || whole.ended != pieces.ended)) {
    std::abort();
  }
  return 0;
}
