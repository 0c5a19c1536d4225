// SeriesAssembler in-process: a fake job submitter records what a complete
// series would become.
#include "server/node/series_assembler.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <set>

#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/server/net/dimse/raw_pdu.h"
#include "tests/testing/fake_clock.h"
#include "tests/testing/paths.h"

namespace interslice::server::node {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";

struct Submitted {
  std::string origin;
  int files = 0;
  v1::JobSpec spec;
};

class AssemblerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = fs::temp_directory_path() /
            ("interslice-assembler-" + std::to_string(::getpid()) + "-" +
             ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(root_);
    for (const auto& e : fs::directory_iterator(kPhantom)) {
      if (e.path().extension() == ".dcm") files_.push_back(e.path());
    }
    std::sort(files_.begin(), files_.end());
  }
  void TearDown() override { fs::remove_all(root_); }

  // The sleeps of 100 ms in these tests let a series' stable time (0.05 s
  // with Rules(..., 0.05)) pass on the clock before the test itself calls
  // CompleteStableSeries: nothing runs concurrently, so they are not
  // synchronisation, and sleep_for never returns early.
  RuleSet Rules(const std::string& modality, double stable_seconds,
                bool complete_on_release = false) {
    RuleSet set;
    set.path = "test-rules.yaml";
    set.stable_seconds = stable_seconds;
    Rule rule;
    rule.name = "r1";
    rule.match.modality = modality;
    rule.job.set_threshold(300);
    rule.complete_on_release = complete_on_release;
    set.rules.push_back(rule);
    return set;
  }

  std::unique_ptr<SeriesAssembler> Open(RuleSet rules,
                                        AssemblerOptions options = {}) {
    options.root = root_.string();
    absl::StatusOr<std::unique_ptr<SeriesAssembler>> a = SeriesAssembler::Open(
        options, std::move(rules), nullptr, nullptr,
        [this](const v1::JobSpec& spec, const std::string& dir,
               const std::string& origin,
               const std::string&) -> absl::StatusOr<std::string> {
          if (fail_next_) {
            fail_next_ = false;
            return absl::ResourceExhaustedError("queue full");
          }
          Submitted s{origin, 0, spec};
          for (const auto& e : fs::directory_iterator(dir)) {
            if (e.path().extension() == ".dcm") ++s.files;
          }
          submitted_.push_back(s);
          return std::string("job") + std::to_string(submitted_.size());
        });
    EXPECT_TRUE(a.ok()) << a.status();
    return a.ok() ? *std::move(a) : nullptr;
  }

  // Stages a copy of `file` and adds it within `association`.
  absl::StatusOr<std::string> AddFile(SeriesAssembler& a, uint64_t association,
                                      const std::string& file) {
    const std::string staged = a.StagingPath();
    fs::copy_file(file, staged);
    absl::StatusOr<std::string> key = a.AddInstance(association, staged, -1);
    EXPECT_FALSE(fs::exists(staged));  // taken or deleted, never left behind
    return key;
  }
  absl::StatusOr<std::string> Add(SeriesAssembler& a, uint64_t association,
                                  size_t i) {
    return AddFile(a, association, files_[i].string());
  }
  // Phantom files [first, last) in one association released normally.
  std::string Send(SeriesAssembler& a, size_t first, size_t last) {
    const uint64_t id =
        a.BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
    std::string key;
    for (size_t i = first; i < last; ++i) {
      absl::StatusOr<std::string> k = Add(a, id, i);
      EXPECT_TRUE(k.ok()) << k.status();
      if (k.ok()) key = *k;
    }
    a.EndTransfer(id, /*released=*/true);
    return key;
  }
  // A copy of phantom file `i` as another instance of its series (a new SOP
  // Instance UID), as a modality adding an image later would send it.
  std::string ExtraInstance(size_t i, const std::string& uid) {
    DcmFileFormat ff;
    EXPECT_TRUE(ff.loadFile(files_[i].c_str()).good());
    ff.getDataset()->putAndInsertString(DCM_SOPInstanceUID, uid.c_str());
    // saveFile brings the meta group's copy of the UID up to date.
    const std::string path =
        (fs::temp_directory_path() /
         ("interslice-extra-" + std::to_string(::getpid()) + ".dcm"))
            .string();
    EXPECT_TRUE(ff.saveFile(path.c_str()).good());
    return path;
  }
  // A copy of phantom file `i` changed by `change` (saved as DCMTK writes
  // it; `name` tells the copies of one test apart).
  std::string Changed(size_t i, const std::string& name,
                      const std::function<void(DcmDataset&)>& change) {
    DcmFileFormat ff;
    EXPECT_TRUE(ff.loadFile(files_[i].c_str()).good());
    change(*ff.getDataset());
    const std::string path =
        (fs::temp_directory_path() /
         ("interslice-changed-" + std::to_string(::getpid()) + "-" + name +
          ".dcm"))
            .string();
    EXPECT_TRUE(ff.saveFile(path.c_str()).good());
    return path;
  }
  // Files [first, last) as given, in one association released normally.
  void SendFiles(SeriesAssembler& a, const std::vector<std::string>& files) {
    const uint64_t id =
        a.BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
    for (const std::string& file : files) {
      absl::StatusOr<std::string> k = AddFile(a, id, file);
      EXPECT_TRUE(k.ok()) << k.status();
    }
    a.EndTransfer(id, /*released=*/true);
  }
  // The held copies' folder names.
  std::vector<std::string> Held() const {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(root_ / "unmatched")) {
      names.push_back(e.path().filename().string());
    }
    std::sort(names.begin(), names.end());
    return names;
  }
  int IncompleteSeries() const {
    int n = 0;
    for (const auto& e : fs::directory_iterator(root_ / "series")) {
      if (fs::exists(e.path() / "incomplete.json")) ++n;
    }
    return n;
  }

  fs::path root_;
  std::vector<fs::path> files_;
  std::vector<Submitted> submitted_;
  bool fail_next_ = false;
};

TEST_F(AssemblerTest, StableSeriesBecomesTheRulesJob) {
  auto a = Open(Rules("CT", 0.05));
  ASSERT_NE(a, nullptr);
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  std::string key;
  for (size_t i = 0; i < files_.size(); ++i) {
    absl::StatusOr<std::string> k = Add(*a, id, i);
    ASSERT_TRUE(k.ok()) << k.status();
    if (i > 0) EXPECT_EQ(*k, key);  // one series
    key = *k;
  }
  // Keys are hashes: no UID in paths.
  EXPECT_EQ(key.size(), 32u);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  // Not while its association is open, however long it has been quiet.
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  a->EndTransfer(id, /*released=*/true);
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 28);
  EXPECT_EQ(submitted_[0].origin, "dicom:PACS->INTERSLICE rule r1");
  EXPECT_FLOAT_EQ(submitted_[0].spec.threshold(), 300);
  EXPECT_EQ(a->pending_series(), 0);
  EXPECT_TRUE(fs::is_empty(root_ / "series"));
  EXPECT_TRUE(fs::is_empty(root_ / "completing"));
}

// Issue 22: instances that arrive after the job was made never make a job
// of their own; the next job is made on the whole series.
TEST_F(AssemblerTest, SeriesThatGrowsAfterItsJobMakesAJobOnAllOfIt) {
  auto a = Open(Rules("CT", 0.05));
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  // One more image of the series, sent later on its own.
  const std::string extra = ExtraInstance(0, "1.2.826.0.1.3680043.2.1125.99.1");
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  ASSERT_TRUE(AddFile(*a, id, extra).ok());
  a->EndTransfer(id, true);
  fs::remove(extra);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 2u);
  EXPECT_EQ(submitted_[1].files, 29);
  // One held copy of the series: the newest.
  int held = 0;
  for (const auto& e : fs::directory_iterator(root_ / "unmatched")) {
    (void)e;
    ++held;
  }
  EXPECT_EQ(held, 1);
}

TEST_F(AssemblerTest, NotCompleteBeforeTheStableWait) {
  auto a = Open(Rules("CT", 3600));
  Send(*a, 0, 1);
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_EQ(a->pending_series(), 1);
  // A normal release completes it only when the rule says so.
  Send(*a, 1, 2);
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_TRUE(submitted_.empty());
}

TEST_F(AssemblerTest, ReleaseCompletesWhenTheRuleSaysSo) {
  auto a = Open(Rules("CT", 3600, /*complete_on_release=*/true));
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  for (size_t i = 0; i < 3; ++i) ASSERT_TRUE(Add(*a, id, i).ok());
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  a->EndTransfer(id, true);
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 3);
}

// Issue 39 finding 3: a client that posts one instance per STOW-RS request
// made one job per request under complete_on_release. A request is only part
// of an upload: the series is grouped across requests and completes after
// the stable wait, whatever complete_on_release says.
TEST_F(AssemblerTest, StowRequestsAreGroupedWhateverCompleteOnReleaseSays) {
  auto a = Open(Rules("CT", 3600, /*complete_on_release=*/true));
  for (size_t i = 0; i < 5; ++i) {
    const uint64_t id =
        a->BeginTransfer(Door::kStowRequest, "STOW:ris", "INTERSLICE");
    ASSERT_TRUE(Add(*a, id, i).ok());
    a->EndTransfer(id, /*whole=*/true);
    EXPECT_EQ(a->CompleteStableSeries(), 0) << "after request " << i + 1;
  }
  EXPECT_TRUE(submitted_.empty());
  EXPECT_EQ(a->pending_series(), 1);
}

TEST_F(AssemblerTest, StowRequestsGroupedCompleteAfterTheStableWait) {
  auto a = Open(Rules("CT", 0.05, /*complete_on_release=*/true));
  for (size_t i = 0; i < 5; ++i) {
    const uint64_t id =
        a->BeginTransfer(Door::kStowRequest, "STOW:ris", "INTERSLICE");
    ASSERT_TRUE(Add(*a, id, i).ok());
    a->EndTransfer(id, /*whole=*/true);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 5);
}

// A rule may opt into one job per request (complete_on_request); it is not
// complete_on_release, which stays the association's.
TEST_F(AssemblerTest, CompleteOnRequestMakesOneJobPerRequest) {
  RuleSet rules = Rules("CT", 3600);
  rules.rules[0].complete_on_request = true;
  auto a = Open(std::move(rules));
  const uint64_t dimse =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  ASSERT_TRUE(Add(*a, dimse, 0).ok());
  a->EndTransfer(dimse, true);
  EXPECT_EQ(a->CompleteStableSeries(), 0);  // an association: stable wait
  const uint64_t stow =
      a->BeginTransfer(Door::kStowRequest, "STOW:ris", "INTERSLICE");
  ASSERT_TRUE(Add(*a, stow, 1).ok());
  a->EndTransfer(stow, true);
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 2);
}

// Issue 39 finding 6: the same SOP classes at every door. The intake refuses
// an instance of a class the DIMSE listener would not negotiate, and its
// transfer's series are incomplete.
TEST_F(AssemblerTest, RefusesSopClassesTheNodeDoesNotStore) {
  auto a = Open(Rules("CT", 0.05));
  const std::string secondary_capture =
      Changed(0, "secondary-capture", [](DcmDataset& ds) {
        ds.putAndInsertString(DCM_SOPClassUID,
                              UID_SecondaryCaptureImageStorage);
      });
  const uint64_t id =
      a->BeginTransfer(Door::kStowRequest, "STOW:ris", "INTERSLICE");
  ASSERT_TRUE(Add(*a, id, 1).ok());
  absl::StatusOr<std::string> refused = AddFile(*a, id, secondary_capture);
  fs::remove(secondary_capture);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(refused.status().message(), HasSubstr("SOP class"));
  a->EndTransfer(id, true);
  EXPECT_EQ(IncompleteSeries(), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_TRUE(StorableSopClass(UID_CTImageStorage));
  EXPECT_FALSE(StorableSopClass(UID_DigitalXRayImageStorageForPresentation));
}

// Issue 22 finding 2: an aborted association leaves its series incomplete;
// no wait and no release makes a job of it.
TEST_F(AssemblerTest, AbortedTransferNeverBecomesAJob) {
  auto a = Open(Rules("CT", 0.05, /*complete_on_release=*/true));
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  for (size_t i = 0; i < 13; ++i) ASSERT_TRUE(Add(*a, id, i).ok());
  a->EndTransfer(id, /*released=*/false);
  EXPECT_EQ(IncompleteSeries(), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_TRUE(submitted_.empty());
  // An unrelated association that stores nothing into it changes nothing.
  a->EndTransfer(a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE"),
                 true);
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  // The sender's retry of the whole series completes it: one job, all 28.
  Send(*a, 0, files_.size());
  EXPECT_EQ(IncompleteSeries(), 0);
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 28);
}

TEST_F(AssemblerTest, OnlyATransferThatBeganLaterCompletesAnIncompleteOne) {
  auto a = Open(Rules("CT", 0.05));
  const uint64_t first =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  const uint64_t second =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  for (size_t i = 0; i < 10; ++i) ASSERT_TRUE(Add(*a, first, i).ok());
  for (size_t i = 10; i < 20; ++i) ASSERT_TRUE(Add(*a, second, i).ok());
  a->EndTransfer(first, /*released=*/false);
  // The second began before the first broke: it cannot have resent what the
  // first lost.
  a->EndTransfer(second, /*released=*/true);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_EQ(IncompleteSeries(), 1);
}

TEST_F(AssemblerTest, RefusedInstancesMakeTheSeriesIncomplete) {
  {
    // Refused by a limit: its series is known.
    AssemblerOptions options;
    options.max_instances_per_series = 5;
    auto a = Open(Rules("CT", 0.05), options);
    const uint64_t id =
        a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
    for (size_t i = 0; i < 5; ++i) ASSERT_TRUE(Add(*a, id, i).ok());
    EXPECT_EQ(Add(*a, id, 5).status().code(),
              absl::StatusCode::kResourceExhausted);
    a->EndTransfer(id, true);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_EQ(a->CompleteStableSeries(), 0);
    EXPECT_EQ(IncompleteSeries(), 1);
  }
  fs::remove_all(root_);
  {
    // Refused before its series was known (not readable): every series of
    // the association is incomplete.
    auto a = Open(Rules("CT", 0.05));
    const uint64_t id =
        a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
    ASSERT_TRUE(Add(*a, id, 0).ok());
    const std::string staged = a->StagingPath();
    std::ofstream(staged) << "not a DICOM file";
    EXPECT_EQ(a->AddInstance(id, staged, -1).status().code(),
              absl::StatusCode::kInvalidArgument);
    ASSERT_TRUE(Add(*a, id, 1).ok());
    a->EndTransfer(id, true);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_EQ(a->CompleteStableSeries(), 0);
    EXPECT_EQ(IncompleteSeries(), 1);
  }
}

// A server that dies mid-association: after the restart the series is
// incomplete (its open-<n> file says a transfer was in progress).
TEST_F(AssemblerTest, TransferInterruptedByARestartIsIncomplete) {
  {
    auto a = Open(Rules("CT", 3600));
    const uint64_t id =
        a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
    for (size_t i = 0; i < 5; ++i) ASSERT_TRUE(Add(*a, id, i).ok());
    // No EndTransfer: the process is gone.
  }
  auto b = Open(Rules("CT", 0.05));
  EXPECT_EQ(b->pending_series(), 1);
  EXPECT_EQ(IncompleteSeries(), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(b->CompleteStableSeries(), 0);
  EXPECT_TRUE(submitted_.empty());
  // The whole series again after the restart completes it.
  Send(*b, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(b->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 28);
}

TEST_F(AssemblerTest, IncompleteSeriesIsDroppedAfterTheRetention) {
  AssemblerOptions options;
  options.unmatched_retention_seconds = 0.2;
  auto a = Open(Rules("CT", 0.05), options);
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  for (size_t i = 0; i < 3; ++i) ASSERT_TRUE(Add(*a, id, i).ok());
  a->EndTransfer(id, false);
  a->DropStaleIncomplete();
  EXPECT_EQ(a->pending_series(), 1);  // not yet
  std::vector<KeptSeries> waiting = a->WaitingSeries();
  ASSERT_EQ(waiting.size(), 1u);
  EXPECT_EQ(waiting[0].state, "incomplete");
  EXPECT_EQ(waiting[0].instances, 3);
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  a->DropStaleIncomplete();
  EXPECT_EQ(a->pending_series(), 0);
  EXPECT_TRUE(fs::is_empty(root_ / "series"));
  EXPECT_TRUE(submitted_.empty());
  // The operator still sees that it was dropped, and why (issue 39).
  waiting = a->WaitingSeries();
  ASSERT_EQ(waiting.size(), 1u);
  EXPECT_EQ(waiting[0].state, "dropped");
  EXPECT_EQ(waiting[0].instances, 3);
  EXPECT_EQ(waiting[0].calling_ae, "PACS");
  EXPECT_THAT(waiting[0].why, HasSubstr("dropped as incomplete"));
  EXPECT_EQ(a->ListKept().front().state, "dropped");
}

TEST_F(AssemblerTest, ResentInstanceReplacesItself) {
  auto a = Open(Rules("CT", 0.05));
  Send(*a, 0, 1);
  Send(*a, 0, 2);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  a->CompleteStableSeries();
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 2);
}

TEST_F(AssemblerTest, FailedSubmissionIsRetriedWithAllInstances) {
  auto a = Open(Rules("CT", 0.05));
  Send(*a, 0, 4);
  fail_next_ = true;
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  EXPECT_TRUE(submitted_.empty());
  EXPECT_EQ(a->pending_series(), 1);  // back, waiting again
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 4);
}

TEST_F(AssemblerTest, UnmatchedSeriesIsKeptThenRemoved) {
  AssemblerOptions options;
  options.unmatched_retention_seconds = 3600;
  {
    auto a = Open(Rules("MR", 0.05), options);
    Send(*a, 0, 1);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    EXPECT_EQ(a->CompleteStableSeries(), 1);
    EXPECT_TRUE(submitted_.empty());
    EXPECT_FALSE(fs::is_empty(root_ / "unmatched"));
    a->SweepUnmatched();  // not expired yet
    EXPECT_FALSE(fs::is_empty(root_ / "unmatched"));
  }
  options.unmatched_retention_seconds = 0;
  auto b = Open(Rules("MR", 0.05), options);
  b->SweepUnmatched();
  EXPECT_TRUE(fs::is_empty(root_ / "unmatched"));
}

TEST_F(AssemblerTest, LimitsRefuseWithResourceExhausted) {
  AssemblerOptions options;
  options.max_instances_per_series = 2;
  auto a = Open(Rules("CT", 3600), options);
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  ASSERT_TRUE(Add(*a, id, 0).ok());
  ASSERT_TRUE(Add(*a, id, 1).ok());
  absl::StatusOr<std::string> third = Add(*a, id, 2);
  EXPECT_EQ(third.status().code(), absl::StatusCode::kResourceExhausted);
  options.max_instances_per_series = 100;
  options.max_bytes_per_series = 100000;  // less than one slice
  fs::remove_all(root_);
  auto b = Open(Rules("CT", 3600), options);
  const uint64_t other =
      b->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  EXPECT_EQ(Add(*b, other, 0).status().code(),
            absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(b->pending_series(), 0);
}

TEST_F(AssemblerTest, NotDicomIsInvalidArgument) {
  auto a = Open(Rules("CT", 3600));
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  const std::string staged = a->StagingPath();
  std::ofstream(staged) << "not a DICOM file";
  EXPECT_EQ(a->AddInstance(id, staged, -1).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(staged));
}

// A data set nested deeper than the scan allows is refused before DCMTK
// parses it (issue 22 finding 1: 10,000 levels overflowed the stack).
TEST_F(AssemblerTest, HostileNestingIsRefusedUnparsed) {
  auto a = Open(Rules("CT", 3600));
  const uint64_t id =
      a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  // A Part 10 file around issue 22's data set: preamble, DICM, a meta group
  // naming explicit VR little endian.
  std::string meta_elements;
  auto element = [&](uint16_t e, const char* vr, std::string value) {
    if (value.size() % 2) value.push_back('\0');
    std::string out;
    out.push_back(0x02);
    out.push_back(0x00);
    out.push_back(static_cast<char>(e & 0xFF));
    out.push_back(static_cast<char>(e >> 8));
    out.append(vr, 2);
    out.push_back(static_cast<char>(value.size() & 0xFF));
    out.push_back(static_cast<char>(value.size() >> 8));
    meta_elements += out + value;
  };
  element(0x0010, "UI", "1.2.840.10008.1.2.1");
  const std::string file = std::string(128, '\0') + "DICM" + meta_elements +
                           interslice::testing::NestedDataset("1.2.3", 10000);
  const std::string staged = a->StagingPath();
  std::ofstream(staged, std::ios::binary) << file;
  absl::StatusOr<std::string> key = a->AddInstance(id, staged, -1);
  ASSERT_FALSE(key.ok());
  EXPECT_EQ(key.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(key.status().message(), HasSubstr("nesting deeper than 32"));
}

TEST_F(AssemblerTest, PendingSeriesSurviveAReopen) {
  {
    auto a = Open(Rules("CT", 3600));
    Send(*a, 0, 5);
  }
  auto b = Open(Rules("CT", 0.05));
  EXPECT_EQ(b->pending_series(), 1);
  EXPECT_EQ(IncompleteSeries(), 0);  // its association was released
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(b->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 5);
  EXPECT_EQ(submitted_[0].origin, "dicom:PACS->INTERSLICE rule r1");
}

TEST_F(AssemblerTest, FactsForRules) {
  auto a = Open(Rules("CT", 3600));
  const std::string key = Send(*a, 0, files_.size());
  const SeriesFacts facts = ReadSeriesFacts((root_ / "series" / key).string());
  EXPECT_EQ(facts.modality, "CT");
  EXPECT_EQ(facts.slice_count, 28);
  ASSERT_TRUE(facts.slice_spacing_mm.has_value());
  EXPECT_NEAR(*facts.slice_spacing_mm, 5.0, 0.01);  // the phantom's README
  ASSERT_TRUE(facts.slice_thickness_mm.has_value());
}

// Issue 25: instances that arrive again after the job was made, each the
// same SOP instance with the same bytes, cannot change the result: no job,
// and the held copy stays as it was (with its job file and retention).
TEST_F(AssemblerTest, ResentUnchangedInstancesMakeNoJob) {
  auto a = Open(Rules("CT", 0.05));
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  const std::vector<std::string> held = Held();
  ASSERT_EQ(held.size(), 1u);
  // A sender retries four of the instances (or all of them).
  Send(*a, 0, 4);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  EXPECT_EQ(submitted_.size(), 1u);
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  EXPECT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(Held(), held);
  int kept = 0;
  for (const auto& e : fs::directory_iterator(root_ / "unmatched" / held[0])) {
    if (e.path().extension() == ".dcm") ++kept;
  }
  EXPECT_EQ(kept, 28);
  EXPECT_TRUE(fs::exists(root_ / "unmatched" / held[0] / "job"));
  EXPECT_EQ(a->pending_series(), 0);
  EXPECT_TRUE(fs::is_empty(root_ / "series"));
  EXPECT_TRUE(fs::is_empty(root_ / "completing"));
}

// Re-sending is how a PACS operator retries: after a job that ended
// without results, the unchanged series makes its job again; after one that
// did not, it makes none (found in review of the re-send change).
TEST_F(AssemblerTest, ResentUnchangedSeriesAfterAFailedJobMakesItAgain) {
  std::set<std::string> failed;
  AssemblerOptions options;
  options.job_ended_without_results = [&failed](const std::string& id) {
    return failed.count(id) > 0;
  };
  auto a = Open(Rules("CT", 0.05), options);
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  Send(*a, 0, files_.size());  // job1 did not fail: nothing made
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  EXPECT_EQ(submitted_.size(), 1u);
  failed.insert("job1");
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 2u);
  EXPECT_EQ(submitted_[1].files, 28);
  const std::vector<std::string> held = Held();
  ASSERT_EQ(held.size(), 1u);
  std::string job;
  std::ifstream(root_ / "unmatched" / held[0] / "job") >> job;
  EXPECT_EQ(job, "job2");
}

// One re-sent instance changed (the same SOP Instance UID, other content):
// the job is made again, on the whole series.
TEST_F(AssemblerTest, ResentChangedInstanceMakesTheJobOnTheWholeSeries) {
  auto a = Open(Rules("CT", 0.05));
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  const std::string changed = Changed(2, "window", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_WindowCenter, "123");
  });
  SendFiles(*a, {files_[1].string(), changed, files_[3].string()});
  fs::remove(changed);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 2u);
  EXPECT_EQ(submitted_[1].files, 28);
  // A new instance (another SOP Instance UID) too.
  const std::string extra = ExtraInstance(0, "1.2.826.0.1.3680043.2.1125.99.7");
  SendFiles(*a, {extra});
  fs::remove(extra);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 3u);
  EXPECT_EQ(submitted_[2].files, 29);
}

// A series held without a job (no rule matched) and sent again unchanged
// is matched again: the rules may have been fixed since.
TEST_F(AssemblerTest, ResentUnmatchedSeriesIsMatchedAgain) {
  auto a = Open(Rules("MR", 0.05));
  Send(*a, 0, 4);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  EXPECT_TRUE(submitted_.empty());
  a->SetRules(Rules("CT", 0.05));
  Send(*a, 0, 4);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 4);
}

// A late instance of a held series from another frame of reference is
// refused (never merged into the held series' geometry); the held copy
// stays, and what its association stored into the series with it is
// incomplete (as for any refused instance).
TEST_F(AssemblerTest, LateInstanceOfAnotherFrameOfReferenceIsRefused) {
  auto a = Open(Rules("CT", 0.05));
  Send(*a, 0, files_.size());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  const std::vector<std::string> held = Held();
  auto other_frame = [](const std::string& uid) {
    return [uid](DcmDataset& ds) {
      ds.putAndInsertString(DCM_SOPInstanceUID, uid.c_str());
      ds.putAndInsertString(DCM_FrameOfReferenceUID,
                            "1.2.826.0.1.3680043.2.1125.99.500");
    };
  };
  // Alone in its association: refused, nothing starts.
  const std::string lone =
      Changed(0, "lone", other_frame("1.2.826.0.1.3680043.2.1125.99.11"));
  uint64_t id = a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  absl::StatusOr<std::string> key = AddFile(*a, id, lone);
  fs::remove(lone);
  ASSERT_FALSE(key.ok());
  EXPECT_EQ(key.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(key.status().message(), HasSubstr("frame of reference"));
  a->EndTransfer(id, true);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(Held(), held);
  // After a late instance of the same frame (accepted): refused too, and
  // the grown series makes no job of two geometries.
  const std::string same = ExtraInstance(1, "1.2.826.0.1.3680043.2.1125.99.12");
  const std::string other =
      Changed(2, "other", other_frame("1.2.826.0.1.3680043.2.1125.99.13"));
  id = a->BeginTransfer(Door::kAssociation, "PACS", "INTERSLICE");
  EXPECT_TRUE(AddFile(*a, id, same).ok());
  key = AddFile(*a, id, other);
  fs::remove(same);
  fs::remove(other);
  ASSERT_FALSE(key.ok());
  EXPECT_THAT(key.status().message(), HasSubstr("frame of reference"));
  a->EndTransfer(id, true);
  EXPECT_EQ(IncompleteSeries(), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_EQ(submitted_.size(), 1u);
}

// Kept series are listed with why they are kept, and run again against the
// rules in force now.
TEST_F(AssemblerTest, KeptSeriesAreListedAndRunAgainByTheRulesNow) {
  auto a = Open(Rules("MR", 0.05));
  Send(*a, 0, 6);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_TRUE(submitted_.empty());
  std::vector<KeptSeries> kept = a->ListKept();
  ASSERT_EQ(kept.size(), 1u);
  EXPECT_EQ(kept[0].calling_ae, "PACS");
  EXPECT_EQ(kept[0].called_ae, "INTERSLICE");
  EXPECT_EQ(kept[0].modality, "CT");
  EXPECT_EQ(kept[0].instances, 6);
  EXPECT_GT(kept[0].kept_since_unix_ms, 0);
  EXPECT_TRUE(kept[0].job_id.empty());
  EXPECT_EQ(kept[0].why,
            "no rule matched; the rules now: rule 'r1': modality is 'CT', not "
            "'MR'");
  EXPECT_FALSE(kept[0].study_uid.empty());
  EXPECT_FALSE(kept[0].series_uid.empty());
  // The same rules: still no match, not an error; kept as it was.
  absl::StatusOr<KeptRerun> again = a->RerunKept(kept[0].id);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->job_id.empty());
  EXPECT_THAT(again->not_matched, HasSubstr("modality is 'CT', not 'MR'"));
  EXPECT_EQ(Held(), std::vector<std::string>{kept[0].id});
  // Unknown ids, a path among them.
  for (const std::string& bad : {std::string("nope"), std::string("../series"),
                                 kept[0].id.substr(0, 33) + "1"}) {
    EXPECT_EQ(a->RerunKept(bad).status().code(), absl::StatusCode::kNotFound)
        << bad;
  }
  // The rules fixed (a reload): its job, with every instance.
  a->SetRules(Rules("CT", 0.05));
  absl::StatusOr<KeptRerun> run = a->RerunKept(kept[0].id);
  ASSERT_TRUE(run.ok()) << run.status();
  EXPECT_EQ(run->job_id, "job1");
  EXPECT_TRUE(run->not_matched.empty());
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 6);
  EXPECT_EQ(submitted_[0].origin, "dicom:PACS->INTERSLICE rule r1");
  // Held again, now with its job; the old id is gone.
  kept = a->ListKept();
  ASSERT_EQ(kept.size(), 1u);
  EXPECT_EQ(kept[0].job_id, "job1");
  EXPECT_EQ(kept[0].why, "job job1 made");
  EXPECT_EQ(a->RerunKept(run->id).status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(fs::is_empty(root_ / "completing"));
  EXPECT_TRUE(fs::is_empty(root_ / "series"));
  // A held series with a job is not "unmatched"; one can still be run by
  // its id.
  absl::StatusOr<std::vector<KeptRerun>> all = a->RerunAllUnmatched();
  ASSERT_TRUE(all.ok()) << all.status();
  EXPECT_TRUE(all->empty());
  run = a->RerunKept(kept[0].id);
  ASSERT_TRUE(run.ok()) << run.status();
  EXPECT_EQ(run->job_id, "job2");
}

// A full queue: the rerun fails with the manager's error and the series
// stays kept under its id; --all-unmatched runs each one without a job.
TEST_F(AssemblerTest, RerunThatCannotBeSubmittedKeepsTheSeries) {
  auto a = Open(Rules("MR", 0.05));
  Send(*a, 0, 3);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ASSERT_EQ(a->CompleteStableSeries(), 1);
  const std::vector<std::string> held = Held();
  ASSERT_EQ(held.size(), 1u);
  a->SetRules(Rules("CT", 0.05));
  fail_next_ = true;
  absl::StatusOr<KeptRerun> run = a->RerunKept(held[0]);
  EXPECT_EQ(run.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(Held(), held);
  EXPECT_EQ(a->pending_series(), 0);
  absl::StatusOr<std::vector<KeptRerun>> all = a->RerunAllUnmatched();
  ASSERT_TRUE(all.ok()) << all.status();
  ASSERT_EQ(all->size(), 1u);
  EXPECT_EQ((*all)[0].job_id, "job1");
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 3);
}

// The stable wait is measured by the clock the assembler is given: a test
// moves it instead of sleeping (tests/testing/fake_clock.h).
TEST_F(AssemblerTest, StableWaitIsMeasuredByTheGivenClock) {
  testing::FakeClock clock;
  AssemblerOptions options;
  options.clock = &clock;
  std::unique_ptr<SeriesAssembler> a = Open(Rules("CT", 30), options);
  ASSERT_NE(a, nullptr);
  Send(*a, 0, 3);
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  clock.Advance(std::chrono::seconds(29));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_TRUE(submitted_.empty());
  clock.Advance(std::chrono::seconds(2));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 3);
}

}  // namespace
}  // namespace interslice::server::node
