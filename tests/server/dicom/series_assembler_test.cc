// SeriesAssembler in-process: a fake job submitter records what a complete
// series would become.
#include "server/dicom/series_assembler.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice::server::dicom {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kPhantom =
    std::string(INTERSLICE_SOURCE_DIR) + "/data/ct-head-phantom-thick";

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

  // Stages a copy of phantom file `i` and adds it.
  absl::StatusOr<std::string> Add(SeriesAssembler& a, size_t i) {
    const std::string staged = a.StagingPath();
    fs::copy_file(files_[i], staged);
    absl::StatusOr<std::string> key =
        a.AddInstance("PACS", "INTERSLICE", staged);
    EXPECT_FALSE(fs::exists(staged));  // taken or deleted, never left behind
    return key;
  }

  fs::path root_;
  std::vector<fs::path> files_;
  std::vector<Submitted> submitted_;
  bool fail_next_ = false;
};

TEST_F(AssemblerTest, StableSeriesBecomesTheRulesJob) {
  auto a = Open(Rules("CT", 0.05));
  ASSERT_NE(a, nullptr);
  std::string key;
  for (size_t i = 0; i < files_.size(); ++i) {
    absl::StatusOr<std::string> k = Add(*a, i);
    ASSERT_TRUE(k.ok()) << k.status();
    if (i > 0) EXPECT_EQ(*k, key);  // one series
    key = *k;
  }
  // Keys are hashes: no UID in paths.
  EXPECT_EQ(key.size(), 32u);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 28);
  EXPECT_EQ(submitted_[0].origin, "dicom:PACS->INTERSLICE rule r1");
  EXPECT_FLOAT_EQ(submitted_[0].spec.threshold(), 300);
  EXPECT_EQ(a->pending_series(), 0);
  EXPECT_TRUE(fs::is_empty(root_ / "series"));
  EXPECT_TRUE(fs::is_empty(root_ / "completing"));
  // The series grows after its job was made: a new series, a new job.
  ASSERT_TRUE(Add(*a, 0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 2u);
  EXPECT_EQ(submitted_[1].files, 1);
}

TEST_F(AssemblerTest, NotCompleteBeforeTheStableWait) {
  auto a = Open(Rules("CT", 3600));
  ASSERT_TRUE(Add(*a, 0).ok());
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_EQ(a->pending_series(), 1);
  // A normal release completes it only when the rule says so.
  a->AssociationReleased({*Add(*a, 1)});
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  EXPECT_TRUE(submitted_.empty());
}

TEST_F(AssemblerTest, ReleaseCompletesWhenTheRuleSaysSo) {
  auto a = Open(Rules("CT", 3600, /*complete_on_release=*/true));
  std::set<std::string> keys;
  for (size_t i = 0; i < 3; ++i) keys.insert(*Add(*a, i));
  EXPECT_EQ(a->CompleteStableSeries(), 0);
  a->AssociationReleased(keys);
  EXPECT_EQ(a->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 3);
}

TEST_F(AssemblerTest, ResentInstanceReplacesItself) {
  auto a = Open(Rules("CT", 0.05));
  ASSERT_TRUE(Add(*a, 0).ok());
  ASSERT_TRUE(Add(*a, 0).ok());
  ASSERT_TRUE(Add(*a, 1).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  a->CompleteStableSeries();
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 2);
}

TEST_F(AssemblerTest, FailedSubmissionIsRetriedWithAllInstances) {
  auto a = Open(Rules("CT", 0.05));
  for (size_t i = 0; i < 4; ++i) ASSERT_TRUE(Add(*a, i).ok());
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
    ASSERT_TRUE(Add(*a, 0).ok());
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
  ASSERT_TRUE(Add(*a, 0).ok());
  ASSERT_TRUE(Add(*a, 1).ok());
  absl::StatusOr<std::string> third = Add(*a, 2);
  EXPECT_EQ(third.status().code(), absl::StatusCode::kResourceExhausted);
  options.max_instances_per_series = 100;
  options.max_bytes_per_series = 100000;  // less than one slice
  fs::remove_all(root_);
  auto b = Open(Rules("CT", 3600), options);
  EXPECT_EQ(Add(*b, 0).status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(b->pending_series(), 0);
}

TEST_F(AssemblerTest, NotDicomIsInvalidArgument) {
  auto a = Open(Rules("CT", 3600));
  const std::string staged = a->StagingPath();
  std::ofstream(staged) << "not a DICOM file";
  EXPECT_EQ(a->AddInstance("PACS", "INTERSLICE", staged).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(staged));
}

TEST_F(AssemblerTest, PendingSeriesSurviveAReopen) {
  {
    auto a = Open(Rules("CT", 3600));
    for (size_t i = 0; i < 5; ++i) ASSERT_TRUE(Add(*a, i).ok());
  }
  auto b = Open(Rules("CT", 0.05));
  EXPECT_EQ(b->pending_series(), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(b->CompleteStableSeries(), 1);
  ASSERT_EQ(submitted_.size(), 1u);
  EXPECT_EQ(submitted_[0].files, 5);
  EXPECT_EQ(submitted_[0].origin, "dicom:PACS->INTERSLICE rule r1");
}

TEST_F(AssemblerTest, FactsForRules) {
  auto a = Open(Rules("CT", 3600));
  std::string key;
  for (size_t i = 0; i < files_.size(); ++i) key = *Add(*a, i);
  const SeriesFacts facts = ReadSeriesFacts((root_ / "series" / key).string());
  EXPECT_EQ(facts.modality, "CT");
  EXPECT_EQ(facts.slice_count, 28);
  ASSERT_TRUE(facts.slice_spacing_mm.has_value());
  EXPECT_NEAR(*facts.slice_spacing_mm, 5.0, 0.01);  // the phantom's README
  ASSERT_TRUE(facts.slice_thickness_mm.has_value());
}

}  // namespace
}  // namespace interslice::server::dicom
