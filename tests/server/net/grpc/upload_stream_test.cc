// Unit tests of UploadStream, the pure validator of upload streams.
#include "server/net/grpc/upload_stream.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "core/common/sha256.h"

namespace interslice::server {
namespace {

std::string Sha(const std::string& data) {
  Sha256 hash;
  hash.Update(data);
  return hash.Finish();
}

v1::UploadRequest Header(int files, int64_t total) {
  v1::UploadRequest r;
  r.mutable_header()->mutable_spec()->set_threshold(300);
  r.mutable_header()->set_file_count(files);
  r.mutable_header()->set_total_bytes(total);
  return r;
}

// The first chunk of file `index` (name, size and SHA-256 of `whole`).
v1::UploadRequest First(int index, const std::string& whole,
                        const std::string& data, std::string name = "a.dcm") {
  v1::UploadRequest r;
  v1::FileChunk* c = r.mutable_chunk();
  c->set_file_index(index);
  c->set_file_name(std::move(name));
  c->set_file_size(static_cast<int64_t>(whole.size()));
  c->set_sha256(Sha(whole));
  c->set_data(data);
  return r;
}

v1::UploadRequest Next(int index, int64_t offset, const std::string& data) {
  v1::UploadRequest r;
  r.mutable_chunk()->set_file_index(index);
  r.mutable_chunk()->set_offset(offset);
  r.mutable_chunk()->set_data(data);
  return r;
}

UploadStreamLimits SmallLimits() {
  UploadStreamLimits limits;
  limits.max_chunk_bytes = 8;
  limits.max_upload_bytes = 100;
  limits.max_files = 3;
  limits.max_file_name_bytes = 16;
  return limits;
}

TEST(UploadStreamTest, AcceptsAWellFormedUploadAndSaysWhatToWrite) {
  UploadStream stream(SmallLimits());
  UploadStep step;
  ASSERT_TRUE(stream.Next(Header(3, 14), &step).ok());
  EXPECT_TRUE(step.header);
  EXPECT_EQ(stream.header().file_count(), 3);

  const std::string a = "0123456789";  // two chunks
  // step.data views the request passed to Next: each request outlives the
  // checks of its step.
  const v1::UploadRequest first = First(0, a, "01234567", "dir/a.dcm");
  ASSERT_TRUE(stream.Next(first, &step).ok());
  EXPECT_FALSE(step.header);
  EXPECT_TRUE(step.open_file);
  EXPECT_EQ(step.file_index, 0);
  EXPECT_EQ(step.offset, 0);
  EXPECT_EQ(step.data, "01234567");
  EXPECT_FALSE(step.close_file);
  const v1::UploadRequest rest = Next(0, 8, "89");
  ASSERT_TRUE(stream.Next(rest, &step).ok());
  EXPECT_FALSE(step.open_file);
  EXPECT_EQ(step.offset, 8);
  EXPECT_EQ(step.data, "89");
  EXPECT_TRUE(step.close_file);

  const v1::UploadRequest empty = First(1, "", "");  // an empty file
  ASSERT_TRUE(stream.Next(empty, &step).ok());
  EXPECT_TRUE(step.open_file);
  EXPECT_TRUE(step.close_file);
  EXPECT_TRUE(step.data.empty());

  EXPECT_FALSE(stream.Finish().ok());  // one file missing
}

TEST(UploadStreamTest, FinishNeedsEveryFileAndByte) {
  UploadStream stream(SmallLimits());
  UploadStep step;
  ASSERT_TRUE(stream.Next(Header(1, 4), &step).ok());
  ASSERT_TRUE(stream.Next(First(0, "abcd", "ab"), &step).ok());
  absl::Status s = stream.Finish();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("incomplete upload: 0 of 1 file(s), 2 of 4"),
            std::string::npos)
      << s;

  UploadStream whole(SmallLimits());
  ASSERT_TRUE(whole.Next(Header(1, 4), &step).ok());
  ASSERT_TRUE(whole.Next(First(0, "abcd", "abcd"), &step).ok());
  EXPECT_TRUE(whole.Finish().ok());
  EXPECT_EQ(whole.bytes_received(), 4);

  UploadStream nothing(SmallLimits());
  EXPECT_FALSE(nothing.Finish().ok());
}

// Each case: the messages after a valid header, and a piece of the error.
struct BadCase {
  const char* name;
  std::vector<v1::UploadRequest> messages;
  const char* error;
};

TEST(UploadStreamTest, RefusesEveryMalformedStream) {
  auto with = [](v1::UploadRequest r, auto change) {
    change(r.mutable_chunk());
    return r;
  };
  const std::string f = "abcdef";
  const std::vector<BadCase> cases = {
      {"header twice", {Header(1, 6)}, "only once"},
      {"empty message", {v1::UploadRequest()}, "header or a chunk"},
      {"chunk too large", {First(0, "0123456789", "012345678")}, "limit of 8"},
      {"file 1 first", {First(1, f, f)}, "expected file index 0, got 1"},
      {"negative index", {Next(-1, 0, "")}, "expected file index 0, got -1"},
      {"index beyond count",
       {First(0, f, f), First(1, f, f), First(2, "", "")},
       "beyond header.file_count (2)"},
      {"no sha",
       {with(First(0, f, f), [](auto* c) { c->clear_sha256(); })},
       "32-byte sha256"},
      {"negative size",
       {with(First(0, f, f), [](auto* c) { c->set_file_size(-1); })},
       "file_size >= 0"},
      {"sizes above total",
       {with(First(0, f, f), [](auto* c) { c->set_file_size(13); })},
       "larger than header.total_bytes"},
      {"huge size",
       {with(First(0, f, f), [](auto* c) { c->set_file_size(INT64_MAX); })},
       "larger than header.total_bytes"},
      {"gap", {First(0, f, "abc"), Next(0, 4, "ef")}, "expected offset 3"},
      {"overlap", {First(0, f, "abc"), Next(0, 2, "cd")}, "expected offset 3"},
      {"too much data",
       {First(0, f, "abc"), Next(0, 3, "defg")},
       "more data than its file_size"},
      {"file cut short",
       {First(0, f, "abc"), First(1, f, f)},
       "file 0 ended after 3 of 6 bytes"},
      {"sha mismatch",
       {with(First(0, f, f), [](auto* c) { c->set_data("abcdeX"); })},
       "SHA-256 mismatch"},
      {"size changed later",
       {First(0, f, "abc"),
        with(Next(0, 3, "def"), [](auto* c) { c->set_file_size(7); })},
       "changes its name, size or sha256"},
      {"name changed later",
       {First(0, f, "abc"),
        with(Next(0, 3, "def"), [](auto* c) { c->set_file_name("b.dcm"); })},
       "changes its name"},
      {"absolute name", {First(0, f, f, "/etc/passwd")}, "must be relative"},
      {"dot-dot name", {First(0, f, f, "a/../../b")}, "'..'"},
      {"newline in name", {First(0, f, f, "a\nFORGED")}, "control characters"},
      {"invalid utf-8 name", {First(0, f, f, "a\xff")}, "invalid UTF-8"},
      {"long name", {First(0, f, f, std::string(17, 'n'))}, "too long"},
  };
  for (const BadCase& c : cases) {
    SCOPED_TRACE(c.name);
    UploadStream stream(SmallLimits());
    UploadStep step;
    ASSERT_TRUE(stream.Next(Header(2, 12), &step).ok());
    absl::Status s;
    for (const v1::UploadRequest& m : c.messages) {
      s = stream.Next(m, &step);
      if (!s.ok()) break;
    }
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << s;
    EXPECT_NE(s.message().find(c.error), std::string::npos) << s;
    // No file name or content in the message.
    EXPECT_EQ(s.message().find("FORGED"), std::string::npos);
    EXPECT_EQ(s.message().find("passwd"), std::string::npos);
    // Errors are final.
    EXPECT_EQ(stream.Next(First(0, f, f), &step), s);
    EXPECT_EQ(stream.Finish(), s);
  }
}

TEST(UploadStreamTest, ChecksTheHeader) {
  UploadStep step;
  {
    UploadStream stream(SmallLimits());
    EXPECT_EQ(stream.Next(First(0, "a", "a"), &step).code(),
              absl::StatusCode::kInvalidArgument);
  }
  for (const auto& [files, total] :
       std::vector<std::pair<int, int64_t>>{{0, 1}, {4, 1}, {1, -1}}) {
    UploadStream stream(SmallLimits());
    EXPECT_EQ(stream.Next(Header(files, total), &step).code(),
              absl::StatusCode::kInvalidArgument)
        << files << " " << total;
  }
  UploadStream big(SmallLimits());
  absl::Status s = big.Next(Header(1, 101), &step);
  EXPECT_EQ(s.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(s.message().find("exceeds the server's limit of 100 bytes"),
            std::string::npos);
}

TEST(UploadStreamTest, LaterChunksMayRepeatTheMetadata) {
  UploadStream stream(SmallLimits());
  UploadStep step;
  ASSERT_TRUE(stream.Next(Header(1, 10), &step).ok());
  const std::string a = "0123456789";
  ASSERT_TRUE(stream.Next(First(0, a, "01234567"), &step).ok());
  v1::UploadRequest again = First(0, a, "89");
  again.mutable_chunk()->set_offset(8);
  ASSERT_TRUE(stream.Next(again, &step).ok());
  EXPECT_TRUE(step.close_file);
  // An empty chunk after the end of a file is harmless and writes nothing.
  const v1::UploadRequest after_end = Next(0, 10, "");
  ASSERT_TRUE(stream.Next(after_end, &step).ok());
  EXPECT_TRUE(step.data.empty());
  EXPECT_FALSE(step.open_file || step.close_file);
  EXPECT_TRUE(stream.Finish().ok());
}

}  // namespace
}  // namespace interslice::server
