// `interslice find` (the Find RPC, C-FIND SCU, server/net/dimse/find.h) against
// a real Orthanc: studies and series with their UIDs, the keys filtering,
// the caps said in the answer, and the errors (unknown or unreachable peer,
// a bad key, a caller who is not an admin), with no UID in the server's log.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;

const std::string kCli = ::interslice::testing::CliPath();
const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
const fs::path kEnhancedMr = fs::path(::interslice::testing::TestDataDir()) /
                             "multiframe" / "philips-enhanced-mr-64frames.dcm";

// The words after `kind` ("study", "series") at the start of output lines.
std::set<std::string> Listed(const std::string& out, const std::string& kind) {
  std::set<std::string> uids;
  for (absl::string_view line : absl::StrSplit(out, '\n')) {
    line = absl::StripLeadingAsciiWhitespace(line);
    if (!absl::StartsWith(line, kind + " ")) continue;
    std::vector<std::string> words =
        absl::StrSplit(line, ' ', absl::SkipEmpty());
    if (words.size() > 1) uids.insert(words[1]);
  }
  return uids;
}

class FindTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto orthanc = Orthanc::Start(
        (dir_.path() / "orthanc").string(),
        {{"interslice", "INTERSLICE", "127.0.0.1", FreeTcpPort()}}, "ORTHANC",
        {.dicomweb = true});
    ASSERT_TRUE(orthanc.ok()) << orthanc.status();
    orthanc_ = *std::move(orthanc);
    absl::StatusOr<int> ct = orthanc_->UploadFolder(kThick.string());
    ASSERT_TRUE(ct.ok()) << ct.status();
    ASSERT_EQ(*ct, 4);
    absl::StatusOr<std::string> mr = orthanc_->Upload(kEnhancedMr.string());
    ASSERT_TRUE(mr.ok()) << mr.status();
    // Orthanc's own view: study UID -> (modalities, series UIDs).
    absl::StatusOr<nlohmann::json> studies =
        orthanc_->GetJson("/studies?expand");
    ASSERT_TRUE(studies.ok()) << studies.status();
    for (const nlohmann::json& study : *studies) {
      const std::string uid =
          study["MainDicomTags"]["StudyInstanceUID"].get<std::string>();
      for (const nlohmann::json& id : study["Series"]) {
        absl::StatusOr<nlohmann::json> series =
            orthanc_->GetJson("/series/" + id.get<std::string>());
        ASSERT_TRUE(series.ok()) << series.status();
        const std::string modality =
            (*series)["MainDicomTags"]["Modality"].get<std::string>();
        const std::string series_uid =
            (*series)["MainDicomTags"]["SeriesInstanceUID"].get<std::string>();
        all_series_.insert(series_uid);
        (modality == "MR" ? mr_studies_ : ct_studies_).insert(uid);
        if (modality == "MR") mr_series_.insert(series_uid);
      }
      all_studies_.insert(uid);
    }
    ASSERT_EQ(all_studies_.size(), 2u);

    const std::string peers = dir_ / "peers.yaml";
    std::ofstream(peers) << "peers:\n  - {name: orthanc, ae_title: "
                         << orthanc_->ae_title() << ", host: 127.0.0.1, port: "
                         << orthanc_->dicom_port()
                         << "}\n  - {name: down, ae_title: DOWN, host: "
                            "127.0.0.1, port: "
                         << FreeTcpPort()
                         << "}\n  - {name: web, type: dicomweb, url: '"
                         << orthanc_->dicomweb_url() << "'}\n";
    std::ofstream(dir_ / "tokens") << "admin:admin-token\nuser:user-token\n";
    std::ofstream(dir_ / "admin.token") << "admin-token\n";
    std::ofstream(dir_ / "user.token") << "user-token\n";
    server_ = std::make_unique<ServerProcess>(
        ServerOptions{.spool = dir_ / "spool",
                      .log = dir_ / "server.log",
                      .extra = {"--dicom-peers", peers, "--auth-token-file",
                                dir_ / "tokens", "--admin-identity", "admin"}});
    ASSERT_TRUE(server_->Start());
  }

  CommandResult Find(const std::vector<std::string>& args,
                     const std::string& token = "admin.token") {
    return RunCommand(
        Cat(Cat({kCli, "find"}, args),
            Cat(server_->ServerFlag(), {"--token-file", dir_ / token})),
        300);
  }

  TempDir dir_;
  std::unique_ptr<Orthanc> orthanc_;
  std::unique_ptr<ServerProcess> server_;
  std::set<std::string> all_studies_, ct_studies_, mr_studies_;
  std::set<std::string> all_series_, mr_series_;
};

TEST_F(FindTest, ListsStudiesAndSeriesWithTheirUidsAndFiltersByKeys) {
  const CommandResult all = Find({"--pacs", "orthanc"});
  ASSERT_EQ(all.exit_code, 0) << all.err << server_->Log();
  EXPECT_EQ(Listed(all.out, "study"), all_studies_) << all.out;
  EXPECT_EQ(Listed(all.out, "series"), all_series_) << all.out;
  EXPECT_THAT(all.out, HasSubstr("4 instance(s)"));  // the CT series
  EXPECT_THAT(all.err, Not(HasSubstr("more matched")));

  const CommandResult mr = Find({"--pacs", "orthanc", "--modality", "MR"});
  ASSERT_EQ(mr.exit_code, 0) << mr.err;
  EXPECT_EQ(Listed(mr.out, "study"), mr_studies_) << mr.out;
  EXPECT_EQ(Listed(mr.out, "series"), mr_series_) << mr.out;

  const CommandResult nobody =
      Find({"--pacs", "orthanc", "--patient-id", "NO-SUCH-PATIENT*"});
  ASSERT_EQ(nobody.exit_code, 0) << nobody.err;
  EXPECT_TRUE(Listed(nobody.out, "study").empty()) << nobody.out;
  EXPECT_THAT(nobody.err, HasSubstr("no study on peer orthanc matches"));

  const CommandResult dated =
      Find({"--pacs", "orthanc", "--study-date", "-19000101"});
  ASSERT_EQ(dated.exit_code, 0) << dated.err;
  EXPECT_TRUE(Listed(dated.out, "study").empty()) << dated.out;

  // The log has the counts, never a UID.
  const std::string log = server_->Log();
  EXPECT_THAT(log, HasSubstr("find on peer orthanc: 2 study(ies)"));
  for (const std::string& uid : all_studies_) {
    EXPECT_THAT(log, Not(HasSubstr(uid)));
  }
  for (const std::string& uid : all_series_) {
    EXPECT_THAT(log, Not(HasSubstr(uid)));
  }
}

// Issue 27: on a DICOMweb peer `interslice find` asks QIDO-RS, and lists
// exactly what C-FIND lists on the same Orthanc, line for line.
TEST_F(FindTest, DicomWebPeerListsWhatCFindLists) {
  for (const std::vector<std::string>& keys :
       {std::vector<std::string>{},
        {"--modality", "MR"},
        {"--patient-id", "NO-SUCH-PATIENT*"}}) {
    const CommandResult dimse = Find(Cat({"--pacs", "orthanc"}, keys));
    const CommandResult web = Find(Cat({"--pacs", "web"}, keys));
    ASSERT_EQ(dimse.exit_code, 0) << dimse.err;
    ASSERT_EQ(web.exit_code, 0) << web.err << server_->Log();
    EXPECT_EQ(web.out, dimse.out);
  }
  const CommandResult all = Find({"--pacs", "web"});
  EXPECT_EQ(Listed(all.out, "study"), all_studies_) << all.out;
  EXPECT_EQ(Listed(all.out, "series"), all_series_) << all.out;
  EXPECT_THAT(all.out, HasSubstr("4 instance(s)"));
}

TEST_F(FindTest, MoreMatchesThanTheCapAreCutAndSaidSo) {
  const CommandResult one = Find({"--pacs", "orthanc", "--max-studies", "1"});
  ASSERT_EQ(one.exit_code, 0) << one.err << server_->Log();
  EXPECT_EQ(Listed(one.out, "study").size(), 1u) << one.out;
  EXPECT_THAT(one.err, HasSubstr("more matched than the caps (1 studies"));
  EXPECT_THAT(server_->Log(), HasSubstr("(truncated at the caps)"));
  // The association survived the C-CANCEL: the next query answers whole.
  const CommandResult all = Find({"--pacs", "orthanc"});
  ASSERT_EQ(all.exit_code, 0) << all.err;
  EXPECT_EQ(Listed(all.out, "study"), all_studies_);
}

TEST_F(FindTest, ErrorsAreOneLineAndExitCodeOne) {
  const CommandResult unknown = Find({"--pacs", "elsewhere"});
  EXPECT_EQ(unknown.exit_code, 1);
  EXPECT_THAT(unknown.err, HasSubstr("unknown DICOM peer \"elsewhere\""));

  const CommandResult down = Find({"--pacs", "down"});
  EXPECT_EQ(down.exit_code, 1);
  EXPECT_THAT(down.err, HasSubstr("error: cannot associate with peer down"));
  EXPECT_THAT(down.err, Not(HasSubstr("cannot reach the server")));

  const CommandResult bad_date =
      Find({"--pacs", "orthanc", "--study-date", "2024"});
  EXPECT_EQ(bad_date.exit_code, 1);
  EXPECT_THAT(bad_date.err, HasSubstr("study_date: expected YYYYMMDD"));

  const CommandResult list =
      Find({"--pacs", "orthanc", "--patient-id", "A\\B"});
  EXPECT_EQ(list.exit_code, 1);
  EXPECT_THAT(list.err, HasSubstr("patient_id: a single value"));

  const CommandResult user = Find({"--pacs", "orthanc"}, "user.token");
  EXPECT_EQ(user.exit_code, 1);
  EXPECT_THAT(user.err, HasSubstr("admin identities only"));
  EXPECT_TRUE(Listed(user.out, "study").empty());
}

}  // namespace
}  // namespace interslice::testing
