// StowReceiver against a real SeriesAssembler (and Spool) in a temporary
// folder: the phantom's instances as STOW-RS bodies, good and bad; a fake
// job submitter records what a complete series would become.
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "nlohmann/json.hpp"
#include "server/engine/spool.h"
#include "server/net/dicomweb/stow.h"
#include "server/node/series_assembler.h"
#include "tests/testing/paths.h"

namespace interslice::server::dicomweb {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";
const char kType[] =
    "multipart/related; type=\"application/dicom\"; boundary=XyZ-boundary";

std::string ReadAll(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

std::string Tag(const fs::path& file, const DcmTagKey& tag) {
  DcmFileFormat ff;
  EXPECT_TRUE(ff.loadFile(file.c_str()).good());
  OFString value;
  ff.getDataset()->findAndGetOFString(tag, value);
  return value.c_str();
}

struct BodyPart {
  std::string content_type = "application/dicom";
  std::string bytes;
};

std::string Body(const std::vector<BodyPart>& parts, bool close = true) {
  std::string body;
  for (const BodyPart& p : parts) {
    absl::StrAppend(&body, "--XyZ-boundary\r\nContent-Type: ", p.content_type,
                    "\r\n\r\n", p.bytes, "\r\n");
  }
  if (close) body += "--XyZ-boundary--\r\n";
  return body;
}

class StowReceiverTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = fs::temp_directory_path() /
            ("interslice-stow-" + std::to_string(::getpid()) + "-" +
             ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(root_);
    for (const auto& e : fs::directory_iterator(kPhantom)) {
      if (e.path().extension() == ".dcm") files_.push_back(e.path());
    }
    std::sort(files_.begin(), files_.end());
    ASSERT_EQ(files_.size(), 28u);
  }
  void TearDown() override {
    assembler_.reset();
    fs::remove_all(root_);
  }

  void Open(int64_t quota = int64_t{1} << 40) {
    absl::StatusOr<std::unique_ptr<Spool>> spool =
        Spool::Open((root_ / "spool").string(), quota);
    ASSERT_TRUE(spool.ok()) << spool.status();
    spool_ = *std::move(spool);
    node::RuleSet rules;
    rules.path = "rules.yaml";
    rules.stable_seconds = 0.05;
    node::Rule rule;
    rule.name = "ct";
    rule.match.modality = "CT";
    rule.job.set_threshold(300);
    rule.complete_on_request = true;  // one job per request
    rules.rules.push_back(rule);
    node::AssemblerOptions options;
    options.root = (root_ / "spool" / "dicom-in").string();
    absl::StatusOr<std::unique_ptr<node::SeriesAssembler>> a =
        node::SeriesAssembler::Open(
            options, rules, spool_.get(), nullptr,
            [this](const v1::JobSpec&, const std::string& dir,
                   const std::string& origin,
                   const std::string&) -> absl::StatusOr<std::string> {
              int n = 0;
              for (const auto& e : fs::directory_iterator(dir)) {
                if (e.path().extension() == ".dcm") ++n;
              }
              jobs_.push_back({origin, n});
              return absl::StrCat("job", jobs_.size());
            });
    ASSERT_TRUE(a.ok()) << a.status();
    assembler_ = *std::move(a);
    receiver_ = std::make_unique<StowReceiver>(StowOptions{}, assembler_.get(),
                                               spool_.get(), nullptr);
  }

  // Sends `body` in reads of `piece` bytes.
  StowResponse Post(const std::string& body, const std::string& study = "",
                    std::string type = kType, bool chunked = false,
                    size_t piece = 1000) {
    size_t at = 0;
    StowRequest request{
        .identity = "alice",
        .source = "127.0.0.1:1",
        .content_type = std::move(type),
        .study_uid = study,
        .content_length = chunked ? -1 : static_cast<int64_t>(body.size()),
        .read = [&](char* buffer, size_t size) -> int64_t {
          const size_t n = std::min({size, piece, body.size() - at});
          std::copy_n(body.data() + at, n, buffer);
          at += n;
          return static_cast<int64_t>(n);
        }};
    return receiver_->Handle(request);
  }

  std::vector<BodyPart> Phantom() const {
    std::vector<BodyPart> parts;
    for (const fs::path& f : files_) parts.push_back({.bytes = ReadAll(f)});
    return parts;
  }

  // Completes what is stable (after its stable wait) and returns the jobs.
  size_t JobsAfterStableWait() {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    assembler_->CompleteStableSeries();
    return jobs_.size();
  }

  fs::path root_;
  std::vector<fs::path> files_;
  std::unique_ptr<Spool> spool_;
  std::unique_ptr<node::SeriesAssembler> assembler_;
  std::unique_ptr<StowReceiver> receiver_;
  struct Job {
    std::string origin;
    int files = 0;
  };
  std::vector<Job> jobs_;
};

TEST_F(StowReceiverTest, WholeSeriesIsStoredAndMakesTheRulesJob) {
  Open();
  const StowResponse r = Post(Body(Phantom()));
  ASSERT_EQ(r.status, 200) << r.body;
  EXPECT_EQ(r.content_type, "application/dicom+json");
  EXPECT_TRUE(r.released);
  EXPECT_EQ(r.stored, 28);
  const nlohmann::json j = nlohmann::json::parse(r.body);
  EXPECT_FALSE(j.contains("00081198"));
  const nlohmann::json& referenced = j["00081199"]["Value"];
  ASSERT_EQ(referenced.size(), 28u);
  EXPECT_EQ(referenced[3]["00081155"]["Value"][0],
            Tag(files_[3], DCM_SOPInstanceUID));
  EXPECT_EQ(referenced[3]["00081150"]["Value"][0],
            Tag(files_[3], DCM_SOPClassUID));
  // complete_on_request: the whole request completes it at once.
  assembler_->CompleteStableSeries();
  ASSERT_EQ(jobs_.size(), 1u);
  EXPECT_EQ(jobs_[0].files, 28);
  EXPECT_THAT(jobs_[0].origin, HasSubstr("STOW:alice->INTERSLICE"));
  // The same, posted to its own study, in 1-byte... 7-byte reads.
  const StowResponse again =
      Post(Body(Phantom()), Tag(files_[0], DCM_StudyInstanceUID), kType,
           /*chunked=*/true, 7);
  EXPECT_EQ(again.status, 200) << again.body;
}

TEST_F(StowReceiverTest, CutOffBodyStoresNothingThatMakesAJob) {
  Open();
  std::string body = Body(Phantom(), /*close=*/false);
  body.resize(body.size() - 1000);  // the last part is cut short too
  const StowResponse r = Post(body);
  EXPECT_EQ(r.status, 400);
  EXPECT_THAT(r.body, HasSubstr("close delimiter"));
  EXPECT_FALSE(r.released);
  EXPECT_EQ(JobsAfterStableWait(), 0u);
  // Staging files are gone: only whole, confirmed parts stay (waiting).
  EXPECT_TRUE(fs::is_empty(root_ / "spool" / "dicom-in" / "incoming"));
  // A later whole request completes the series.
  EXPECT_EQ(Post(Body(Phantom())).status, 200);
  assembler_->CompleteStableSeries();
  ASSERT_EQ(jobs_.size(), 1u);
  EXPECT_EQ(jobs_[0].files, 28);
}

// Issue 39, finding 2: a whole multipart body that is shorter than its
// Content-Length (the client still waiting when the read ended) is not a
// whole request: 400, and its series is incomplete.
TEST_F(StowReceiverTest, BodyShortOfItsContentLengthIsNotWhole) {
  Open();
  const std::string body = Body(Phantom());
  size_t at = 0;
  const StowResponse r = receiver_->Handle(
      {.identity = "alice",
       .content_type = kType,
       .content_length = static_cast<int64_t>(body.size()) + 1,
       .read = [&](char* buffer, size_t size) -> int64_t {
         const size_t n = std::min(size, body.size() - at);
         std::copy_n(body.data() + at, n, buffer);
         at += n;
         return static_cast<int64_t>(n);  // 0 at the end: the read timed out
       }});
  EXPECT_EQ(r.status, 400) << r.body;
  EXPECT_THAT(r.body, HasSubstr("Content-Length promised"));
  EXPECT_FALSE(r.released);
  EXPECT_EQ(r.stored, 28);  // kept, but as an incomplete series
  EXPECT_EQ(JobsAfterStableWait(), 0u);
  // A single-part body (Content-Type application/dicom) of one instance is
  // whole at its end; it makes no job of the incomplete series, since it
  // re-sends, unchanged, one instance the series holds.
  const std::string one = ReadAll(files_[0]);
  at = 0;
  const StowResponse single =
      receiver_->Handle({.identity = "alice",
                         .content_type = "application/dicom",
                         .content_length = static_cast<int64_t>(one.size()),
                         .read = [&](char* buffer, size_t size) -> int64_t {
                           const size_t n = std::min(size, one.size() - at);
                           std::copy_n(one.data() + at, n, buffer);
                           at += n;
                           return static_cast<int64_t>(n);
                         }});
  EXPECT_EQ(single.status, 200) << single.body;
  EXPECT_TRUE(single.released);
  EXPECT_EQ(single.stored, 1);
  EXPECT_EQ(JobsAfterStableWait(), 0u);
}

TEST_F(StowReceiverTest, PartNotDicomIsRefusedAndTheSeriesIsIncomplete) {
  Open();
  std::vector<BodyPart> parts = Phantom();
  parts[5].bytes = "this is not DICOM";
  parts[9].content_type = "application/octet-stream";
  const StowResponse r = Post(Body(parts));
  ASSERT_EQ(r.status, 202) << r.body;
  EXPECT_FALSE(r.released);
  EXPECT_EQ(r.stored, 26);
  const nlohmann::json j = nlohmann::json::parse(r.body);
  const nlohmann::json& failed = j["00081198"]["Value"];
  ASSERT_EQ(failed.size(), 2u);
  for (const nlohmann::json& item : failed) {
    EXPECT_EQ(item["00081197"]["Value"][0], kFailureCannotUnderstand);
  }
  EXPECT_EQ(j["00081199"]["Value"].size(), 26u);
  EXPECT_EQ(JobsAfterStableWait(), 0u);

  // Nothing stored at all: 409.
  const StowResponse none =
      Post(Body({{.bytes = "junk"}, {.content_type = "text/plain"}}));
  EXPECT_EQ(none.status, 409) << none.body;
  EXPECT_EQ(none.stored, 0);
}

TEST_F(StowReceiverTest, InstanceOfAnotherStudyIsRefusedForAStudyPath) {
  Open();
  const StowResponse r = Post(Body(Phantom()), "1.2.3.4");
  ASSERT_EQ(r.status, 409) << r.body;
  const nlohmann::json j = nlohmann::json::parse(r.body);
  ASSERT_EQ(j["00081198"]["Value"].size(), 28u);
  EXPECT_EQ(j["00081198"]["Value"][0]["00081197"]["Value"][0],
            kFailureDoesNotMatch);
  EXPECT_EQ(JobsAfterStableWait(), 0u);
}

TEST_F(StowReceiverTest, WrongTypeAndOversizeBodiesAreRefusedUnread) {
  Open();
  auto unread = [&](std::string type, int64_t length) {
    bool read = false;
    StowRequest request{.identity = "alice",
                        .content_type = std::move(type),
                        .content_length = length,
                        .read = [&](char*, size_t) -> int64_t {
                          read = true;
                          return 0;
                        }};
    const StowResponse r = receiver_->Handle(request);
    EXPECT_FALSE(read);
    return r.status;
  };
  EXPECT_EQ(unread("application/json", 10), 415);
  EXPECT_EQ(unread("multipart/related; type=\"application/dicom+json\"; "
                   "boundary=x",
                   10),
            415);
  EXPECT_EQ(unread("multipart/related; type=\"application/dicom\"", 10), 400);
  EXPECT_EQ(unread(kType, receiver_->max_body_bytes() + 1), 413);
  EXPECT_EQ(JobsAfterStableWait(), 0u);
}

TEST_F(StowReceiverTest, ChunkedBodyOverTheLimitIsCutAt413) {
  Open();
  receiver_ =
      std::make_unique<StowReceiver>(StowOptions{.max_body_bytes = 2 << 20},
                                     assembler_.get(), spool_.get(), nullptr);
  const StowResponse r = Post(Body(Phantom()), "", kType, /*chunked=*/true);
  EXPECT_EQ(r.status, 413) << r.body;
  EXPECT_FALSE(r.released);
  EXPECT_EQ(JobsAfterStableWait(), 0u);
  EXPECT_TRUE(fs::is_empty(root_ / "spool" / "dicom-in" / "incoming"));
}

TEST_F(StowReceiverTest, FullSpoolQuotaAnswers507) {
  Open(/*quota=*/3 << 19);  // 1.5 MiB: 2 instances of the phantom
  // Content-Length above what the quota has left: refused before reading.
  EXPECT_EQ(Post(Body(Phantom())).status, 507);
  // Chunked (no length): the instances that fit are stored, the rest
  // refused out of resources (0xA700).
  const StowResponse r = Post(Body(Phantom()), "", kType, /*chunked=*/true);
  ASSERT_EQ(r.status, 202) << r.body;
  const nlohmann::json j = nlohmann::json::parse(r.body);
  EXPECT_EQ(j["00081198"]["Value"][0]["00081197"]["Value"][0],
            kFailureOutOfResources);
  EXPECT_EQ(JobsAfterStableWait(), 0u);
  // Only refusals by the quota: 507 with the Failed SOP Sequence.
  const StowResponse full =
      Post(Body({Phantom()[20], Phantom()[21]}), "", kType, true);
  EXPECT_EQ(full.status, 507) << full.body;
  EXPECT_THAT(full.body, HasSubstr("00081198"));
}

TEST(StowPathTest, UidSegments) {
  EXPECT_TRUE(IsUidPathSegment("1.2.840.10008.1"));
  EXPECT_FALSE(IsUidPathSegment(""));
  EXPECT_FALSE(IsUidPathSegment(".."));
  EXPECT_FALSE(IsUidPathSegment("1..2"));
  EXPECT_FALSE(IsUidPathSegment("1.2."));
  EXPECT_FALSE(IsUidPathSegment("1.2a"));
  EXPECT_FALSE(IsUidPathSegment(std::string(65, '1')));
}

}  // namespace
}  // namespace interslice::server::dicomweb
