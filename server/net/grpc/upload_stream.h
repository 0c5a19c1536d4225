// The rules of an upload stream (Interpolate and Submit), without I/O: feed
// it every UploadRequest in order; it checks the header, the file order,
// indexes, names, sizes, offsets, the size limits and each file's SHA-256,
// and tells the caller which bytes to write where. The reactors' UploadSink
// does the writing; tests/fuzz/upload_stream_fuzzer.cc fuzzes this class.
//
// Pure and bounded: no I/O, no allocation that grows with the stream (it
// keeps the header, the current file's name and a SHA-256 state). Not
// thread-safe; one instance per upload.
#ifndef INTERSLICE_SERVER_NET_GRPC_UPLOAD_STREAM_H_
#define INTERSLICE_SERVER_NET_GRPC_UPLOAD_STREAM_H_

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice {
class Sha256;
}  // namespace interslice

namespace interslice::server {

struct UploadStreamLimits {
  // Largest FileChunk.data, bytes.
  int64_t max_chunk_bytes = 1 << 20;
  // Largest header.total_bytes (RESOURCE_EXHAUSTED beyond).
  int64_t max_upload_bytes = int64_t{2} << 30;
  // Largest header.file_count.
  int max_files = 100000;
  // Longest FileChunk.file_name, bytes.
  int64_t max_file_name_bytes = 1024;
};

// What to do with one accepted message, in this order.
struct UploadStep {
  // The message was the header (UploadStream::header()): admit the job.
  bool header = false;
  // The file the rest of the step is about; -1 for the header.
  int file_index = -1;
  // First chunk of the file: create it, empty.
  bool open_file = false;
  // Write `data` (a view into the message passed to Next) at `offset`.
  int64_t offset = 0;
  std::string_view data;
  // The file is complete and its SHA-256 matched: flush and close it.
  bool close_file = false;
};

class UploadStream {
 public:
  explicit UploadStream(const UploadStreamLimits& limits);
  ~UploadStream();
  UploadStream(const UploadStream&) = delete;
  UploadStream& operator=(const UploadStream&) = delete;

  // Checks the next message and fills `step`. INVALID_ARGUMENT (order, size,
  // offset, name or SHA-256 errors) or RESOURCE_EXHAUSTED (header above the
  // upload limit). Errors are final: every later call returns the same one.
  // Messages name files by index only, never by name or content.
  absl::Status Next(const v1::UploadRequest& message, UploadStep* step);

  // The client half-closed: OK only if every file arrived whole and
  // verified, and the sizes add up to header.total_bytes.
  absl::Status Finish();

  bool has_header() const { return has_header_; }
  const v1::UploadHeader& header() const { return header_; }
  // File bytes accepted so far.
  int64_t bytes_received() const { return received_; }

 private:
  absl::Status Fail(absl::Status status);
  absl::Status CheckHeader(const v1::UploadHeader& header) const;
  absl::Status CheckFileName(const std::string& name) const;

  const UploadStreamLimits limits_;
  absl::Status error_;
  bool has_header_ = false;
  v1::UploadHeader header_;
  int index_ = -1;        // current file
  bool complete_ = true;  // the current file (if any) is whole and verified
  int64_t size_ = 0, written_ = 0, received_ = 0;
  std::string name_, expected_sha_;
  std::unique_ptr<Sha256> hash_;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_UPLOAD_STREAM_H_
