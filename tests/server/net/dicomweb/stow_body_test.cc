#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <string>
#include <string_view>
#include <vector>

#include "server/net/dicomweb/multipart.h"

namespace interslice::server::dicomweb {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

// Collects the parts as the parser hands them over.
struct Part {
  PartHeaders headers;
  std::string bytes;
  bool ended = false;
};
class CollectingSink : public MultipartSink {
 public:
  absl::Status BeginPart(const PartHeaders& headers) override {
    parts.push_back({headers, "", false});
    return absl::OkStatus();
  }
  absl::Status PartBytes(std::string_view bytes) override {
    if (parts.empty() || parts.back().ended) {
      return absl::InternalError("bytes outside a part");
    }
    parts.back().bytes.append(bytes);
    return absl::OkStatus();
  }
  absl::Status EndPart() override {
    parts.back().ended = true;
    return absl::OkStatus();
  }
  std::vector<Part> parts;
};

std::vector<std::string> Bodies(const CollectingSink& sink) {
  std::vector<std::string> out;
  for (const Part& p : sink.parts) out.push_back(p.bytes);
  return out;
}

// The limits these tests vary in the STOW-RS configuration of the parser.
struct StowBodyLimits {
  int64_t max_part_header_bytes = 16 * 1024;
  int64_t max_parts = 100000;
};

// The parser as the STOW-RS receiver (stow.cc) configures it.
MultipartParser StowParser(const std::string& boundary, MultipartSink* sink,
                           StowBodyLimits limits = {}) {
  MultipartOptions options = StowRequestMultipart(limits.max_parts);
  options.limits.max_header_bytes = limits.max_part_header_bytes;
  return MultipartParser(boundary, options, sink);
}

// Feeds `body` in pieces of `piece` bytes (0: whole) and finishes.
absl::Status Parse(const std::string& body, CollectingSink& sink,
                   size_t piece = 0, const std::string& boundary = "b0und",
                   StowBodyLimits limits = {}) {
  MultipartParser parser = StowParser(boundary, &sink, limits);
  if (piece == 0) piece = body.size() + 1;
  for (size_t i = 0; i < body.size(); i += piece) {
    if (absl::Status s = parser.Feed(std::string_view(body).substr(i, piece));
        !s.ok()) {
      return s;
    }
  }
  return parser.Finish();
}

// Two parts whose bytes hold line breaks, dashes and a near-boundary.
const std::string kFirst("DICM\r\n--b0un\r\n-- b0und\n\x00\xff", 25);
const std::string kSecond = "\r\n\r\nsecond\rx";

std::string TwoParts(const std::string& nl) {
  return "preamble text" + nl + "--b0und" + nl +
         "Content-Type: application/dicom" + nl + nl + kFirst + nl +
         "--b0und  \t" + nl + "content-type: Application/DICOM; x=1" + nl +
         "Content-Location: a" + nl + nl + kSecond + nl + "--b0und--" + nl +
         "epilogue" + nl;
}

TEST(StowBodyTest, CrlfAndLfBodiesGiveTheSameParts) {
  for (const std::string nl : {"\r\n", "\n"}) {
    CollectingSink sink;
    ASSERT_TRUE(Parse(TwoParts(nl), sink).ok()) << nl.size();
    ASSERT_EQ(sink.parts.size(), 2u);
    EXPECT_THAT(Bodies(sink), ElementsAre(kFirst, kSecond));
    EXPECT_TRUE(sink.parts[0].ended && sink.parts[1].ended);
    EXPECT_EQ(sink.parts[0].headers.at("content-type"), "application/dicom");
    EXPECT_EQ(PartMediaType(sink.parts[1].headers, ""), "application/dicom");
    EXPECT_EQ(sink.parts[1].headers.at("content-location"), "a");
  }
}

// Every split of the body into two reads, and reads of 1..7 bytes, give
// the same parts: a delimiter split anywhere is still found.
TEST(StowBodyTest, DelimiterSplitAcrossReadsAnywhere) {
  const std::string body = TwoParts("\r\n");
  for (size_t piece = 1; piece <= 7; ++piece) {
    CollectingSink sink;
    ASSERT_TRUE(Parse(body, sink, piece).ok()) << piece;
    EXPECT_THAT(Bodies(sink), ElementsAre(kFirst, kSecond)) << piece;
  }
  for (size_t cut = 1; cut < body.size(); ++cut) {
    CollectingSink sink;
    MultipartParser parser = StowParser("b0und", &sink);
    ASSERT_TRUE(parser.Feed(body.substr(0, cut)).ok()) << cut;
    ASSERT_TRUE(parser.Feed(body.substr(cut)).ok()) << cut;
    ASSERT_TRUE(parser.Finish().ok()) << cut;
    EXPECT_THAT(Bodies(sink), ElementsAre(kFirst, kSecond)) << cut;
  }
}

TEST(StowBodyTest, BodyMayStartWithTheDelimiterAndEndWithoutLineBreak) {
  CollectingSink sink;
  ASSERT_TRUE(Parse("--b0und\r\n\r\nxyz\r\n--b0und--", sink).ok());
  EXPECT_THAT(Bodies(sink), ElementsAre("xyz"));
  EXPECT_TRUE(sink.parts[0].headers.empty());
}

TEST(StowBodyTest, MissingCloseDelimiterFails) {
  for (const std::string body :
       {"--b0und\r\n\r\nxyz\r\n--b0und\r\n", "--b0und\r\n\r\nxyz",
        "--b0und\r\n\r\nxyz\r\n--b0und-", "--b0und\r\nContent-Type: a",
        "no delimiter at all", ""}) {
    CollectingSink sink;
    const absl::Status s = Parse(body, sink);
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << body;
  }
  // The part before the missing close was handed over but the body is not
  // whole: the caller must not confirm it.
  CollectingSink sink;
  const absl::Status s = Parse("--b0und\r\n\r\nxyz\r\n--b0und\r\n", sink);
  EXPECT_THAT(s.message(), HasSubstr("close delimiter"));
}

TEST(StowBodyTest, GarbageAfterABoundaryFails) {
  CollectingSink sink;
  const absl::Status s =
      Parse("--b0und\r\n\r\nx\r\n--b0undX\r\n\r\ny\r\n--b0und--", sink);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("followed by other text"));
}

TEST(StowBodyTest, PartHeadersAreBounded) {
  CollectingSink sink;
  const std::string body = "--b0und\r\nX-Long: " + std::string(20000, 'a') +
                           "\r\n\r\nx\r\n--b0und--";
  // Fed in small pieces: the parser must not wait for the end of headers
  // forever while they grow.
  const absl::Status s = Parse(body, sink, 100);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("headers are too long"));
  std::string many = "--b0und\r\n";
  for (int i = 0; i < 65; ++i) many += "X-A: b\r\n";
  many += "\r\nx\r\n--b0und--";
  CollectingSink sink2;
  EXPECT_THAT(Parse(many, sink2).message(), HasSubstr("64 header lines"));
  CollectingSink sink3;
  EXPECT_THAT(
      Parse("--b0und\r\nno colon\r\n\r\nx\r\n--b0und--", sink3).message(),
      HasSubstr("colon"));
  CollectingSink sink4;
  EXPECT_THAT(Parse("--b0und\r\nContent-Transfer-Encoding: base64\r\n\r\nx\r\n"
                    "--b0und--",
                    sink4)
                  .message(),
              HasSubstr("Content-Transfer-Encoding"));
}

TEST(StowBodyTest, PartCountIsBounded) {
  std::string body;
  for (int i = 0; i < 4; ++i) body += "--b0und\r\n\r\nx\r\n";
  body += "--b0und--";
  CollectingSink sink;
  EXPECT_THAT(Parse(body, sink, 0, "b0und", {.max_parts = 3}).message(),
              HasSubstr("more than 3 parts"));
  CollectingSink sink2;
  EXPECT_TRUE(Parse(body, sink2, 0, "b0und", {.max_parts = 4}).ok());
}

// A large part streams through: the parser never holds more than one read
// and a delimiter's worth (the sink sees many small pieces).
TEST(StowBodyTest, LargePartStreamsInPieces) {
  class CountingSink : public MultipartSink {
   public:
    absl::Status BeginPart(const PartHeaders&) override {
      return absl::OkStatus();
    }
    absl::Status PartBytes(std::string_view b) override {
      ++calls;
      largest = std::max(largest, b.size());
      total += b.size();
      return absl::OkStatus();
    }
    absl::Status EndPart() override { return absl::OkStatus(); }
    size_t calls = 0, largest = 0, total = 0;
  } sink;
  MultipartParser parser = StowParser("b0und", &sink);
  ASSERT_TRUE(parser.Feed("--b0und\r\n\r\n").ok());
  const std::string chunk(4096, 'z');
  for (int i = 0; i < 1000; ++i) ASSERT_TRUE(parser.Feed(chunk).ok());
  ASSERT_TRUE(parser.Feed("\r\n--b0und--\r\n").ok());
  ASSERT_TRUE(parser.Finish().ok());
  EXPECT_EQ(sink.total, 4096u * 1000);
  EXPECT_GE(sink.calls, 1000u);
  EXPECT_LE(sink.largest, 4096u + 16);
}

TEST(StowBodyTest, SinkErrorStopsTheParse) {
  class FailingSink : public MultipartSink {
   public:
    absl::Status BeginPart(const PartHeaders&) override {
      return absl::ResourceExhaustedError("no room");
    }
    absl::Status PartBytes(std::string_view) override {
      return absl::OkStatus();
    }
    absl::Status EndPart() override { return absl::OkStatus(); }
  } sink;
  MultipartParser parser = StowParser("b0und", &sink);
  EXPECT_EQ(parser.Feed("--b0und\r\n\r\nx\r\n--b0und--").code(),
            absl::StatusCode::kResourceExhausted);
  EXPECT_FALSE(parser.Finish().ok());
}

TEST(StowBodyTest, ContentType) {
  absl::StatusOr<StowContentType> t = ParseStowContentType(
      "Multipart/Related; x=\"p;q\"; type=\"application/dicom\"; "
      "boundary=\"a b?c\"");
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_EQ(t->boundary, "a b?c");
  EXPECT_EQ(t->type, "application/dicom");
  t = ParseStowContentType("multipart/related; boundary=xyz");
  ASSERT_TRUE(t.ok());
  EXPECT_EQ(t->boundary, "xyz");
  EXPECT_EQ(t->type, "");
  // A single-part body (issue 39, finding 6: it was 415).
  t = ParseStowContentType("Application/DICOM");
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_TRUE(t->single_part);
  // Wrong media types: UNIMPLEMENTED (415).
  for (const char* wrong :
       {"application/json", "multipart/form-data; boundary=x", "",
        "multipart/related; type=\"application/dicom+xml\"; boundary=x"}) {
    EXPECT_EQ(ParseStowContentType(wrong).status().code(),
              absl::StatusCode::kUnimplemented)
        << wrong;
  }
  // Malformed: INVALID_ARGUMENT (400).
  for (const char* bad :
       {"multipart/related", "multipart/related; boundary=",
        "multipart/related; boundary", "multipart/related; boundary=a\x01",
        "multipart/related; boundary=\"ends with space \""}) {
    EXPECT_EQ(ParseStowContentType(bad).status().code(),
              absl::StatusCode::kInvalidArgument)
        << bad;
  }
  // Longer than RFC 2046's 70 as real clients send (Orthanc: 73; issue 39,
  // finding 6) up to the stated limit; past it INVALID_ARGUMENT.
  t = ParseStowContentType("multipart/related; boundary=" +
                           std::string(73, 'a'));
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_EQ(t->boundary.size(), 73u);
  EXPECT_FALSE(t->single_part);
  EXPECT_TRUE(ParseStowContentType("multipart/related; boundary=" +
                                   std::string(kMaxBoundaryChars, 'a'))
                  .ok());
  absl::StatusOr<StowContentType> too_long = ParseStowContentType(
      "multipart/related; boundary=" + std::string(kMaxBoundaryChars + 1, 'a'));
  EXPECT_EQ(too_long.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(too_long.status().message()),
              ::testing::HasSubstr("1-256 characters"));
}

}  // namespace
}  // namespace interslice::server::dicomweb
