// STOW-RS body parser (server/net/dicomweb/stow_body.h) on arbitrary bytes. The
// first byte picks the boundary's length (1-70, taken from the next bytes,
// mapped into RFC 2046's characters), the next the size of each read; the
// rest is the body. The sink checks that bytes arrive only inside a part.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "server/net/dicomweb/stow_body.h"

namespace {

using interslice::server::dicomweb::PartHeaders;
using interslice::server::dicomweb::StowBodyParser;
using interslice::server::dicomweb::StowPartSink;

class CheckingSink : public StowPartSink {
 public:
  absl::Status BeginPart(const PartHeaders& headers) override {
    if (in_part_) std::abort();
    if (headers.size() > 64) std::abort();
    in_part_ = true;
    return absl::OkStatus();
  }
  absl::Status PartBytes(std::string_view bytes) override {
    if (!in_part_ || bytes.empty()) std::abort();
    return absl::OkStatus();
  }
  absl::Status EndPart() override {
    if (!in_part_) std::abort();
    in_part_ = false;
    return absl::OkStatus();
  }

 private:
  bool in_part_ = false;
};

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
  CheckingSink sink;
  StowBodyParser parser(boundary, &sink,
                        {.max_part_header_bytes = 512, .max_parts = 64});
  const std::string_view body(reinterpret_cast<const char*>(data), size);
  for (size_t i = 0; i < body.size(); i += piece) {
    if (!parser.Feed(body.substr(i, piece)).ok()) return 0;
  }
  (void)parser.Finish();
  return 0;
}
