// Pulling from a DICOMweb peer (server/net/dicomweb/pull.h) through the
// same interface as DIMSE (node::PeerClient's Retrieve and Find, as the
// server's peer registry makes them): against
// Debian's Orthanc with its DICOMweb plugin, the QIDO-RS + WADO-RS pull
// equals the C-GET pull byte for byte and QIDO-RS finds what C-FIND finds;
// against canned answers, every lie (sizes, counts, truncation, HTML) is a
// clean error with nothing partial left behind.
#include <openssl/sha.h>

#include <algorithm>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/net/dicomweb/dicomweb_peer.h"
#include "server/net/dimse/dimse_peer.h"
#include "server/node/outbox.h"
#include "server/node/peer.h"
#include "tests/testing/canned_http.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/temp_dir.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dctk.h"

namespace interslice::server::dicomweb {
namespace {

namespace fs = std::filesystem;
using node::DicomPeer;
using node::RetrieveResult;
using RetrieveOptions = node::RetrieveLimits;
using testing::CannedHttp;
using testing::CannedRequest;
using ::testing::HasSubstr;
using testing::Orthanc;

const fs::path kPhantom = fs::path(::interslice::testing::SourceDir()) /
                          "data" / "ct-head-phantom-thick";
const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";

DicomPeer WebPeer(const std::string& url) {
  DicomPeer peer;
  peer.name = "web";
  peer.type = node::PeerType::kDicomWeb;
  peer.web.url = url;
  return peer;
}

// The peer's client, as the server's factory makes it (app/server.cc).
std::unique_ptr<node::PeerClient> Client(const DicomPeer& peer) {
  if (peer.type == node::PeerType::kDicomWeb) {
    return std::make_unique<DicomWebPeerClient>(peer,
                                                node::PeerClientSettings{});
  }
  return std::make_unique<dimse::DimsePeerClient>(peer,
                                                  node::PeerClientSettings{});
}

absl::StatusOr<RetrieveResult> Retrieve(const DicomPeer& peer,
                                        const std::string& study,
                                        const std::string& series,
                                        const std::string& dir,
                                        const node::RetrieveLimits& limits) {
  return Client(peer)->Retrieve(study, series, dir, limits);
}

absl::StatusOr<node::FindResult> Find(const DicomPeer& peer,
                                      const node::FindQuery& query,
                                      const node::FindLimits& limits) {
  return Client(peer)->Find(query, limits);
}

std::string Tag(const std::string& file, const DcmTagKey& tag) {
  DcmFileFormat f;
  EXPECT_TRUE(f.loadFile(file.c_str()).good()) << file;
  OFString value;
  f.getDataset()->findAndGetOFString(tag, value);
  return value.c_str();
}

std::string Sha256Hex(const std::string& bytes) {
  unsigned char digest[SHA256_DIGEST_LENGTH];
  SHA256(reinterpret_cast<const unsigned char*>(bytes.data()), bytes.size(),
         digest);
  return absl::BytesToHexString(
      absl::string_view(reinterpret_cast<const char*>(digest), sizeof(digest)));
}

// Sorted SHA-256 (hex) of every regular file in `dir`.
std::vector<std::string> Hashes(const fs::path& dir) {
  std::vector<std::string> out;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    out.push_back(Sha256Hex(testing::ReadFileOrEmpty(e.path().string())));
  }
  std::sort(out.begin(), out.end());
  return out;
}

// The data set of a Part 10 file: what follows the File Meta Information
// (preamble, "DICM", then group 0002, whose length (0002,0000) comes first,
// explicit VR little endian: PS3.10 7.1).
std::string DatasetBytes(const std::string& file) {
  if (file.size() < 144 || file.compare(128, 4, "DICM") != 0 ||
      file.compare(132, 4, std::string("\x02\x00\x00\x00", 4)) != 0) {
    ADD_FAILURE() << "not a Part 10 file with a group length";
    return "";
  }
  const auto* p = reinterpret_cast<const unsigned char*>(file.data()) + 140;
  const uint32_t group_length =
      p[0] | (p[1] << 8) | (p[2] << 16) | (static_cast<uint32_t>(p[3]) << 24);
  return file.substr(std::min<size_t>(file.size(), 144 + group_length));
}

// Sorted SHA-256 of the data sets (after the meta header) in `dir`.
std::vector<std::string> DatasetHashes(const fs::path& dir) {
  std::vector<std::string> out;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    out.push_back(
        Sha256Hex(DatasetBytes(testing::ReadFileOrEmpty(e.path().string()))));
  }
  std::sort(out.begin(), out.end());
  return out;
}

size_t FileCount(const fs::path& dir) {
  size_t n = 0;
  for (const auto& e : fs::directory_iterator(dir)) n += e.is_regular_file();
  return n;
}

class OrthancPullTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto orthanc = Orthanc::Start(
        (dir_.path() / "orthanc").string(),
        {{"interslice", "INTERSLICE", "127.0.0.1", testing::FreeTcpPort()}},
        "ORTHANC", {.dicomweb = true});
    ASSERT_TRUE(orthanc.ok()) << orthanc.status();
    orthanc_ = *std::move(orthanc);
    absl::StatusOr<int> n = orthanc_->UploadFolder(kPhantom.string());
    ASSERT_TRUE(n.ok()) << n.status();
    ASSERT_EQ(*n, 28);
    const std::string first = (kPhantom / "I10.dcm").string();
    study_ = Tag(first, DCM_StudyInstanceUID);
    series_ = Tag(first, DCM_SeriesInstanceUID);
    dimse_.name = "orthanc";
    dimse_.ae_title = orthanc_->ae_title();
    dimse_.host = "127.0.0.1";
    dimse_.port = orthanc_->dicom_port();
    web_ = WebPeer(orthanc_->dicomweb_url());
  }
  fs::path Folder(const std::string& name) {
    const fs::path p = dir_.path() / name;
    fs::create_directories(p);
    return p;
  }

  testing::TempDir dir_{"interslice_dicomweb_pull_"};
  std::unique_ptr<Orthanc> orthanc_;
  std::string study_, series_;
  DicomPeer dimse_, web_;
};

// The brief's check: the QIDO+WADO pull of a series equals the C-GET pull
// from the same Orthanc, file contents byte for byte (sorted SHA-256s).
TEST_F(OrthancPullTest, WadoPullEqualsCGetPullByteForByte) {
  const fs::path by_web = Folder("web"), by_get = Folder("get");
  absl::StatusOr<RetrieveResult> web =
      Retrieve(web_, study_, series_, by_web.string(), {});
  ASSERT_TRUE(web.ok()) << web.status();
  absl::StatusOr<RetrieveResult> get =
      Retrieve(dimse_, study_, series_, by_get.string(), {});
  ASSERT_TRUE(get.ok()) << get.status();
  EXPECT_EQ(web->instances, 28);
  EXPECT_EQ(get->instances, 28);
  EXPECT_EQ(FileCount(by_web), 28u);  // no temporary file left
  // WADO-RS gives the files as Orthanc holds them: the uploaded files, byte
  // for byte.
  std::vector<std::string> uploaded;
  for (const std::string& f : node::ListDicomFiles(kPhantom.string())) {
    uploaded.push_back(Sha256Hex(testing::ReadFileOrEmpty(f)));
  }
  std::sort(uploaded.begin(), uploaded.end());
  EXPECT_EQ(Hashes(by_web), uploaded);
  // C-GET carries data sets only: the retriever writes them bit-preserved
  // under a File Meta Information of DCMTK's making (its implementation
  // class UID and version name), so the files differ in that header alone
  // and the data sets are equal byte for byte.
  EXPECT_EQ(DatasetHashes(by_web), DatasetHashes(by_get));
  EXPECT_NE(Hashes(by_web), Hashes(by_get));
}

TEST_F(OrthancPullTest, LimitsAndMissingSeries) {
  RetrieveOptions few;
  few.max_instances = 27;
  const fs::path out = Folder("limited");
  absl::StatusOr<RetrieveResult> r =
      Retrieve(web_, study_, series_, out.string(), few);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(r.status().message(), HasSubstr("more than 27 instances"));
  EXPECT_EQ(FileCount(out), 0u);  // refused before any download

  RetrieveOptions small;
  small.max_bytes = 3 << 20;  // about 6 of the 532 KiB slices
  r = Retrieve(web_, study_, series_, out.string(), small);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(r.status().message(), HasSubstr("larger than"));
  for (const auto& e : fs::directory_iterator(out)) {
    EXPECT_FALSE(absl::EndsWith(e.path().string(), ".part")) << e.path();
  }

  r = Retrieve(web_, study_, "1.2.3.4", Folder("none").string(), {});
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound) << r.status();
  EXPECT_THAT(r.status().message(), HasSubstr("peer web"));
  EXPECT_THAT(r.status().message(), ::testing::Not(HasSubstr(study_)));
}

// QIDO-RS lists what C-FIND lists, field for field.
TEST_F(OrthancPullTest, QidoFindEqualsCFind) {
  node::FindQuery query;
  query.modality = "CT";
  absl::StatusOr<node::FindResult> web = Find(web_, query, {});
  ASSERT_TRUE(web.ok()) << web.status();
  absl::StatusOr<node::FindResult> find = Find(dimse_, query, {});
  ASSERT_TRUE(find.ok()) << find.status();
  ASSERT_EQ(web->studies.size(), 1u);
  ASSERT_EQ(find->studies.size(), 1u);
  const node::FoundStudy& a = web->studies[0];
  const node::FoundStudy& b = find->studies[0];
  EXPECT_EQ(a.study_instance_uid, study_);
  EXPECT_EQ(a.study_instance_uid, b.study_instance_uid);
  EXPECT_EQ(a.patient_id, b.patient_id);
  EXPECT_EQ(a.study_date, b.study_date);
  EXPECT_EQ(a.accession_number, b.accession_number);
  EXPECT_EQ(a.study_description, b.study_description);
  EXPECT_EQ(a.modalities, b.modalities);
  ASSERT_EQ(a.series.size(), 1u);
  ASSERT_EQ(b.series.size(), 1u);
  EXPECT_EQ(a.series[0].series_instance_uid, series_);
  EXPECT_EQ(a.series[0].series_instance_uid, b.series[0].series_instance_uid);
  EXPECT_EQ(a.series[0].modality, b.series[0].modality);
  EXPECT_EQ(a.series[0].series_number, b.series[0].series_number);
  EXPECT_EQ(a.series[0].series_description, b.series[0].series_description);
  EXPECT_EQ(a.series[0].instances, 28);
  EXPECT_EQ(a.series[0].instances, b.series[0].instances);
  EXPECT_FALSE(web->truncated);

  // A key that matches nothing, and the caps.
  query.modality = "MR";
  web = Find(web_, query, {});
  ASSERT_TRUE(web.ok()) << web.status();
  EXPECT_TRUE(web->studies.empty());
  query.modality = "";
  node::FindLimits capped;
  capped.max_series = 0;
  web = Find(web_, query, capped);
  ASSERT_TRUE(web.ok()) << web.status();
  EXPECT_TRUE(web->truncated);
}

TEST(DicomWebPullAuthTest, WrongCredentialsNameAuthentication) {
  testing::TempDir dir("interslice_dicomweb_pull_auth_");
  auto orthanc =
      Orthanc::Start(dir.str(), {}, "ORTHANC",
                     {.dicomweb = true, .users = {{"alice", "right-pw"}}});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  DicomPeer peer = WebPeer((*orthanc)->dicomweb_url());  // no credentials
  absl::StatusOr<RetrieveResult> r =
      Retrieve(peer, "1.2", "3.4", dir.str(), {});
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(r.status().message(), HasSubstr("HTTP 401"));
  absl::StatusOr<node::FindResult> f = Find(peer, {}, {});
  EXPECT_EQ(f.status().code(), absl::StatusCode::kPermissionDenied);
}

// A canned peer: a QIDO answer listing `listed` instances, then `wado` as
// the WADO-RS answer (raw HTTP).
class CannedPeer {
 public:
  CannedPeer(int listed, std::string wado)
      : server_([this, listed, wado](const CannedRequest& r) {
          if (absl::StrContains(r.target, "/instances")) {
            std::string json = "[";
            for (int i = 0; i < listed; ++i) {
              absl::StrAppend(&json, i ? "," : "",
                              R"({"00080018":{"vr":"UI","Value":["1.2.)", i,
                              R"("]}})");
            }
            return CannedHttp::Response(200, "application/dicom+json",
                                        json + "]");
          }
          return wado;
        }) {}
  DicomPeer peer() { return WebPeer(server_.url("/dw")); }
  CannedHttp& server() { return server_; }

 private:
  CannedHttp server_;
};

std::string Multipart(const std::vector<std::string>& parts, bool close = true,
                      const std::string& part_headers = "") {
  std::string body;
  for (const std::string& p : parts) {
    absl::StrAppend(&body, "--b0und\r\nContent-Type: application/dicom\r\n",
                    part_headers, "\r\n", p, "\r\n");
  }
  if (close) body += "--b0und--\r\n";
  return body;
}

std::string WadoResponse(const std::string& body) {
  return CannedHttp::Response(
      200, "multipart/related; type=\"application/dicom\"; boundary=b0und",
      body);
}

struct PullCase {
  std::string name;
  int listed;
  std::string wado;
  RetrieveOptions options;
  absl::StatusCode code;
  std::string message;
};

TEST(DicomWebPullTest, LyingOrBrokenAnswersFailCleanly) {
  const std::string a = testing::ReadFileOrEmpty((kThick / "I10.dcm").string());
  const std::string b = testing::ReadFileOrEmpty((kThick / "I20.dcm").string());
  ASSERT_FALSE(a.empty());
  ASSERT_FALSE(b.empty());
  RetrieveOptions defaults;
  RetrieveOptions two;
  two.max_instances = 2;
  RetrieveOptions tight;
  tight.max_bytes = static_cast<int64_t>(a.size()) + 100;
  const std::vector<PullCase> cases = {
      {"truncated part", 2,
       WadoResponse(Multipart({a}, /*close=*/false) + "--b0und\r\n\r\n" +
                    b.substr(0, 1000)),
       defaults, absl::StatusCode::kInvalidArgument, "truncated"},
      {"body shorter than its HTTP Content-Length", 2,
       WadoResponse(Multipart({a, b})).substr(0, 2000), defaults,
       absl::StatusCode::kUnavailable, "cannot reach peer web"},
      {"oversize part", 2, WadoResponse(Multipart({a, b})), tight,
       absl::StatusCode::kResourceExhausted, "larger than"},
      {"part longer than its Content-Length", 1,
       WadoResponse(Multipart({a}, true, "Content-Length: 500\r\n")), defaults,
       absl::StatusCode::kInvalidArgument, "longer than its Content-Length"},
      {"part announcing more than the limit", 1,
       WadoResponse(Multipart({a}, true, "Content-Length: 99999999999999\r\n")),
       defaults, absl::StatusCode::kResourceExhausted, "announces"},
      {"more parts than listed", 1, WadoResponse(Multipart({a, b})), defaults,
       absl::StatusCode::kFailedPrecondition, "more instances than"},
      {"fewer parts than listed", 3, WadoResponse(Multipart({a, b})), defaults,
       absl::StatusCode::kFailedPrecondition, "sent 2 of the 3"},
      {"QIDO listing more than the limit", 5, WadoResponse(Multipart({a})), two,
       absl::StatusCode::kResourceExhausted, "more than 2 instances"},
      {"a part that is not DICOM", 1,
       WadoResponse(Multipart({std::string(200, 'x')})), defaults,
       absl::StatusCode::kInvalidArgument, "refused"},
      {"HTML instead of multipart", 1,
       CannedHttp::Response(200, "text/html", "<html>hello</html>"), defaults,
       absl::StatusCode::kFailedPrecondition, "not multipart/related"},
      {"an HTML page of 2 MiB", 1,
       CannedHttp::Response(200, "text/html", std::string(2 << 20, 'h')),
       defaults, absl::StatusCode::kFailedPrecondition,
       "not multipart/related"},
      {"server error", 1, CannedHttp::Response(500, "text/plain", "oops"),
       defaults, absl::StatusCode::kUnavailable, "HTTP 500"},
  };
  for (const PullCase& c : cases) {
    SCOPED_TRACE(c.name);
    testing::TempDir dir("interslice_dicomweb_canned_");
    CannedPeer peer(c.listed, c.wado);
    absl::StatusOr<RetrieveResult> r =
        Retrieve(peer.peer(), "1.2", "3.4", dir.str(), c.options);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.status().code(), c.code) << r.status();
    EXPECT_THAT(r.status().message(), HasSubstr(c.message));
    EXPECT_EQ(r.status().message().find('\n'), absl::string_view::npos);
    for (const auto& e : fs::directory_iterator(dir.path())) {
      EXPECT_FALSE(absl::EndsWith(e.path().string(), ".part")) << e.path();
    }
    if (c.code == absl::StatusCode::kResourceExhausted && c.listed > 2) {
      // Refused on the QIDO answer: no WADO-RS request at all.
      EXPECT_EQ(peer.server().requests().size(), 1u);
    }
  }
  // The well-formed answer passes (the cases above fail for their fault).
  testing::TempDir dir("interslice_dicomweb_canned_ok_");
  CannedPeer good(2, WadoResponse(Multipart({a, b})));
  absl::StatusOr<RetrieveResult> r =
      Retrieve(good.peer(), "1.2", "3.4", dir.str(), {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->instances, 2);
  std::vector<std::string> sent = {Sha256Hex(a), Sha256Hex(b)};
  std::sort(sent.begin(), sent.end());
  EXPECT_EQ(Hashes(dir.path()), sent);
  ASSERT_EQ(good.server().requests().size(), 2u);
  EXPECT_THAT(good.server().requests()[0].target,
              HasSubstr("/dw/studies/1.2/series/3.4/instances?limit="));
  EXPECT_EQ(good.server().requests()[1].target, "/dw/studies/1.2/series/3.4");
  EXPECT_THAT(good.server().requests()[1].head, HasSubstr("transfer-syntax=*"));
}

}  // namespace
}  // namespace interslice::server::dicomweb
