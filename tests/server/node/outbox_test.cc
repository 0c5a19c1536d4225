// The outbox against a real Orthanc: C-STORE of files, sending twice,
// a peer that is down and comes back, giving up, unknown peer names.
#include "server/node/outbox.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/net/dimse/dimse_peer.h"
#include "server/node/peer_registry.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"

namespace interslice::server::node {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using testing::Orthanc;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
const fs::path kPhantom = fs::path(::interslice::testing::SourceDir()) /
                          "data" / "ct-head-phantom-thick";
// Enhanced MR Image Storage (a SOP class the CT-only receiver refuses).
const fs::path kEnhancedMr = fs::path(::interslice::testing::TestDataDir()) /
                             "multiframe" / "philips-enhanced-mr-64frames.dcm";

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

// The DIMSE client's settings: 5 s timeouts.
PeerClientSettings FastOptions() {
  PeerClientSettings settings;
  settings.store_timeout_seconds = 5;
  return settings;
}

// The outbox's retries: quick.
DeliveryOptions FastRetries() {
  DeliveryOptions options;
  options.initial_backoff = std::chrono::milliseconds(200);
  options.max_backoff = std::chrono::milliseconds(400);
  return options;
}

// C-STORE through the peer's client, as the outbox sends.
absl::StatusOr<StoreResult> StoreFiles(const DicomPeer& peer,
                                       const std::vector<std::string>& files,
                                       const PeerClientSettings& settings) {
  return dimse::DimsePeerClient(peer, settings).Store(files);
}

// The outbox over a registry of the peers' DIMSE clients, as the server
// wires it (server/app/server.cc).
struct Outbox {
  Outbox(std::vector<DicomPeer> peers, DeliveryOptions retries,
         DeliveryQueue::OnUpdate on_update,
         PeerClientSettings settings = FastOptions())
      : registry(
            [settings](const DicomPeer& peer) {
              return std::make_unique<dimse::DimsePeerClient>(peer, settings);
            },
            PeersConfig{std::move(peers), false}),
        queue(&registry, retries, std::move(on_update)) {}
  PeerRegistry registry;
  DeliveryQueue queue;
};

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

// Outgoing TLS (server/net/dimse/tls.h) against DCMTK's own storescp +tls,
// which requires our certificate signed by the test CA; a CA that did not sign
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
  PeerClientSettings options = FastOptions();
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
  Outbox outbox({PeerOf(**orthanc)}, FastRetries(), updates.callback());
  DeliveryQueue& queue = outbox.queue;
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
  DeliveryOptions options = FastRetries();
  options.give_up_after = std::chrono::milliseconds(0);
  Updates updates;
  Outbox outbox({peer}, options, updates.callback());
  DeliveryQueue& queue = outbox.queue;
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
  PeerClientSettings settings = FastOptions();
  settings.store_timeout_seconds = 20;
  Updates updates;
  Outbox outbox({peer}, FastRetries(), updates.callback(), settings);
  DeliveryQueue& queue = outbox.queue;
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

// A TCP listener on loopback that accepts and never answers (a PACS that
// hangs): counts the associations a StoreFiles call opens at once.
class SilentPeer {
 public:
  SilentPeer() {
    fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof(addr));
    ::listen(fd_, 32);
    socklen_t len = sizeof(addr);
    ::getsockname(fd_, reinterpret_cast<sockaddr*>(&addr), &len);
    port_ = ntohs(addr.sin_port);
  }
  ~SilentPeer() {
    CloseConnections();
    ::close(fd_);
  }
  int port() const { return port_; }
  // Accepts what is waiting; the connections accepted so far.
  int Accept() {
    int fd;
    while ((fd = ::accept4(fd_, nullptr, nullptr, SOCK_CLOEXEC)) >= 0) {
      connections_.push_back(fd);
    }
    return static_cast<int>(connections_.size());
  }
  // Whether every accepted connection is still open and has sent bytes
  // (its A-ASSOCIATE-RQ): all of them in flight at once.
  bool AllOpenWithARequest() const {
    for (const int fd : connections_) {
      char byte;
      if (::recv(fd, &byte, 1, MSG_PEEK | MSG_DONTWAIT) != 1) return false;
    }
    return true;
  }
  void CloseConnections() {
    for (const int fd : connections_) ::close(fd);
    connections_.clear();
  }

 private:
  int fd_ = -1;
  int port_ = 0;
  std::vector<int> connections_;
};

// Issue 25: a delivery sends over max_associations associations at once,
// never more; 1 keeps the former one-at-a-time behaviour.
class MaxAssociationsTest : public ::testing::TestWithParam<int> {};

TEST_P(MaxAssociationsTest, OpensThatManyAssociationsAtOnce) {
  const int max_associations = GetParam();
  SilentPeer silent;
  DicomPeer peer;
  peer.name = "silent";
  peer.ae_title = "SILENT";
  peer.host = "127.0.0.1";
  peer.port = silent.port();
  peer.max_associations = max_associations;
  PeerClientSettings options = FastOptions();
  // The test ends the associations itself.
  options.store_timeout_seconds = 60;
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(kPhantom)) {
    if (e.path().extension() == ".dcm") files.push_back(e.path().string());
  }
  ASSERT_EQ(files.size(), 28u);
  absl::StatusOr<StoreResult> result = StoreResult{};
  std::thread sender([&] { result = StoreFiles(peer, files, options); });
  // Every lane connects and sends its request; none gets an answer.
  const bool all_in_flight = testing::WaitFor(
      [&] {
        return silent.Accept() >= max_associations &&
               silent.AllOpenWithARequest();
      },
      std::chrono::seconds(60));
  EXPECT_TRUE(all_in_flight);
  EXPECT_EQ(silent.Accept(), max_associations);
  silent.CloseConnections();  // every lane fails now
  sender.join();
  EXPECT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(result.status().message(), HasSubstr("silent"));
  // Each lane tried once: no association beyond the limit, ever.
  EXPECT_EQ(silent.Accept(), 0);
}

INSTANTIATE_TEST_SUITE_P(OneAndSeveral, MaxAssociationsTest,
                         ::testing::Values(1, 3));

// The SOP Instance UIDs of every instance Orthanc holds.
std::multiset<std::string> OrthancSopInstanceUids(const Orthanc& orthanc) {
  std::multiset<std::string> uids;
  absl::StatusOr<nlohmann::json> all = orthanc.GetJson("/instances?expand");
  EXPECT_TRUE(all.ok()) << all.status();
  if (!all.ok()) return uids;
  for (const nlohmann::json& i : *all) {
    uids.insert(i["MainDicomTags"]["SOPInstanceUID"].get<std::string>());
  }
  return uids;
}

TEST(StoreFilesTest, FourAssociationsStoreEveryInstanceOnceInOrthanc) {
  testing::TempDir dir("interslice_orthanc_");
  auto orthanc = Orthanc::Start(dir.str(), {});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  std::vector<std::string> files = ListDicomFiles(kPhantom.string());
  ASSERT_EQ(files.size(), 28u);
  DicomPeer peer = PeerOf(**orthanc);
  peer.max_associations = 4;
  absl::StatusOr<StoreResult> sent = StoreFiles(peer, files, FastOptions());
  ASSERT_TRUE(sent.ok()) << sent.status();
  EXPECT_EQ(sent->accepted, 28);
  EXPECT_EQ(sent->refused, 0);
  // Each instance once, none missing: Orthanc's UIDs are the files' UIDs.
  std::multiset<std::string> expected;
  for (const std::string& f : files) {
    const testing::CommandResult uid =
        testing::RunCommand({"/usr/bin/dcmdump", "+P", "0008,0018", f}, 60);
    const size_t open = uid.out.find('['), close = uid.out.find(']');
    ASSERT_NE(open, std::string::npos) << uid.out;
    expected.insert(uid.out.substr(open + 1, close - open - 1));
  }
  EXPECT_EQ(OrthancSopInstanceUids(**orthanc), expected);
  // Sent again over four: still one copy each (fixed UIDs, Orthanc replaces).
  sent = StoreFiles(peer, files, FastOptions());
  ASSERT_TRUE(sent.ok()) << sent.status();
  EXPECT_EQ(sent->accepted, 28);
  EXPECT_EQ(OrthancSopInstanceUids(**orthanc), expected);
}

// A receiver that takes CT but not Enhanced MR (DCMTK's storescp with an
// association profile): over four associations the refusal is counted once,
// the rest stored, and the outbox keeps the delivery PENDING with the
// peer's reason, as with one association.
TEST(DeliveryQueueTest, PeerRefusingSomeInstancesOverFourAssociations) {
  testing::TempDir dir("interslice_store_refuse_");
  const std::string d = dir.str();
  std::ofstream(d + "/ct-only.cfg")
      << "[[TransferSyntaxes]]\n[Uncompressed]\n"
         "TransferSyntax1 = LocalEndianExplicit\n"
         "TransferSyntax2 = OppositeEndianExplicit\n"
         "TransferSyntax3 = LittleEndianImplicit\n"
         "[[PresentationContexts]]\n[CtOnly]\n"
         "PresentationContext1 = CTImageStorage\\Uncompressed\n"
         "[[Profiles]]\n[CtOnly]\nPresentationContexts = CtOnly\n";
  const int port = testing::FreeTcpPort();
  fs::create_directories(dir.path() / "received");
  // --fork: an association each (storescp alone serves one at a time).
  const pid_t scp = testing::StartProcess(
      {"/usr/bin/storescp", "--fork", "-xf", d + "/ct-only.cfg", "CtOnly",
       "-od", d + "/received", std::to_string(port)},
      d + "/storescp.log");
  ASSERT_TRUE(testing::WaitFor([&] { return Listening(port); },
                               std::chrono::seconds(60)))
      << testing::ReadFileOrEmpty(d + "/storescp.log");
  DicomPeer peer;
  peer.name = "ctonly";
  peer.ae_title = "STORESCP";
  peer.host = "127.0.0.1";
  peer.port = port;
  peer.max_associations = 4;
  std::vector<std::string> files = ListDicomFiles(kThick.string());
  files.push_back(kEnhancedMr.string());
  absl::StatusOr<StoreResult> result = StoreFiles(peer, files, FastOptions());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 4);
  EXPECT_EQ(result->refused, 1);
  EXPECT_THAT(result->first_refusal, HasSubstr("presentation context"));
  // storescp's children write as they receive: wait for the four.
  auto received = [&] {
    int n = 0;
    std::error_code ec;
    for (const auto& e : fs::directory_iterator(dir.path() / "received", ec)) {
      n += e.is_regular_file() ? 1 : 0;
    }
    return n;
  };
  EXPECT_TRUE(testing::WaitFor([&] { return received() == 4; },
                               std::chrono::seconds(30)));
  EXPECT_EQ(received(), 4);

  Updates updates;
  Outbox outbox({peer}, FastRetries(), updates.callback());
  DeliveryQueue& queue = outbox.queue;
  queue.Start();
  v1::Delivery delivery;
  delivery.set_peer("ctonly");
  queue.Add("job4", delivery, files,
            std::chrono::duration_cast<std::chrono::milliseconds>(
                std::chrono::system_clock::now().time_since_epoch())
                .count());
  ASSERT_TRUE(testing::WaitFor(
      [&] {
        for (const v1::Delivery& u : updates.all()) {
          if (!u.last_error().empty()) return true;
        }
        return false;
      },
      std::chrono::seconds(60)));
  queue.Stop();
  v1::Delivery failed;
  for (const v1::Delivery& u : updates.all()) {
    if (!u.last_error().empty()) failed = u;
  }
  EXPECT_EQ(failed.state(), v1::Delivery::PENDING);  // retried later
  EXPECT_EQ(failed.instances_total(), 5);
  EXPECT_EQ(failed.instances_sent(), 4);
  EXPECT_THAT(failed.last_error(), HasSubstr("1 of 5 instance(s) refused"));
  testing::StopProcess(scp, 30);
}

TEST(DeliveryQueueTest, UnknownPeerNamesAreInvalidArgument) {
  DicomPeer peer;
  peer.name = "pacs";
  Outbox outbox({peer}, FastRetries(), [](auto&, auto&) {});
  DeliveryQueue& queue = outbox.queue;
  EXPECT_TRUE(queue.CheckPeers({"pacs"}).ok());
  const absl::Status s = queue.CheckPeers({"pacs", "elsewhere"});
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(s.message(), HasSubstr("\"elsewhere\""));
  EXPECT_THAT(s.message(), HasSubstr("pacs"));
}

}  // namespace
}  // namespace interslice::server::node
