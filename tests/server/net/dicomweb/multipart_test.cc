// The streaming multipart/related parser (server/net/dicomweb/multipart.h): the
// parts of well-formed bodies however they are chunked, and every kind of
// lie or cut a hostile or broken peer can send, each a clean error.
#include "server/net/dicomweb/multipart.h"

#include <functional>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice::server::dicomweb {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

struct Parsed {
  absl::Status status;
  std::vector<std::map<std::string, std::string>> headers;
  std::vector<std::string> data;
  int ended = 0;
};

// The parser's sink as three callbacks (any may be empty).
struct MultipartCallbacks : MultipartSink {
  std::function<absl::Status(const PartHeaders&)> on_part_begin;
  std::function<absl::Status(std::string_view)> on_part_data;
  std::function<absl::Status()> on_part_end;
  absl::Status BeginPart(const PartHeaders& h) override {
    return on_part_begin ? on_part_begin(h) : absl::OkStatus();
  }
  absl::Status PartBytes(std::string_view d) override {
    return on_part_data ? on_part_data(d) : absl::OkStatus();
  }
  absl::Status EndPart() override {
    return on_part_end ? on_part_end() : absl::OkStatus();
  }
};

// The parser as the WADO-RS client (pull.cc) configures it.
MultipartParser WadoParser(MultipartLimits limits, MultipartSink* sink) {
  return MultipartParser("frontier", WadoResponseMultipart(limits), sink);
}

Parsed Parse(const std::string& body, size_t chunk,
             MultipartLimits limits = {}) {
  Parsed out;
  MultipartCallbacks callbacks;
  callbacks.on_part_begin = [&](const auto& headers) {
    out.headers.push_back(headers);
    out.data.emplace_back();
    return absl::OkStatus();
  };
  callbacks.on_part_data = [&](std::string_view d) {
    out.data.back().append(d.data(), d.size());
    return absl::OkStatus();
  };
  callbacks.on_part_end = [&] {
    ++out.ended;
    return absl::OkStatus();
  };
  MultipartParser parser = WadoParser(limits, &callbacks);
  for (size_t at = 0; at < body.size() && out.status.ok(); at += chunk) {
    out.status = parser.Feed(std::string_view(body).substr(at, chunk));
  }
  if (out.status.ok()) out.status = parser.Finish();
  return out;
}

std::string Part(
    const std::string& data,
    const std::string& headers = "Content-Type: application/dicom\r\n") {
  return absl::StrCat("--frontier\r\n", headers, "\r\n", data, "\r\n");
}

const std::string kEnd = "--frontier--\r\n";

TEST(MultipartTest, PartsWhateverTheChunking) {
  // Data that looks like a delimiter but is not one, CR LF inside parts, a
  // preamble, transport padding and an epilogue.
  const std::string first = "DICM\r\n--frontie\r\n-frontier\r\n\r\nbytes";
  const std::string second(70000, 'x');
  const std::string body =
      absl::StrCat("This is the preamble.\r\n", Part(first),
                   "--frontier \t\r\nContent-Length: 70000\r\n\r\n", second,
                   "\r\n", Part("", ""), kEnd, "epilogue --frontier\r\n");
  for (size_t chunk : {1u, 2u, 3u, 7u, 13u, 64u, 4096u, 1000000u}) {
    const Parsed p = Parse(body, chunk);
    ASSERT_TRUE(p.status.ok()) << chunk << ": " << p.status;
    ASSERT_EQ(p.data.size(), 3u) << chunk;
    EXPECT_EQ(p.data[0], first) << chunk;
    EXPECT_TRUE(p.data[1] == second) << chunk;
    EXPECT_EQ(p.data[2], "") << chunk;
    EXPECT_EQ(p.ended, 3);
    EXPECT_EQ(p.headers[0].at("content-type"), "application/dicom");
    EXPECT_EQ(p.headers[1].at("content-length"), "70000");
    EXPECT_TRUE(p.headers[2].empty());
  }
  // The first delimiter may open the body.
  EXPECT_TRUE(Parse(Part("a") + kEnd, 5).status.ok());
}

TEST(MultipartTest, TruncatedBodyIsAnError) {
  const std::string body = Part("first") + "--frontier\r\n\r\nsecond, cut";
  for (size_t chunk : {1u, 5u, 1000u}) {
    const Parsed p = Parse(body, chunk);
    EXPECT_EQ(p.status.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(p.status.message(), HasSubstr("truncated"));
    EXPECT_EQ(p.ended, 1);  // the second part never ends
  }
  EXPECT_THAT(Parse("no boundary at all", 4).status.message(),
              HasSubstr("no multipart boundary"));
  EXPECT_EQ(Parse("", 4).status.code(), absl::StatusCode::kInvalidArgument);
}

TEST(MultipartTest, PartsThatLieAboutTheirSize) {
  // Longer than announced: found while the data arrives, not after.
  Parsed p = Parse(Part("0123456789", "Content-Length: 4\r\n") + kEnd, 1);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(p.status.message(), HasSubstr("longer than its Content-Length"));
  EXPECT_LE(p.data[0].size(), 4u);
  // Shorter than announced.
  p = Parse(Part("0123", "Content-Length: 10\r\n") + kEnd, 3);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(p.status.message(), HasSubstr("Content-Length says 10"));
  // Announcing more than the limit fails before any data is taken.
  MultipartLimits limits;
  limits.max_part_bytes = 100;
  p = Parse(Part("small", "Content-Length: 99999999999\r\n") + kEnd, 1000,
            limits);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_TRUE(p.data.empty());
  p = Parse(Part("x", "Content-Length: -1\r\n") + kEnd, 1000);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kInvalidArgument);
}

TEST(MultipartTest, LimitsHold) {
  MultipartLimits limits;
  limits.max_part_bytes = 10;
  Parsed p = Parse(Part(std::string(11, 'x')) + kEnd, 1, limits);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_LE(p.data[0].size(), 10u);

  limits = {};
  limits.max_parts = 2;
  p = Parse(Part("a") + Part("b") + Part("c") + kEnd, 1000, limits);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(p.status.message(), HasSubstr("more than 2 parts"));
  EXPECT_EQ(p.data.size(), 2u);

  limits = {};
  limits.max_total_bytes = 100;
  p = Parse(Part(std::string(200, 'x')) + kEnd, 7, limits);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_LE(p.data[0].size(), 100u);

  limits = {};
  limits.max_header_bytes = 32;
  p = Parse(Part("a", "X-Long: " + std::string(100, 'h') + "\r\n") + kEnd, 1,
            limits);
  EXPECT_EQ(p.status.code(), absl::StatusCode::kResourceExhausted);
  // Headers of exactly the limit pass, chunked or not.
  const std::string header = "X: " + std::string(27, 'h') + "\r\n";  // 32
  ASSERT_EQ(header.size(), 32u);
  for (size_t chunk : {1u, 31u, 33u, 1000u}) {
    EXPECT_TRUE(Parse(Part("a", header) + kEnd, chunk, limits).status.ok())
        << chunk;
  }
}

TEST(MultipartTest, MalformedFraming) {
  EXPECT_THAT(Parse("--frontierX\r\n\r\na\r\n" + kEnd, 1000).status.message(),
              HasSubstr("followed by other text"));
  EXPECT_THAT(Parse("--frontier\r\nno colon here\r\n\r\na\r\n" + kEnd, 1000)
                  .status.message(),
              HasSubstr("has no colon"));
  // An error stays: the parser refuses more input after it.
  MultipartCallbacks none;
  MultipartParser parser = WadoParser({}, &none);
  EXPECT_FALSE(parser.Feed("--frontierX\r\n").ok());
  EXPECT_FALSE(parser.Feed(Part("a") + kEnd).ok());
  EXPECT_FALSE(parser.Finish().ok());
}

TEST(MultipartTest, CallbackErrorsStopTheParser) {
  MultipartCallbacks callbacks;
  int parts = 0;
  callbacks.on_part_begin = [&](const auto&) {
    return ++parts > 1 ? absl::FailedPreconditionError("enough")
                       : absl::OkStatus();
  };
  MultipartParser parser = WadoParser({}, &callbacks);
  const absl::Status s = parser.Feed(Part("a") + Part("b") + kEnd);
  EXPECT_EQ(s.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(parts, 2);
}

TEST(MultipartTest, ContentTypeParameters) {
  absl::StatusOr<std::string> b = MultipartBoundary(
      "multipart/related; type=\"application/dicom\"; boundary=abc123");
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(*b, "abc123");
  b = MultipartBoundary(
      "Multipart/Related;boundary=\"a;b c\";type=application/dicom");
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(*b, "a;b c");
  EXPECT_EQ(MultipartRootType("multipart/related; type=\"application/dicom\""),
            "application/dicom");
  EXPECT_FALSE(MultipartBoundary("text/html; charset=utf-8").ok());
  EXPECT_FALSE(MultipartBoundary("multipart/related; type=x").ok());
  // Longer than RFC 2046's 70, as real clients send, up to the stated limit.
  EXPECT_TRUE(
      MultipartBoundary("multipart/related; boundary=" + std::string(73, 'b'))
          .ok());
  EXPECT_FALSE(MultipartBoundary("multipart/related; boundary=" +
                                 std::string(kMaxBoundaryChars + 1, 'b'))
                   .ok());
}

}  // namespace
}  // namespace interslice::server::dicomweb
