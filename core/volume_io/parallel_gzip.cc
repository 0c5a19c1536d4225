#include "core/volume_io/parallel_gzip.h"

#include <libdeflate.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_pipeline.h>
#include <tbb/task_arena.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <memory>
#include <mutex>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "core/common/status_macros.h"

namespace interslice::volume_io_internal {
namespace {

// One block of the logical input stream, then its compressed member.
struct Block {
  size_t offset = 0;  // in the concatenation of the pieces
  size_t length = 0;
  bool last = false;
  std::vector<uint8_t> member;  // a gzip member, or a run of deflate blocks
  uint32_t crc = 0;             // CRC-32 of the input (single member)
};

// Deflates `length` bytes as a run of raw deflate blocks that a following
// run can continue (Z_SYNC_FLUSH ends on a byte boundary without the final
// bit), or that ends the stream (`last`). Z_RLE finds only runs (distance 1),
// so no block refers to another block's data and blocks can be deflated
// independently, as pigz does with a preset dictionary.
absl::Status DeflateRun(const uint8_t* in, size_t length, bool last,
                        std::vector<uint8_t>& out) {
  z_stream z{};
  if (deflateInit2(&z, /*level=*/1, Z_DEFLATED, /*windowBits=*/-15,
                   /*memLevel=*/8, Z_RLE) != Z_OK) {
    return absl::ResourceExhaustedError("cannot start zlib deflate");
  }
  out.resize(deflateBound(&z, length) + 16);
  z.next_in = const_cast<Bytef*>(in);
  z.avail_in = static_cast<uInt>(length);
  z.next_out = out.data();
  z.avail_out = static_cast<uInt>(out.size());
  const int result = deflate(&z, last ? Z_FINISH : Z_SYNC_FLUSH);
  const bool ok = last ? result == Z_STREAM_END
                       : (result == Z_OK && z.avail_in == 0 && z.avail_out > 0);
  out.resize(out.size() - z.avail_out);
  deflateEnd(&z);
  return ok ? absl::OkStatus() : absl::InternalError("zlib deflate failed");
}

struct CompressorDeleter {
  void operator()(libdeflate_compressor* c) const {
    libdeflate_free_compressor(c);
  }
};
using CompressorPtr = std::unique_ptr<libdeflate_compressor, CompressorDeleter>;

absl::Status WriteAll(int fd, const uint8_t* data, size_t size) {
  while (size > 0) {
    const ssize_t n = ::write(fd, data, size);
    if (n < 0) {
      if (errno == EINTR) continue;
      return absl::InternalError(
          std::error_code(errno, std::generic_category()).message());
    }
    data += n;
    size -= static_cast<size_t>(n);
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status WriteParallelGzip(
    int fd, const std::vector<std::span<const std::byte>>& pieces,
    const GzipOptions& options, const ComputeContext& context) {
  if (options.level < 0 || options.level > 12 || options.block_size == 0 ||
      (options.single_member && options.block_size > (size_t{1} << 30))) {
    return absl::InvalidArgumentError(
        absl::StrCat("gzip level ", options.level, " or block size ",
                     options.block_size, " out of range"));
  }
  // Piece starts in the logical stream, for gathering a block.
  std::vector<size_t> starts;
  size_t total = 0;
  for (const auto& piece : pieces) {
    starts.push_back(total);
    total += piece.size();
  }
  // Copies [offset, offset + length) of the stream into `out`; returns a
  // pointer to the bytes without a copy when they lie in one piece.
  auto gather = [&](size_t offset, size_t length,
                    std::vector<uint8_t>& scratch) -> const uint8_t* {
    size_t p = std::upper_bound(starts.begin(), starts.end(), offset) -
               starts.begin() - 1;
    // Skip empty pieces that start at the same offset.
    while (p < pieces.size() && offset - starts[p] >= pieces[p].size() &&
           length > 0) {
      ++p;
    }
    if (length == 0 || offset - starts[p] + length <= pieces[p].size()) {
      return length == 0 ? nullptr
                         : reinterpret_cast<const uint8_t*>(
                               pieces[p].data() + (offset - starts[p]));
    }
    scratch.resize(length);
    size_t copied = 0;
    while (copied < length) {
      const size_t in_piece = offset + copied - starts[p];
      const size_t n = std::min(length - copied, pieces[p].size() - in_piece);
      std::memcpy(scratch.data() + copied, pieces[p].data() + in_piece, n);
      copied += n;
      ++p;
    }
    return scratch.data();
  };

  tbb::enumerable_thread_specific<CompressorPtr> compressors([&] {
    return CompressorPtr(libdeflate_alloc_compressor(options.level));
  });
  tbb::enumerable_thread_specific<std::vector<uint8_t>> scratches;
  std::mutex status_mutex;
  absl::Status status;
  std::atomic<bool> failed{false};
  auto fail = [&](absl::Status s) {
    std::lock_guard<std::mutex> lock(status_mutex);
    if (status.ok()) status = std::move(s);
    failed.store(true, std::memory_order_relaxed);
  };

  const int threads = context.threads > 0
                          ? context.threads
                          : tbb::this_task_arena::max_concurrency();
  size_t next = 0;
  // An empty input is still one (empty) member: a gzip file needs one.
  bool emitted_any = false;
  // Single member: gzip header (no name, no time, OS unknown), the deflate
  // runs, then the CRC-32 and the length modulo 2^32 of the whole input.
  uint32_t crc = 0;
  if (options.single_member) {
    const uint8_t header[10] = {0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 0, 255};
    INTERSLICE_RETURN_IF_ERROR(WriteAll(fd, header, sizeof(header)));
  }
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_pipeline(
        static_cast<size_t>(2 * std::max(1, threads)),
        tbb::make_filter<void, Block*>(
            tbb::filter_mode::serial_in_order,
            [&](tbb::flow_control& fc) -> Block* {
              if (failed.load(std::memory_order_relaxed) ||
                  (next >= total && emitted_any)) {
                fc.stop();
                return nullptr;
              }
              if (absl::Status s = context.CheckCancelled(); !s.ok()) {
                fail(std::move(s));
                fc.stop();
                return nullptr;
              }
              auto* block = new Block;
              block->offset = next;
              block->length = std::min(options.block_size, total - next);
              next += block->length;
              block->last = next >= total;
              emitted_any = true;
              return block;
            }) &
            tbb::make_filter<Block*, Block*>(
                tbb::filter_mode::parallel,
                [&](Block* block) -> Block* {
                  if (failed.load(std::memory_order_relaxed)) return block;
                  if (options.single_member) {
                    const uint8_t* in =
                        gather(block->offset, block->length, scratches.local());
                    block->crc =
                        static_cast<uint32_t>(crc32_z(0, in, block->length));
                    if (absl::Status s = DeflateRun(in, block->length,
                                                    block->last, block->member);
                        !s.ok()) {
                      fail(std::move(s));
                    }
                    return block;
                  }
                  CompressorPtr& compressor = compressors.local();
                  if (compressor == nullptr) {
                    fail(absl::ResourceExhaustedError(
                        "cannot allocate a deflate compressor"));
                    return block;
                  }
                  const uint8_t* in =
                      gather(block->offset, block->length, scratches.local());
                  block->member.resize(libdeflate_gzip_compress_bound(
                      compressor.get(), block->length));
                  const size_t n = libdeflate_gzip_compress(
                      compressor.get(), in, block->length, block->member.data(),
                      block->member.size());
                  if (n == 0) {
                    fail(absl::InternalError("deflate failed"));
                  }
                  block->member.resize(n);
                  return block;
                }) &
            tbb::make_filter<Block*, void>(
                tbb::filter_mode::serial_in_order, [&](Block* block) {
                  std::unique_ptr<Block> owned(block);
                  if (failed.load(std::memory_order_relaxed)) return;
                  if (options.single_member) {
                    crc = static_cast<uint32_t>(
                        crc32_combine(crc, owned->crc, owned->length));
                  }
                  if (absl::Status s = WriteAll(fd, owned->member.data(),
                                                owned->member.size());
                      !s.ok()) {
                    fail(std::move(s));
                  }
                }));
  });
  if (status.ok() && options.single_member) {
    uint8_t trailer[8];
    const uint32_t size = static_cast<uint32_t>(total);
    for (int i = 0; i < 4; ++i) {
      trailer[i] = static_cast<uint8_t>(crc >> (8 * i));
      trailer[4 + i] = static_cast<uint8_t>(size >> (8 * i));
    }
    status = WriteAll(fd, trailer, sizeof(trailer));
  }
  return status;
}

}  // namespace interslice::volume_io_internal
