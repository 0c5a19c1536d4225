// Unit tests of the server library's pure parts.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "server/auth.h"
#include "server/hashing.h"
#include "server/log_safe.h"
#include "server/spec_mapping.h"
#include "server/status_map.h"
#include "server/upload_guard.h"

namespace interslice::server {
namespace {

TEST(RedactPhiTest, ReplacesUidsButKeepsNumbers) {
  EXPECT_EQ(RedactPhi("several series: 1.2.840.113619.2.55.3 (CT, 4 images)."),
            "several series: <uid> (CT, 4 images).");
  EXPECT_EQ(RedactPhi("file 3 of 12 bytes, spacing 0.45 mm, v1.2.3"),
            "file 3 of 12 bytes, spacing 0.45 mm, v1.2.3");
}

TEST(LogSafeTest, EscapesControlCharactersAndInvalidUtf8) {
  EXPECT_EQ(LogSafe("plain text, 1.5 mm"), "plain text, 1.5 mm");
  EXPECT_EQ(LogSafe("a\nFORGED b\r\tc"), "a\\nFORGED b\\r\\tc");
  EXPECT_EQ(LogSafe(std::string("x\0y\x1b[31m\x7f", 9)),
            "x\\x00y\\x1b[31m\\x7f");
  // Valid UTF-8 stays; stray, overlong, surrogate and truncated bytes not.
  EXPECT_EQ(LogSafe("Gr\xc3\xb6\xc3\x9f\xe2\x82\xac \xf0\x9f\x98\x80"),
            "Gr\xc3\xb6\xc3\x9f\xe2\x82\xac \xf0\x9f\x98\x80");
  EXPECT_EQ(LogSafe("\xff\xc0\xaf\xed\xa0\x80\xe2\x82"),
            "\\xff\\xc0\\xaf\\xed\\xa0\\x80\\xe2\\x82");
  // Idempotent, so that layers may each apply it.
  const std::string once = LogSafe("a\n\\n\xff");
  EXPECT_EQ(LogSafe(once), once);
  EXPECT_TRUE(IsLogSafe(once));
  EXPECT_FALSE(IsLogSafe("a\nb"));
  EXPECT_FALSE(IsLogSafe("\xc3"));
  EXPECT_TRUE(IsLogSafe("\xc3\xb6"));
}

TEST(RedactPhiTest, OutputIsOneLine) {
  EXPECT_EQ(RedactPhi("volume \"\nFORGED 1.2.840.10008.1\" is not in"),
            "volume \"\\nFORGED <uid>\" is not in");
}

TEST(StatusMapTest, CodesMapOneToOne) {
  EXPECT_EQ(ToGrpcStatus(absl::ResourceExhaustedError("x")).error_code(),
            grpc::RESOURCE_EXHAUSTED);
  EXPECT_EQ(ToGrpcStatus(absl::DeadlineExceededError("x")).error_code(),
            grpc::DEADLINE_EXCEEDED);
  EXPECT_TRUE(ToGrpcStatus(absl::OkStatus()).ok());
}

// Issue 22: a job whose output hit a full spool failed INTERNAL with the
// server's spool path in the client's message.
TEST(StatusMapTest, FullDiskIsResourceExhaustedWithoutPaths) {
  const absl::Status write = absl::InternalError(
      "cannot write /var/tmp/spool/jobs/j1/out/volume.nii.gz: No space left "
      "on device");
  const absl::Status mapped = DiskFullAsResourceExhausted(write, false);
  EXPECT_EQ(mapped.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(std::string(mapped.message()),
              ::testing::StartsWith("disk full"));
  EXPECT_THAT(std::string(mapped.message()),
              ::testing::Not(::testing::HasSubstr("/var/tmp")));
  // A write error the writer did not explain, on a spool with no room.
  EXPECT_EQ(DiskFullAsResourceExhausted(
                absl::InternalError("Could not write file"), true)
                .code(),
            absl::StatusCode::kResourceExhausted);
  // Otherwise nothing changes.
  EXPECT_EQ(DiskFullAsResourceExhausted(
                absl::InternalError("Could not write file"), false),
            absl::InternalError("Could not write file"));
  EXPECT_EQ(
      DiskFullAsResourceExhausted(absl::InvalidArgumentError("bad"), true),
      absl::InvalidArgumentError("bad"));
  EXPECT_EQ(DiskFullAsResourceExhausted(absl::CancelledError("stop"), true),
            absl::CancelledError("stop"));
}

TEST(SpecMappingTest, DefaultsMatchTheCli) {
  v1::JobSpec p;
  EXPECT_FALSE(JobSpecFromProto(p).ok());  // threshold is required
  p.set_threshold(300);
  absl::StatusOr<JobSpec> spec = JobSpecFromProto(p);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->solver.method, SolverMethod::kConjugateGradient);
  EXPECT_EQ(spec->solver.max_iterations, 15);
  EXPECT_EQ(spec->volume_formats, std::vector<std::string>{"nii"});
  EXPECT_EQ(spec->mesh_formats, std::vector<std::string>{"stl"});
  p.set_tolerance(1e-3);
  EXPECT_EQ(JobSpecFromProto(p)->solver.max_iterations, 100000);
  p.mutable_outputs();  // present and empty: no files
  EXPECT_TRUE(JobSpecFromProto(p)->mesh_formats.empty());
  p.set_strict_spacing(true);
  p.set_uid_root("1.2.3");
  p.mutable_segmentation()->set_enabled(true);
  p.set_multiframe_volume("stack 1");
  auto mapped = JobSpecFromProto(p);
  ASSERT_TRUE(mapped.ok()) << mapped.status();
  EXPECT_TRUE(mapped->strict_spacing);
  EXPECT_TRUE(mapped->write_seg);
  EXPECT_EQ(mapped->uid_root, "1.2.3");
  EXPECT_EQ(mapped->multiframe_volume, "stack 1");
  p.set_method(v1::SOLVER_METHOD_MORPH);
  EXPECT_EQ(JobSpecFromProto(p)->solver.method, SolverMethod::kMorph);
  p.mutable_derived_series()->add_contents("mask");
  EXPECT_EQ(JobSpecFromProto(p)->output_series,
            std::vector<std::string>{"mask"});
  p.mutable_derived_series()->add_contents("bogus");
  EXPECT_EQ(JobSpecFromProto(p).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(SpecMappingTest, UncompressedNiftiAndRleIntensityMap) {
  v1::JobSpec p;
  p.set_threshold(300);
  p.mutable_outputs()->add_volume_formats(v1::VOLUME_FORMAT_NIFTI_UNCOMPRESSED);
  p.mutable_outputs()->add_volume_formats(v1::VOLUME_FORMAT_NIFTI);
  absl::StatusOr<JobSpec> spec = JobSpecFromProto(p);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->volume_formats,
            (std::vector<std::string>{"nii-uncompressed", "nii"}));
  EXPECT_EQ(spec->dicom_compression, "none");
  p.mutable_derived_series()->set_pixel_compression(
      v1::DICOM_PIXEL_COMPRESSION_RLE_LOSSLESS);
  EXPECT_EQ(JobSpecFromProto(p)->dicom_compression, "rle");
  p.mutable_derived_series()->set_pixel_compression(
      v1::DICOM_PIXEL_COMPRESSION_NONE);
  EXPECT_EQ(JobSpecFromProto(p)->dicom_compression, "none");
  p.mutable_derived_series()->set_pixel_compression(
      static_cast<v1::DicomPixelCompression>(99));
  EXPECT_EQ(JobSpecFromProto(p).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(MediaTypeForArtifact("distance.nii"), "application/octet-stream");
}

TEST(TokenFileTest, OneTokenAloneIsTheDefaultIdentity) {
  auto tokens = ParseTokenFile("  s3cret-token\n");
  ASSERT_TRUE(tokens.ok()) << tokens.status();
  ASSERT_EQ(tokens->size(), 1u);
  EXPECT_EQ((*tokens)[0].name, "default");
  EXPECT_EQ((*tokens)[0].token, "s3cret-token");
}

TEST(TokenFileTest, NamedTokens) {
  auto tokens =
      ParseTokenFile("# who:token\nalice: tok-a\n\nbob:tok:b\nops@site:c\n");
  ASSERT_TRUE(tokens.ok()) << tokens.status();
  ASSERT_EQ(tokens->size(), 3u);
  EXPECT_EQ((*tokens)[0].name, "alice");
  EXPECT_EQ((*tokens)[0].token, "tok-a");
  EXPECT_EQ((*tokens)[1].token, "tok:b");  // split at the first ':'
  EXPECT_EQ((*tokens)[2].name, "ops@site");
  for (const char* bad :
       {"", "# only a comment\n", "alice:a\nbob\n", "alice:a\nalice:b\n",
        "alice:a\nbob:a\n", "al ice:a\n", ":a\n", "alice:\n", "alice:a b\n",
        "two words\n"}) {
    auto parsed = ParseTokenFile(bad);
    EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument)
        << bad;
    // A refusal never quotes a token.
    if (!parsed.ok()) {
      EXPECT_EQ(parsed.status().message().find("a b"), std::string::npos);
    }
  }
}

TEST(AuthenticatorTest, MatchesBearerTokensByName) {
  Authenticator auth({{"alice", "tok-a"}, {"bob", "tok-b"}}, {"bob"});
  EXPECT_EQ(auth.MatchBearer("Bearer tok-a"), "alice");
  EXPECT_EQ(auth.MatchBearer("Bearer tok-b"), "bob");
  EXPECT_EQ(auth.MatchBearer("Bearer tok-"), std::nullopt);
  EXPECT_EQ(auth.MatchBearer("Bearer tok-ab"), std::nullopt);
  EXPECT_EQ(auth.MatchBearer("tok-a"), std::nullopt);
  EXPECT_EQ(auth.MatchBearer(""), std::nullopt);
  EXPECT_TRUE(Authenticator::MayAccess({"alice", false}, "alice"));
  EXPECT_FALSE(Authenticator::MayAccess({"bob", false}, "alice"));
  EXPECT_TRUE(Authenticator::MayAccess({"bob", true}, "alice"));
  EXPECT_TRUE(Authenticator::MayAccess({"", false}, ""));
  // Without authentication the one anonymous user also sees the jobs the
  // DICOM listener made (regression: they were invisible to every client).
  EXPECT_TRUE(Authenticator::MayAccess({"", false}, "dicom"));
  EXPECT_FALSE(Authenticator::MayAccess({"alice", false}, "dicom"));
}

TEST(PeerAddressTest, DropsThePort) {
  EXPECT_EQ(PeerAddress("ipv4:10.1.2.3:5000"), "10.1.2.3");
  EXPECT_EQ(PeerAddress("ipv6:[::1]:5000"), "::1");
  EXPECT_EQ(PeerAddress("ipv6:%5B::1%5D:5000"), "::1");
  EXPECT_EQ(PeerAddress("unix:/tmp/socket"), "unix:/tmp/socket");
}

TEST(UploadGuardTest, LimitsUploadsInAllAndPerPeer) {
  UploadGuardOptions options;
  options.max_concurrent = 3;
  options.max_per_peer = 2;
  options.idle_timeout_seconds = 0;
  UploadGuard guard(options);
  auto a1 = guard.Begin("a", nullptr);
  auto a2 = guard.Begin("a", nullptr);
  ASSERT_TRUE(a1.ok() && a2.ok());
  auto a3 = guard.Begin("a", nullptr);
  EXPECT_EQ(a3.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(a3.status().message().find("--max-uploads-per-peer"),
            std::string::npos);
  auto b1 = guard.Begin("b", nullptr);
  ASSERT_TRUE(b1.ok());
  auto c1 = guard.Begin("c", nullptr);
  EXPECT_EQ(c1.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(c1.status().message().find("--max-concurrent-uploads"),
            std::string::npos);
  EXPECT_EQ(guard.active(), 3);
  (*a1)->Release();
  (*a1)->Release();  // idempotent
  EXPECT_EQ(guard.active(), 2);
  EXPECT_TRUE(guard.Begin("a", nullptr).ok());  // released with the ticket
  EXPECT_EQ(guard.active(), 2);
  b1->reset();  // a ticket dropped without Release frees its slot too
  EXPECT_EQ(guard.active(), 1);
}

TEST(UploadGuardTest, ReportsStallsUntilClosed) {
  UploadGuardOptions options;
  options.idle_timeout_seconds = 0.3;
  UploadGuard guard(options);
  std::atomic<int> stalls{0};
  absl::Status last;
  std::mutex mu;
  auto ticket = guard.Begin("a", [&](const absl::Status& s, bool idle) {
    std::lock_guard<std::mutex> lock(mu);
    EXPECT_TRUE(idle);
    last = s;
    ++stalls;
  });
  ASSERT_TRUE(ticket.ok());
  // Progress keeps it alive.
  for (int i = 0; i < 8; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    (*ticket)->Progress();
  }
  EXPECT_EQ(stalls, 0);
  for (int i = 0; i < 50 && stalls == 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_GE(stalls, 1);
  {
    std::lock_guard<std::mutex> lock(mu);
    EXPECT_EQ(last.code(), absl::StatusCode::kDeadlineExceeded);
    EXPECT_EQ(last.message(),
              "upload stalled: no data for 0.3 s; the server cancelled it");
  }
  (*ticket)->Close();
  const int seen = stalls;
  std::this_thread::sleep_for(std::chrono::milliseconds(800));
  EXPECT_EQ(stalls, seen);
}

TEST(UploadGuardTest, ReportsTheTotalLimitOnce) {
  UploadGuardOptions options;
  options.idle_timeout_seconds = 0;
  options.total_timeout_seconds = 0.2;
  UploadGuard guard(options);
  std::atomic<int> calls{0};
  auto ticket = guard.Begin("a", [&](const absl::Status& s, bool idle) {
    EXPECT_FALSE(idle);
    EXPECT_EQ(s.code(), absl::StatusCode::kDeadlineExceeded);
    ++calls;
  });
  ASSERT_TRUE(ticket.ok());
  for (int i = 0; i < 8; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    (*ticket)->Progress();  // data arrives, yet the total limit applies
  }
  EXPECT_EQ(calls, 1);
  (*ticket)->Close();
}

// Artifacts are hashed on several threads: each digest must land in its own
// file's slot whatever the order of completion, and an unreadable file gives
// an error in its slot only.
TEST(Sha256OfFilesTest, EachDigestInItsSlotOnAnyThreadCount) {
  const std::filesystem::path dir =
      std::filesystem::path(::testing::TempDir()) / "sha256-of-files";
  std::filesystem::create_directories(dir);
  std::vector<std::string> paths;
  for (int n = 0; n < 7; ++n) {
    paths.push_back((dir / ("f" + std::to_string(n))).string());
    // Sizes in no particular order, so largest-first changes the order.
    std::ofstream(paths.back(), std::ios::binary)
        << std::string(static_cast<size_t>((n * 37 % 7) * 100000 + n),
                       static_cast<char>('a' + n));
  }
  paths.insert(paths.begin() + 3, (dir / "missing").string());
  for (int threads : {0, 1, 2, 5, 16}) {
    const auto shas = Sha256OfFiles(paths, threads);
    ASSERT_EQ(shas.size(), paths.size());
    for (size_t n = 0; n < paths.size(); ++n) {
      const auto one = Sha256OfFile(paths[n]);
      ASSERT_EQ(shas[n].ok(), one.ok()) << paths[n];
      if (one.ok()) {
        EXPECT_EQ(*shas[n], *one) << paths[n] << " threads " << threads;
      }
    }
    EXPECT_FALSE(shas[3].ok());
  }
  // The digest itself, for a known input ("abc", FIPS 180-2 appendix B.1).
  const std::string abc = (dir / "abc").string();
  std::ofstream(abc, std::ios::binary) << "abc";
  EXPECT_EQ(HexString(*Sha256OfFiles({abc}, 2)[0]),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace interslice::server
