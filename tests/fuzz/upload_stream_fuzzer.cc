// libFuzzer target for UploadStream (server/net/grpc/upload_stream.h), the
// validator of Interpolate and Submit upload streams.
//
// Input: one mode byte, then records of a 2-byte little-endian length and
// that many bytes, each parsed as an interslice.v1.UploadRequest (bytes
// that do not parse become an empty message) and fed to the validator in
// order; then Finish(). Mode bit 0: fix up the SHA-256 of a file's first
// chunk when that chunk holds the whole file, so that inputs get past the
// hash check to multi-file streams and Finish(). Mode bit 1: tiny limits.
//
// Checks, beyond "no crash, no hang, no unbounded allocation": every step
// the validator accepts is consistent (data within the chunk limit and the
// message, offsets and byte counts within the header's totals), and every
// error message is one line.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/common/sha256.h"
#include "google/protobuf/stubs/logging.h"
#include "interslice/v1/interslice.pb.h"
#include "server/base/log_safe.h"
#include "server/net/grpc/upload_stream.h"

namespace {

using interslice::Sha256;
using interslice::server::IsLogSafe;
using interslice::server::UploadStep;
using interslice::server::UploadStream;
using interslice::server::UploadStreamLimits;

constexpr int kMaxMessages = 4096;

void Check(bool condition) {
  if (!condition) __builtin_trap();
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  // Unparseable inputs are expected: keep protobuf quiet about them.
  google::protobuf::SetLogHandler(nullptr);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const uint8_t mode = data[0];
  const bool fix_sha = (mode & 1) != 0;
  UploadStreamLimits limits;
  if ((mode & 2) != 0) {
    limits.max_chunk_bytes = 16;
    limits.max_upload_bytes = 64;
    limits.max_files = 4;
    limits.max_file_name_bytes = 8;
  } else {
    limits.max_chunk_bytes = 4096;
    limits.max_upload_bytes = 1 << 20;
    limits.max_files = 64;
    limits.max_file_name_bytes = 256;
  }
  UploadStream stream(limits);
  size_t pos = 1;
  int last_index = -1;
  for (int messages = 0; pos + 2 <= size && messages < kMaxMessages;
       ++messages) {
    size_t n = data[pos] | (static_cast<size_t>(data[pos + 1]) << 8);
    pos += 2;
    if (n > size - pos) n = size - pos;
    interslice::v1::UploadRequest request;
    if (!request.ParseFromArray(data + pos, static_cast<int>(n))) {
      request.Clear();
    }
    pos += n;
    if (fix_sha && request.has_chunk()) {
      interslice::v1::FileChunk* chunk = request.mutable_chunk();
      if (chunk->offset() == 0 && chunk->file_size() >= 0 &&
          static_cast<uint64_t>(chunk->file_size()) == chunk->data().size()) {
        Sha256 hash;
        hash.Update(chunk->data());
        chunk->set_sha256(hash.Finish());
      }
    }
    UploadStep step;
    const absl::Status status = stream.Next(request, &step);
    if (!status.ok()) {
      Check(IsLogSafe(status.message()));
      Check(stream.Next(request, &step) == status);  // errors are final
      break;
    }
    const interslice::v1::UploadHeader& header = stream.header();
    Check(stream.has_header());
    Check(stream.bytes_received() >= 0 &&
          stream.bytes_received() <= header.total_bytes());
    if (step.header) {
      Check(request.has_header() && step.data.empty() && !step.open_file);
      continue;
    }
    Check(request.has_chunk());
    Check(step.file_index >= 0 && step.file_index < header.file_count());
    Check(step.file_index == last_index ||
          (step.file_index == last_index + 1 && step.open_file));
    last_index = step.file_index;
    Check(static_cast<int64_t>(step.data.size()) <= limits.max_chunk_bytes);
    Check(step.data.data() == request.chunk().data().data() ||
          step.data.empty());
    Check(step.offset >= 0 && step.offset == request.chunk().offset());
    Check(step.offset + static_cast<int64_t>(step.data.size()) <=
          header.total_bytes());
  }
  const absl::Status finished = stream.Finish();
  if (!finished.ok()) Check(IsLogSafe(finished.message()));
  return 0;
}
