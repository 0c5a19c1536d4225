#include "core/volume_io/parallel_gzip.h"

#include <fcntl.h>
#include <unistd.h>
#include <zlib.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "gtest/gtest.h"

namespace interslice::volume_io_internal {
namespace {

// Decompresses every member of a gzip file with zlib's gzread (the reader
// ITK's NIfTI and NRRD IO use), and counts the members by walking them with
// inflate, which stops at the end of each.
struct Unzipped {
  std::string bytes;
  int members = 0;
  bool ok = false;
};

Unzipped Gunzip(const std::string& path) {
  Unzipped result;
  gzFile in = gzopen(path.c_str(), "rb");
  if (in == nullptr) return result;
  char buffer[1 << 16];
  int n;
  while ((n = gzread(in, buffer, sizeof(buffer))) > 0) {
    result.bytes.append(buffer, n);
  }
  result.ok = n == 0 && gzclose(in) == Z_OK;

  std::FILE* f = std::fopen(path.c_str(), "rb");
  std::string compressed;
  while ((n = static_cast<int>(std::fread(buffer, 1, sizeof(buffer), f))) > 0) {
    compressed.append(buffer, n);
  }
  std::fclose(f);
  size_t offset = 0;
  std::vector<unsigned char> sink(1 << 16);
  while (offset < compressed.size()) {
    z_stream z{};
    if (inflateInit2(&z, 16 + MAX_WBITS) != Z_OK) return Unzipped{};
    z.next_in = reinterpret_cast<Bytef*>(compressed.data() + offset);
    z.avail_in = static_cast<uInt>(compressed.size() - offset);
    int status;
    do {
      z.next_out = sink.data();
      z.avail_out = static_cast<uInt>(sink.size());
      status = inflate(&z, Z_NO_FLUSH);
    } while (status == Z_OK);
    const size_t used = compressed.size() - offset - z.avail_in;
    inflateEnd(&z);
    if (status != Z_STREAM_END) return Unzipped{};
    offset += used;
    ++result.members;
  }
  return result;
}

class ParallelGzipTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = std::filesystem::path(::testing::TempDir()) /
           (std::string("parallel_gzip_test_") + info->name());
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  // Writes `pieces` to a new file through WriteParallelGzip.
  absl::Status Write(const std::string& name,
                     const std::vector<std::string>& pieces,
                     const GzipOptions& options,
                     const ComputeContext& context) {
    const std::string path = (dir_ / name).string();
    const int fd = open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd < 0) return absl::InternalError("open");
    std::vector<std::span<const std::byte>> spans;
    for (const std::string& p : pieces) {
      spans.push_back(std::as_bytes(std::span(p.data(), p.size())));
    }
    absl::Status status = WriteParallelGzip(fd, spans, options, context);
    close(fd);
    return status;
  }
  std::string Path(const std::string& name) const { return dir_ / name; }

  std::filesystem::path dir_;
};

std::string Noise(size_t size, uint32_t seed) {
  std::mt19937 engine(seed);
  std::string s(size, '\0');
  // Half noise, half runs: something for deflate to find in each block.
  for (size_t i = 0; i < size; ++i) {
    s[i] = (i / 1000) % 2 ? static_cast<char>(engine() & 0x0f) : 'a';
  }
  return s;
}

TEST_F(ParallelGzipTest, MembersConcatenateToTheInputAcrossPieceBoundaries) {
  // Pieces of awkward sizes, including empty ones, so that blocks straddle
  // piece boundaries and pieces straddle blocks.
  const std::vector<std::string> pieces = {
      "", Noise(352, 1), Noise(1000, 2), "", Noise(25000, 3), Noise(7, 4), ""};
  std::string all;
  for (const auto& p : pieces) all += p;
  GzipOptions options;
  options.block_size = 4096;
  ASSERT_TRUE(Write("a.gz", pieces, options, {.threads = 2}).ok());
  const Unzipped unzipped = Gunzip(Path("a.gz"));
  ASSERT_TRUE(unzipped.ok);
  EXPECT_EQ(unzipped.bytes, all);
  EXPECT_EQ(unzipped.members, static_cast<int>((all.size() + 4095) / 4096));
}

TEST_F(ParallelGzipTest, OutputDoesNotDependOnThreads) {
  const std::vector<std::string> pieces = {Noise(100, 5), Noise(300000, 6)};
  GzipOptions options;
  options.block_size = 10000;
  ASSERT_TRUE(Write("one.gz", pieces, options, {.threads = 1}).ok());
  ASSERT_TRUE(Write("four.gz", pieces, options, {.threads = 4}).ok());
  const Unzipped one = Gunzip(Path("one.gz"));
  ASSERT_TRUE(one.ok);
  EXPECT_EQ(one.bytes, pieces[0] + pieces[1]);
  std::ifstream a(Path("one.gz"), std::ios::binary),
      b(Path("four.gz"), std::ios::binary);
  const std::string bytes_a((std::istreambuf_iterator<char>(a)), {});
  const std::string bytes_b((std::istreambuf_iterator<char>(b)), {});
  EXPECT_EQ(bytes_a, bytes_b);
}

TEST_F(ParallelGzipTest, SingleMemberJoinsTheBlocksIntoOneStream) {
  const std::vector<std::string> pieces = {Noise(352, 11), "", Noise(70001, 12),
                                           Noise(5, 13)};
  const std::string all = pieces[0] + pieces[2] + pieces[3];
  GzipOptions options;
  options.single_member = true;
  options.block_size = 4096;  // 18 blocks
  ASSERT_TRUE(Write("one.gz", pieces, options, {.threads = 3}).ok());
  const Unzipped unzipped = Gunzip(Path("one.gz"));
  ASSERT_TRUE(unzipped.ok);
  EXPECT_EQ(unzipped.bytes, all);
  EXPECT_EQ(unzipped.members, 1);
  EXPECT_LT(std::filesystem::file_size(Path("one.gz")), all.size());
  // Independent of the thread count, and readable by a reader that takes
  // one member only (a single zlib inflate over the whole file).
  ASSERT_TRUE(Write("two.gz", pieces, options, {.threads = 1}).ok());
  std::ifstream a(Path("one.gz"), std::ios::binary),
      b(Path("two.gz"), std::ios::binary);
  EXPECT_EQ(std::string((std::istreambuf_iterator<char>(a)), {}),
            std::string((std::istreambuf_iterator<char>(b)), {}));

  options.block_size = 1000;
  ASSERT_TRUE(Write("empty.gz", {}, options, {}).ok());
  const Unzipped empty = Gunzip(Path("empty.gz"));
  ASSERT_TRUE(empty.ok);
  EXPECT_EQ(empty.bytes, "");
  EXPECT_EQ(empty.members, 1);
}

TEST_F(ParallelGzipTest, EmptyInputIsOneEmptyMember) {
  ASSERT_TRUE(Write("empty.gz", {}, {}, {}).ok());
  const Unzipped unzipped = Gunzip(Path("empty.gz"));
  ASSERT_TRUE(unzipped.ok);
  EXPECT_EQ(unzipped.bytes, "");
  EXPECT_EQ(unzipped.members, 1);
}

TEST_F(ParallelGzipTest, LevelZeroStoresAndStillReads) {
  const std::string data = Noise(50000, 7);
  GzipOptions options;
  options.level = 0;
  ASSERT_TRUE(Write("stored.gz", {data}, options, {}).ok());
  EXPECT_GT(std::filesystem::file_size(Path("stored.gz")), data.size());
  EXPECT_EQ(Gunzip(Path("stored.gz")).bytes, data);
}

TEST_F(ParallelGzipTest, CancelledBeforeStartIsCancelled) {
  CancellationToken token;
  token.Cancel();
  const absl::Status status =
      Write("c.gz", {Noise(100000, 8)}, {}, {.cancel = &token});
  EXPECT_EQ(status.code(), absl::StatusCode::kCancelled);
}

TEST_F(ParallelGzipTest, BadOptionsAreInvalid) {
  GzipOptions options;
  options.level = 13;
  EXPECT_EQ(Write("x.gz", {"abc"}, options, {}).code(),
            absl::StatusCode::kInvalidArgument);
  options = {};
  options.block_size = 0;
  EXPECT_EQ(Write("x.gz", {"abc"}, options, {}).code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(ParallelGzipTest, WriteFailureIsInternal) {
  // A read-only descriptor: write() fails with EBADF.
  const std::string path = Path("ro");
  { std::ofstream(path) << "x"; }
  const int fd = open(path.c_str(), O_RDONLY);
  ASSERT_GE(fd, 0);
  const std::string data = Noise(1000, 9);
  const absl::Status status = WriteParallelGzip(
      fd, {std::as_bytes(std::span(data.data(), data.size()))}, {}, {});
  close(fd);
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
}

}  // namespace
}  // namespace interslice::volume_io_internal
