// Private to core/surface: writes a file in full or not at all (a temporary
// file next to the target, flushed and synced, then renamed over it).
#ifndef INTERSLICE_CORE_SURFACE_ATOMIC_FILE_H_
#define INTERSLICE_CORE_SURFACE_ATOMIC_FILE_H_

#include <cstdio>
#include <functional>
#include <string>

#include "absl/status/status.h"

namespace interslice::surface_internal {

// Collects output in memory and hands it to the file in large chunks.
class ChunkedWriter {
 public:
  explicit ChunkedWriter(std::FILE* file) : file_(file) {}
  ChunkedWriter(const ChunkedWriter&) = delete;
  ChunkedWriter& operator=(const ChunkedWriter&) = delete;

  // Append output here, then call MaybeFlush() now and then.
  std::string& buffer() { return buffer_; }
  void MaybeFlush() {
    if (buffer_.size() >= kChunkBytes) Flush();
  }
  void Flush();
  // errno of the first failed write, or 0.
  int error() const { return error_; }

 private:
  static constexpr size_t kChunkBytes = size_t{1} << 20;
  std::FILE* file_;
  std::string buffer_;
  int error_ = 0;
};

// Writes `path` through `fill` via "<path>.tmp-<random>" and a rename. On any
// failure the temporary file is removed and INTERNAL names `path`.
absl::Status WriteFileAtomically(
    const std::string& path, const std::function<void(ChunkedWriter&)>& fill);

}  // namespace interslice::surface_internal

#endif  // INTERSLICE_CORE_SURFACE_ATOMIC_FILE_H_
