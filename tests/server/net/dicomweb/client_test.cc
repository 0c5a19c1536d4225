// The DICOMweb client (server/net/dicomweb/client.h) against Debian's Orthanc
// with its DICOMweb plugin: STOW-RS delivery (every byte arrives, refusals
// counted, credentials, the queue's retries), and against canned answers for
// what Orthanc does not do (an HTML page where DICOM JSON belongs).
#include "server/net/dicomweb/client.h"

#include <sys/stat.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/net/dicomweb/dicomweb_peer.h"
#include "server/node/outbox.h"
#include "server/node/peer_registry.h"
#include "tests/testing/canned_http.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dctk.h"

namespace interslice::server::dicomweb {
namespace {

namespace fs = std::filesystem;
using node::DicomPeer;
using node::StoreResult;
using testing::CannedHttp;
using ::testing::HasSubstr;
using ::testing::Not;
using testing::Orthanc;
using testing::OrthancExtras;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
const fs::path kEnhancedMr = fs::path(::interslice::testing::TestDataDir()) /
                             "multiframe" / "philips-enhanced-mr-64frames.dcm";

DicomPeer WebPeer(const std::string& url) {
  DicomPeer peer;
  peer.name = "web";
  peer.type = node::PeerType::kDicomWeb;
  peer.web.url = url;
  peer.max_associations = 2;
  return peer;
}

// The client's settings: 10 s timeouts.
node::PeerClientSettings FastOptions() {
  node::PeerClientSettings settings;
  settings.store_timeout_seconds = 10;
  settings.echo_timeout_seconds = 10;
  return settings;
}

// The outbox's retries: quick.
node::DeliveryOptions FastRetries() {
  node::DeliveryOptions options;
  options.initial_backoff = std::chrono::milliseconds(200);
  options.max_backoff = std::chrono::milliseconds(400);
  return options;
}

// STOW-RS through the peer's client, as the outbox sends.
absl::StatusOr<StoreResult> Store(const DicomPeer& peer,
                                  const std::vector<std::string>& files,
                                  const node::PeerClientSettings& settings) {
  return DicomWebPeerClient(peer, settings).Store(files);
}

// The QIDO-RS probe through the peer's client (Echo).
absl::Status Probe(const DicomPeer& peer) {
  return DicomWebPeerClient(peer, FastOptions()).Echo();
}

std::string Write(const fs::path& path, const std::string& text) {
  std::ofstream(path, std::ios::binary) << text;
  return path.string();
}

// Orthanc's instances' files (REST /instances/{id}/file), sorted.
std::vector<std::string> StoredFiles(const Orthanc& orthanc) {
  std::vector<std::string> files;
  absl::StatusOr<nlohmann::json> ids = orthanc.GetJson("/instances");
  EXPECT_TRUE(ids.ok()) << ids.status();
  if (!ids.ok()) return files;
  for (const auto& id : *ids) {
    absl::StatusOr<std::string> file =
        orthanc.InstanceFile(id.get<std::string>());
    EXPECT_TRUE(file.ok()) << file.status();
    if (file.ok()) files.push_back(*file);
  }
  std::sort(files.begin(), files.end());
  return files;
}

std::vector<std::string> Contents(const std::vector<std::string>& paths) {
  std::vector<std::string> out;
  for (const std::string& p : paths) {
    out.push_back(testing::ReadFileOrEmpty(p));
  }
  std::sort(out.begin(), out.end());
  return out;
}

// A copy of `from` whose Series Description is `description`.
std::string WithSeriesDescription(const std::string& from, const fs::path& to,
                                  const std::string& description) {
  DcmFileFormat file;
  EXPECT_TRUE(file.loadFile(from.c_str()).good());
  EXPECT_TRUE(
      file.getDataset()
          ->putAndInsertString(DCM_SeriesDescription, description.c_str())
          .good());
  EXPECT_TRUE(file.saveFile(to.c_str(), EXS_LittleEndianExplicit).good());
  return to.string();
}

// Every file of the small series and a 64-frame Enhanced MR, split into
// several requests sent two at a time, arrives in Orthanc byte for byte;
// sending again keeps one copy.
TEST(StowTest, StoresEveryInstanceByteForByte) {
  testing::TempDir dir("interslice_stow_");
  auto orthanc = Orthanc::Start(dir.str(), {}, "ORTHANC", {.dicomweb = true});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  std::vector<std::string> files = node::ListDicomFiles(kThick.string());
  ASSERT_EQ(files.size(), 4u);
  files.push_back(kEnhancedMr.string());
  node::PeerClientSettings options = FastOptions();
  options.stow_max_instances = 2;  // 3 requests: 2, 2, 1
  const DicomPeer peer = WebPeer((*orthanc)->dicomweb_url());

  absl::StatusOr<StoreResult> result = Store(peer, files, options);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 5);
  EXPECT_EQ(result->refused, 0);
  EXPECT_EQ(result->first_refusal, "");
  EXPECT_EQ(StoredFiles(**orthanc), Contents(files));

  // Split by bytes instead: every file its own request.
  options.stow_max_instances = 50;
  options.stow_max_bytes = 1;
  absl::StatusOr<StoreResult> again = Store(peer, files, options);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->accepted, 5);
  EXPECT_EQ(StoredFiles(**orthanc), Contents(files));
}

// An instance the PACS does not store is counted as refused: Orthanc's
// plugin (1.7) leaves an instance whose storage failed out of both
// sequences, so it is "not confirmed" rather than silently accepted.
TEST(StowTest, RefusedInstanceIsCounted) {
  testing::TempDir dir("interslice_stow_refuse_");
  OrthancExtras extras{.dicomweb = true};
  extras.lua_script =
      "function ReceivedInstanceFilter(dicom, origin, info)\n"
      "  if dicom.SeriesDescription == 'REFUSE ME' then\n"
      "    error('refused by the test')\n"
      "  end\n"
      "  return true\n"
      "end\n";
  auto orthanc = Orthanc::Start(dir.str(), {}, "ORTHANC", extras);
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  std::vector<std::string> files = node::ListDicomFiles(kThick.string());
  ASSERT_EQ(files.size(), 4u);
  files[3] =
      WithSeriesDescription(files[3], dir.path() / "refused.dcm", "REFUSE ME");
  absl::StatusOr<StoreResult> result =
      Store(WebPeer((*orthanc)->dicomweb_url()), files, FastOptions());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 3);
  EXPECT_EQ(result->refused, 1);
  EXPECT_THAT(result->first_refusal, HasSubstr("not confirmed"));
  EXPECT_EQ(StoredFiles(**orthanc), Contents({files[0], files[1], files[2]}));
}

// The Failed SOP Sequence's Failure Reason is the first refusal's text, and
// a 409 (nothing stored) is counted, not an error.
TEST(StowTest, FailedSopSequenceGivesTheFailureReason) {
  const std::string json = R"({
    "00081198": {"vr": "SQ", "Value": [
      {"00081150": {"vr": "UI", "Value": ["1.2.840.10008.5.1.4.1.1.2"]},
       "00081155": {"vr": "UI", "Value": ["1.2.3"]},
       "00081197": {"vr": "US", "Value": [42752]}}]}})";
  CannedHttp server([&](const testing::CannedRequest&) {
    return CannedHttp::Response(409, "application/dicom+json", json);
  });
  absl::StatusOr<StoreResult> result =
      Store(WebPeer(server.url("/dw")), {(kThick / "I10.dcm").string()},
            FastOptions());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 0);
  EXPECT_EQ(result->refused, 1);
  EXPECT_THAT(result->first_refusal, HasSubstr("0xA700"));
  ASSERT_EQ(server.requests().size(), 1u);
  const testing::CannedRequest request = server.requests()[0];
  EXPECT_EQ(request.method, "POST");
  EXPECT_EQ(request.target, "/dw/studies");
  EXPECT_THAT(request.head,
              HasSubstr("multipart/related; type=\"application/dicom\""));
  EXPECT_THAT(request.head, HasSubstr("Accept: application/dicom+json"));
  // The part and its framing: more than the file, less than twice.
  const size_t file_size = fs::file_size(kThick / "I10.dcm");
  EXPECT_GT(request.body_bytes, file_size);
  EXPECT_LT(request.body_bytes, file_size + 300);
}

// A web page where the store response belongs (url points at something
// that is not a DICOMweb service) fails the try naming the peer; so do
// statuses outside 200/202/409.
TEST(StowTest, NonDicomWebAnswersFail) {
  CannedHttp html([](const testing::CannedRequest&) {
    return CannedHttp::Response(200, "text/html",
                                "<html><body>Welcome</body></html>");
  });
  const std::vector<std::string> one = {(kThick / "I10.dcm").string()};
  absl::StatusOr<StoreResult> result =
      Store(WebPeer(html.url()), one, FastOptions());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(result.status().message(), HasSubstr("peer web"));
  EXPECT_THAT(result.status().message(), HasSubstr("DICOMweb service"));
  absl::Status probe = Probe(WebPeer(html.url()));
  EXPECT_EQ(probe.code(), absl::StatusCode::kFailedPrecondition) << probe;

  CannedHttp failing([](const testing::CannedRequest&) {
    return CannedHttp::Response(503, "text/plain", "busy");
  });
  result = Store(WebPeer(failing.url()), one, FastOptions());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(result.status().message(), HasSubstr("HTTP 503"));
}

TEST(StowTest, UnreachableUrlIsUnavailableNamingThePeer) {
  const DicomPeer peer =
      WebPeer(absl::StrCat("http://127.0.0.1:", testing::FreeTcpPort(), "/dw"));
  absl::StatusOr<StoreResult> result =
      Store(peer, {(kThick / "I10.dcm").string()}, FastOptions());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(result.status().message(), HasSubstr("peer web ("));
  EXPECT_EQ(Probe(peer).code(), absl::StatusCode::kUnavailable);
}

TEST(StowTest, NotDicomIsInvalidArgumentBeforeSending) {
  testing::TempDir dir("interslice_stow_bad_");
  CannedHttp server([](const testing::CannedRequest&) {
    return CannedHttp::Response(200, "application/dicom+json", "{}");
  });
  absl::StatusOr<StoreResult> result = Store(
      WebPeer(server.url()),
      {(kThick / "I10.dcm").string(), Write(dir.path() / "x.dcm", "hello")},
      FastOptions());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(), HasSubstr("x.dcm"));
  EXPECT_TRUE(server.requests().empty());
}

// HTTP basic against Orthanc's registered users: a wrong password is a
// clear credentials error (never the password), the right one stores; the
// probe says the same.
TEST(StowTest, BasicAuthentication) {
  testing::TempDir dir("interslice_stow_auth_");
  auto orthanc =
      Orthanc::Start(dir.str(), {}, "ORTHANC",
                     {.dicomweb = true, .users = {{"alice", "right-pw"}}});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  DicomPeer peer = WebPeer((*orthanc)->dicomweb_url());
  peer.web.basic_user = "alice";
  peer.web.basic_password_file = Write(dir.path() / "pw", "wrong-pw\n");
  const std::vector<std::string> files = node::ListDicomFiles(kThick.string());
  absl::StatusOr<StoreResult> denied = Store(peer, files, FastOptions());
  ASSERT_FALSE(denied.ok());
  EXPECT_EQ(denied.status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(denied.status().message(), HasSubstr("HTTP 401"));
  EXPECT_THAT(denied.status().message(), HasSubstr("credentials"));
  EXPECT_THAT(denied.status().message(), Not(HasSubstr("wrong-pw")));
  EXPECT_EQ(Probe(peer).code(), absl::StatusCode::kPermissionDenied);

  // A rotated password file is read at the next request.
  Write(dir.path() / "pw", "right-pw\n");
  EXPECT_TRUE(Probe(peer).ok());
  absl::StatusOr<StoreResult> stored = Store(peer, files, FastOptions());
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_EQ(stored->accepted, 4);
  EXPECT_EQ(StoredFiles(**orthanc), Contents(files));
}

// Records the outbox's updates.
class Updates {
 public:
  node::DeliveryQueue::OnUpdate callback() {
    return [this](const std::string&, const v1::Delivery& d) {
      std::lock_guard<std::mutex> lock(mu_);
      updates_.push_back(d);
      cv_.notify_all();
    };
  }
  std::optional<v1::Delivery> WaitFor(v1::Delivery::State state,
                                      std::chrono::seconds timeout) {
    std::unique_lock<std::mutex> lock(mu_);
    std::optional<v1::Delivery> found;
    cv_.wait_for(lock, timeout, [&] {
      for (const v1::Delivery& d : updates_) {
        if (d.state() == state) found = d;
      }
      return found.has_value();
    });
    return found;
  }
  std::vector<v1::Delivery> all() {
    std::lock_guard<std::mutex> lock(mu_);
    return updates_;
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  std::vector<v1::Delivery> updates_;
};

// The persistent outbox with a DICOMweb peer: tries while Orthanc is down
// fail as UNAVAILABLE naming the peer and are retried; once it is back the
// delivery completes with every instance.
TEST(StowDeliveryQueueTest, PeerDownThenBackIsDelivered) {
  testing::TempDir dir("interslice_stow_queue_");
  auto orthanc = Orthanc::Start(dir.str(), {}, "ORTHANC", {.dicomweb = true});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  (*orthanc)->Stop();
  Updates updates;
  node::PeersConfig peers;
  peers.peers = {WebPeer((*orthanc)->dicomweb_url())};
  const node::PeerRegistry registry(
      [](const DicomPeer& peer) {
        return std::make_unique<DicomWebPeerClient>(peer, FastOptions());
      },
      peers);
  node::DeliveryQueue queue(&registry, FastRetries(), updates.callback());
  queue.Start();
  v1::Delivery d;
  d.set_peer("web");
  d.set_state(v1::Delivery::PENDING);
  const std::vector<std::string> files = node::ListDicomFiles(kThick.string());
  queue.Add("job1", d, files,
            std::chrono::duration_cast<std::chrono::milliseconds>(
                std::chrono::system_clock::now().time_since_epoch())
                .count());
  auto failures = [&] {
    int n = 0;
    for (const v1::Delivery& u : updates.all()) {
      if (!u.last_error().empty() && u.next_attempt_unix_ms() > 0) ++n;
    }
    return n;
  };
  ASSERT_TRUE(testing::WaitFor([&] { return failures() >= 2; },
                               std::chrono::seconds(60)));
  for (const v1::Delivery& u : updates.all()) {
    if (u.last_error().empty()) continue;
    EXPECT_EQ(u.state(), v1::Delivery::PENDING);
    EXPECT_THAT(u.last_error(), HasSubstr("cannot reach peer web"));
  }
  ASSERT_TRUE((*orthanc)->Restart().ok());
  std::optional<v1::Delivery> done =
      updates.WaitFor(v1::Delivery::DELIVERED, std::chrono::seconds(120));
  ASSERT_TRUE(done.has_value());
  EXPECT_EQ(done->instances_sent(), 4);
  EXPECT_GE(done->attempts(), 3);
  EXPECT_EQ(StoredFiles(**orthanc), Contents(files));
}

}  // namespace
}  // namespace interslice::server::dicomweb
