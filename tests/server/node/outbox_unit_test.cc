// The outbox and the peer registry in the test's process, with fake peers
// (tests/testing/fake_peer.h): retries, and what a reload of the peers does
// to a delivery still owed.
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/base/clock.h"
#include "server/node/outbox.h"
#include "server/node/peer_registry.h"
#include "tests/testing/fake_peer.h"
#include "tests/testing/wait_for.h"

namespace interslice::server::node {
namespace {

using testing::AsFake;
using ::testing::HasSubstr;
using ::testing::SizeIs;

DicomPeer Peer(const std::string& name, const std::string& host) {
  DicomPeer peer;
  peer.name = name;
  peer.ae_title = "PACS";
  peer.host = host;
  peer.port = 104;
  return peer;
}

PeersConfig Config(std::vector<DicomPeer> peers) {
  PeersConfig config;
  config.peers = std::move(peers);
  return config;
}

DeliveryOptions Quick() {
  DeliveryOptions options;
  options.initial_backoff = std::chrono::milliseconds(20);
  options.max_backoff = std::chrono::milliseconds(40);
  return options;
}

// The outbox's reports, waited for.
class Updates {
 public:
  DeliveryQueue::OnUpdate callback() {
    return [this](const std::string&, const v1::Delivery& d) {
      std::lock_guard<std::mutex> lock(mu_);
      all_.push_back(d);
      cv_.notify_all();
    };
  }
  bool WaitFor(v1::Delivery::State state) {
    std::unique_lock<std::mutex> lock(mu_);
    return cv_.wait_for(lock, std::chrono::seconds(30), [&] {
      for (const v1::Delivery& d : all_) {
        if (d.state() == state) return true;
      }
      return false;
    });
  }
  std::vector<v1::Delivery> all() {
    std::lock_guard<std::mutex> lock(mu_);
    return all_;
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  std::vector<v1::Delivery> all_;
};

// Now, in Unix milliseconds: when a delivery was first added (its give-up
// time counts from there).
int64_t NowMs() { return Clock::Real()->UnixMillis(); }

v1::Delivery Pending(const std::string& peer) {
  v1::Delivery d;
  d.set_peer(peer);
  d.set_state(v1::Delivery::PENDING);
  return d;
}

// A peer that cannot be reached is tried again after the backoff, and the
// delivery ends DELIVERED once it takes every file.
TEST(OutboxTest, UnreachablePeerIsRetriedUntilItTakesEveryFile) {
  PeerRegistry registry(
      testing::FakePeerFactory([](testing::FakePeerClient& c) {
        c.QueueStoreAnswer(absl::UnavailableError("down"));
        c.QueueStoreAnswer(absl::UnavailableError("down"));
      }),
      Config({Peer("pacs", "a.example")}));
  Updates updates;
  DeliveryQueue queue(&registry, Quick(), updates.callback());
  queue.Start();
  queue.Add("job1", Pending("pacs"), {"a.dcm", "b.dcm"}, NowMs());
  ASSERT_TRUE(updates.WaitFor(v1::Delivery::DELIVERED));
  queue.Stop();
  EXPECT_THAT(AsFake(registry.Find("pacs"))->stored(), SizeIs(3));
  const v1::Delivery last = updates.all().back();
  EXPECT_EQ(last.attempts(), 3);
  EXPECT_EQ(last.instances_sent(), 2);
  EXPECT_EQ(last.instances_total(), 2);
}

// Issue 38: the peers are one registry, so a reload reaches the outbox: the
// next try of a delivery still owed goes to the peer's new address (its new
// client), not to the one it had at the start.
TEST(OutboxTest, ReloadedPeerTakesTheNextTry) {
  PeerRegistry registry(
      testing::FakePeerFactory([](testing::FakePeerClient& c) {
        if (c.peer().host == "old.example") {
          c.QueueStoreAnswer(absl::UnavailableError("gone"));
          c.QueueStoreAnswer(absl::UnavailableError("gone"));
          c.QueueStoreAnswer(absl::UnavailableError("gone"));
        }
      }),
      Config({Peer("pacs", "old.example")}));
  const std::shared_ptr<PeerClient> old_client = registry.Find("pacs");
  Updates updates;
  DeliveryOptions slow = Quick();
  slow.initial_backoff = std::chrono::milliseconds(300);
  slow.max_backoff = std::chrono::milliseconds(300);
  DeliveryQueue queue(&registry, slow, updates.callback());
  queue.Start();
  queue.Add("job1", Pending("pacs"), {"a.dcm"}, NowMs());
  // The first try fails at the old address; the reload comes before the
  // next.
  ASSERT_TRUE(
      testing::WaitFor([&] { return !AsFake(old_client)->stored().empty(); },
                       std::chrono::seconds(30)));
  registry.SetPeers(Config({Peer("pacs", "new.example")}));
  ASSERT_TRUE(updates.WaitFor(v1::Delivery::DELIVERED));
  queue.Stop();
  EXPECT_THAT(AsFake(old_client)->stored(), SizeIs(1));
  EXPECT_THAT(AsFake(registry.Find("pacs"))->stored(), SizeIs(1));
}

// A peer the reload removed fails the tries of what is still owed to it
// (they are retried, as for a peer that cannot be reached).
TEST(OutboxTest, RemovedPeerFailsTheTryAndStaysPending) {
  PeerRegistry registry(testing::FakePeerFactory(),
                        Config({Peer("pacs", "a.example")}));
  registry.SetPeers(Config({}));
  Updates updates;
  DeliveryQueue queue(&registry, Quick(), updates.callback());
  queue.Start();
  queue.Add("job1", Pending("pacs"), {"a.dcm"}, NowMs());
  ASSERT_TRUE(testing::WaitFor(
      [&] {
        for (const v1::Delivery& d : updates.all()) {
          if (!d.last_error().empty()) return true;
        }
        return false;
      },
      std::chrono::seconds(30)));
  queue.Stop();
  v1::Delivery failed;
  for (const v1::Delivery& d : updates.all()) {
    if (!d.last_error().empty()) failed = d;
  }
  EXPECT_EQ(failed.state(), v1::Delivery::PENDING);
  EXPECT_THAT(failed.last_error(), HasSubstr("no longer in the peers file"));
}

// The engine's pull (PeerSeriesSource) asks the registry: an unknown peer is
// INVALID_ARGUMENT at admission and FAILED_PRECONDITION when it is gone by
// the time the job runs.
TEST(PeerRegistryTest, PullsFromTheNamedPeerOnly) {
  PeerRegistry registry(testing::FakePeerFactory(),
                        Config({Peer("pacs", "a.example")}));
  EXPECT_TRUE(registry.CheckPeer("pacs").ok());
  EXPECT_EQ(registry.CheckPeer("other").code(),
            absl::StatusCode::kInvalidArgument);
  v1::PacsSeriesSource source;
  source.set_peer("other");
  EXPECT_EQ(registry.Retrieve(source, "/nonexistent", 1 << 20, nullptr)
                .status()
                .code(),
            absl::StatusCode::kFailedPrecondition);
  const absl::Status unknown = registry.CheckPeers({"pacs", "elsewhere"});
  EXPECT_EQ(unknown.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(unknown.message(), HasSubstr("\"elsewhere\" (configured: pacs)"));
}

}  // namespace
}  // namespace interslice::server::node
