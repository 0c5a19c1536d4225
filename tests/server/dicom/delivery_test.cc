// The outbox against a real Orthanc: C-STORE of files, sending twice,
// a peer that is down and comes back, giving up, unknown peer names.
#include "server/dicom/delivery.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"

namespace interslice::server::dicom {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using testing::Orthanc;

const fs::path kThick = fs::path(INTERSLICE_TEST_DATA_DIR) / "ct-thick";

DicomPeer PeerOf(const Orthanc& orthanc) {
  DicomPeer peer;
  peer.name = "orthanc";
  peer.ae_title = orthanc.ae_title();
  peer.host = "127.0.0.1";
  peer.port = orthanc.dicom_port();
  return peer;
}

int InstanceCount(const Orthanc& orthanc) {
  absl::StatusOr<nlohmann::json> ids = orthanc.GetJson("/instances");
  EXPECT_TRUE(ids.ok()) << ids.status();
  return ids.ok() ? static_cast<int>(ids->size()) : -1;
}

DeliveryOptions FastOptions() {
  DeliveryOptions options;
  options.initial_backoff = std::chrono::milliseconds(200);
  options.max_backoff = std::chrono::milliseconds(400);
  options.timeout_seconds = 5;
  return options;
}

// Records the outbox's updates.
class Updates {
 public:
  DeliveryQueue::OnUpdate callback() {
    return [this](const std::string& job, const v1::Delivery& d) {
      std::lock_guard<std::mutex> lock(mu_);
      jobs_.push_back(job);
      updates_.push_back(d);
      cv_.notify_all();
    };
  }
  // Waits for an update in `state`; the last such update.
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
  std::vector<std::string> jobs_;
  std::vector<v1::Delivery> updates_;
};

TEST(StoreFilesTest, StoresEveryInstanceAndSendingTwiceKeepsOneCopy) {
  testing::TempDir dir("interslice_orthanc_");
  auto orthanc = Orthanc::Start(dir.str(), {});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  const std::vector<std::string> files = ListDicomFiles(kThick.string());
  ASSERT_EQ(files.size(), 4u);  // the LICENSE file is not DICOM

  absl::StatusOr<StoreResult> first =
      StoreFiles(PeerOf(**orthanc), files, FastOptions());
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->accepted, 4);
  EXPECT_EQ(first->refused, 0);
  EXPECT_EQ(InstanceCount(**orthanc), 4);

  absl::StatusOr<StoreResult> again =
      StoreFiles(PeerOf(**orthanc), files, FastOptions());
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->accepted, 4);
  EXPECT_EQ(InstanceCount(**orthanc), 4);  // same SOP Instance UIDs
}

TEST(StoreFilesTest, PeerDownIsUnavailableNamingThePeer) {
  DicomPeer peer;
  peer.name = "nowhere";
  peer.ae_title = "NOWHERE";
  peer.host = "127.0.0.1";
  peer.port = testing::FreeTcpPort();
  absl::StatusOr<StoreResult> result =
      StoreFiles(peer, ListDicomFiles(kThick.string()), FastOptions());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(result.status().message(), HasSubstr("nowhere"));
}

TEST(StoreFilesTest, UnreadableFileIsInvalidArgument) {
  testing::TempDir dir("interslice_store_");
  DicomPeer peer;
  peer.name = "p";
  peer.ae_title = "P";
  peer.host = "127.0.0.1";
  peer.port = testing::FreeTcpPort();
  absl::StatusOr<StoreResult> result =
      StoreFiles(peer, {(dir.path() / "missing.dcm").string()}, FastOptions());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(), HasSubstr("missing.dcm"));
}

bool Listening(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  addr.sin_port = htons(static_cast<uint16_t>(port));
  const bool ok =
      ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0;
  ::close(fd);
  return ok;
}

// Outgoing TLS (server/dicom/tls.h) against DCMTK's own storescp +tls, which
// requires our certificate signed by the test CA; a CA that did not sign
// the peer's certificate makes the handshake fail.
TEST(StoreFilesTest, TlsPeerWithCaCheckedCertificates) {
  testing::TempDir dir("interslice_store_tls_");
  const std::string d = dir.str();
  const testing::CommandResult certs = testing::RunCommand(
      {"/bin/sh", "-c",
       "set -e; cd '" + d +
           "'; "
           "openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=ca "
           "-keyout ca.key -out ca.pem; "
           "for who in pacs interslice; do "
           "openssl req -newkey rsa:2048 -nodes -subj /CN=$who -keyout "
           "$who.key -out $who.csr; "
           "openssl x509 -req -in $who.csr -CA ca.pem -CAkey ca.key "
           "-CAcreateserial -days 1 -out $who.pem; done; "
           "openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj "
           "/CN=rogue -keyout rogue.key -out rogue.pem"},
      120);
  ASSERT_EQ(certs.exit_code, 0) << certs.err;
  const int port = testing::FreeTcpPort();
  fs::create_directories(dir.path() / "received");
  const pid_t scp = testing::StartProcess(
      {"/usr/bin/storescp", "+tls", d + "/pacs.key", d + "/pacs.pem", "+cf",
       d + "/ca.pem", "-rc", "-od", d + "/received", std::to_string(port)},
      d + "/storescp.log");
  ASSERT_TRUE(testing::WaitFor([&] { return Listening(port); },
                               std::chrono::seconds(60)))
      << testing::ReadFileOrEmpty(d + "/storescp.log");
  DicomPeer peer;
  peer.name = "secure";
  peer.ae_title = "STORESCP";
  peer.host = "127.0.0.1";
  peer.port = port;
  peer.tls = true;
  DeliveryOptions options = FastOptions();
  options.tls = {d + "/interslice.pem", d + "/interslice.key", d + "/ca.pem"};
  const std::vector<std::string> files = ListDicomFiles(kThick.string());
  absl::StatusOr<StoreResult> result = StoreFiles(peer, files, options);
  EXPECT_TRUE(result.ok()) << result.status()
                           << testing::ReadFileOrEmpty(d + "/storescp.log");
  if (result.ok()) EXPECT_EQ(result->accepted, 4);
  int received = 0;
  for (const auto& e : fs::directory_iterator(dir.path() / "received")) {
    received += e.is_regular_file() ? 1 : 0;
  }
  EXPECT_EQ(received, 4);

  // Trusting only a CA that did not sign the peer: no association.
  options.tls.ca_certificates = d + "/rogue.pem";
  absl::StatusOr<StoreResult> refused = StoreFiles(peer, files, options);
  EXPECT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kUnavailable);
  testing::StopProcess(scp, 30);
}

TEST(DeliveryQueueTest, PeerDownThenBackIsDeliveredWithBackoff) {
  testing::TempDir dir("interslice_orthanc_");
  auto orthanc = Orthanc::Start(dir.str(), {});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  (*orthanc)->Stop();

  Updates updates;
  DeliveryQueue queue({PeerOf(**orthanc)}, FastOptions(), updates.callback());
  queue.Start();
  v1::Delivery d;
  d.set_peer("orthanc");
  d.set_state(v1::Delivery::PENDING);
  const auto t0 = std::chrono::system_clock::now();
  queue.Add("job1", d, ListDicomFiles(kThick.string()),
            std::chrono::duration_cast<std::chrono::milliseconds>(
                t0.time_since_epoch())
                .count());
  // Two failed tries while the peer is down, each with the error and a
  // next attempt in the future (each try is also reported as it begins,
  // without an error yet the first time).
  auto failed_tries = [&] {
    std::vector<v1::Delivery> failures;
    for (const v1::Delivery& u : updates.all()) {
      if (!u.last_error().empty() && u.next_attempt_unix_ms() > 0 &&
          (failures.empty() || u.attempts() > failures.back().attempts())) {
        failures.push_back(u);
      }
    }
    return failures;
  };
  testing::WaitFor([&] { return failed_tries().size() >= 2; },
                   std::chrono::seconds(60));
  const std::vector<v1::Delivery> failures = failed_tries();
  ASSERT_GE(failures.size(), 2u);
  EXPECT_EQ(updates.all().front().attempts(), 1);
  EXPECT_EQ(updates.all().front().last_error(), "");
  for (const v1::Delivery& f : failures) {
    EXPECT_EQ(f.state(), v1::Delivery::PENDING);
    EXPECT_THAT(f.last_error(), HasSubstr("orthanc"));
    EXPECT_GT(f.next_attempt_unix_ms(), 0);
    EXPECT_EQ(f.instances_total(), 4);
  }
  EXPECT_EQ(failures[0].attempts(), 1);
  EXPECT_EQ(failures[1].attempts(), 2);
  EXPECT_EQ(queue.pending(), 1);

  ASSERT_TRUE((*orthanc)->Restart().ok());
  std::optional<v1::Delivery> done =
      updates.WaitFor(v1::Delivery::DELIVERED, std::chrono::seconds(120));
  ASSERT_TRUE(done.has_value());
  EXPECT_EQ(done->instances_sent(), 4);
  EXPECT_EQ(done->last_error(), "");
  EXPECT_GE(done->attempts(), 3);
  EXPECT_EQ(InstanceCount(**orthanc), 4);
  EXPECT_EQ(queue.pending(), 0);
}

TEST(DeliveryQueueTest, GivesUpAfterTheConfiguredTime) {
  DicomPeer peer;
  peer.name = "down";
  peer.ae_title = "DOWN";
  peer.host = "127.0.0.1";
  peer.port = testing::FreeTcpPort();
  DeliveryOptions options = FastOptions();
  options.give_up_after = std::chrono::milliseconds(0);
  Updates updates;
  DeliveryQueue queue({peer}, options, updates.callback());
  queue.Start();
  v1::Delivery d;
  d.set_peer("down");
  queue.Add("job2", d, ListDicomFiles(kThick.string()), 0);
  std::optional<v1::Delivery> failed =
      updates.WaitFor(v1::Delivery::FAILED, std::chrono::seconds(120));
  ASSERT_TRUE(failed.has_value());
  EXPECT_EQ(failed->attempts(), 1);
  EXPECT_THAT(failed->last_error(), HasSubstr("down"));
  EXPECT_EQ(queue.pending(), 0);
}

// Issue 22: a delivery cut by a kill -9 reported "1 attempt(s)" after any
// number of tries, because the count was stored only after a try ended.
// The attempt is recorded before it is made: here the peer accepts the TCP
// connection and never answers, and the record says attempt 1 while the
// try still hangs.
TEST(DeliveryQueueTest, AttemptIsRecordedBeforeItIsMade) {
  const int listener = ::socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(listener, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::bind(listener, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)),
            0);
  ASSERT_EQ(::listen(listener, 4), 0);  // the kernel accepts; nobody reads
  socklen_t len = sizeof(addr);
  ::getsockname(listener, reinterpret_cast<sockaddr*>(&addr), &len);
  DicomPeer peer;
  peer.name = "silent";
  peer.ae_title = "SILENT";
  peer.host = "127.0.0.1";
  peer.port = ntohs(addr.sin_port);
  DeliveryOptions options = FastOptions();
  options.timeout_seconds = 20;
  Updates updates;
  DeliveryQueue queue({peer}, options, updates.callback());
  queue.Start();
  v1::Delivery d;
  d.set_peer("silent");
  d.set_state(v1::Delivery::PENDING);
  queue.Add("job3", d, ListDicomFiles(kThick.string()), 0);
  std::optional<v1::Delivery> started =
      updates.WaitFor(v1::Delivery::PENDING, std::chrono::seconds(15));
  ASSERT_TRUE(started.has_value());
  EXPECT_EQ(started->attempts(), 1);
  // Recorded as the try began, not after it failed.
  EXPECT_EQ(started->last_error(), "");
  ::close(listener);  // the try now fails at once
  queue.Stop();
}

TEST(DeliveryQueueTest, UnknownPeerNamesAreInvalidArgument) {
  DicomPeer peer;
  peer.name = "pacs";
  DeliveryQueue queue({peer}, FastOptions(), [](auto&, auto&) {});
  EXPECT_TRUE(queue.CheckPeers({"pacs"}).ok());
  const absl::Status s = queue.CheckPeers({"pacs", "elsewhere"});
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("\"elsewhere\""));
  EXPECT_THAT(s.message(), HasSubstr("pacs"));
}

}  // namespace
}  // namespace interslice::server::dicom
