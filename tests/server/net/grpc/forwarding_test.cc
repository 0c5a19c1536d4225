// Job ids that name their owner, and which owners a replica forwards to.
#include "server/net/grpc/forwarding.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <memory>
#include <random>
#include <string>
#include <thread>

#include "absl/strings/str_cat.h"
#include "grpcpp/grpcpp.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::server {
namespace {

const char kLocal[] = "0123456789abcdef";

TEST(JobIdTest, OwnerRoundTripsThroughTheId) {
  for (const std::string owner :
       {"127.0.0.1:5001",
        "interslice-2.interslice.imaging.svc.cluster.local:50051",
        "[::1]:50051", "a:1"}) {
    const std::string id = kLocal + JobIdSuffix(owner);
    ASSERT_TRUE(JobOwner(id).has_value()) << id;
    EXPECT_EQ(*JobOwner(id), owner);
    // Safe in file names and URLs, whatever the filesystem's case rules.
    for (char c : id) {
      EXPECT_TRUE((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.')
          << id;
    }
  }
}

TEST(JobIdTest, LegacyAndMalformedIdsNameNoOwner) {
  EXPECT_FALSE(JobOwner(kLocal).has_value());  // ids from before replicas
  EXPECT_FALSE(JobOwner("").has_value());
  EXPECT_FALSE(JobOwner("0123.gezdgnbvgy3tqojq").has_value());
  // Not base32, upper case, non-canonical padding bits.
  EXPECT_FALSE(JobOwner(std::string(kLocal) + ".gezdgnbv!y3t").has_value());
  EXPECT_FALSE(JobOwner(std::string(kLocal) + ".GEZDGNBV").has_value());
  EXPECT_FALSE(JobOwner(std::string(kLocal) + ".b").has_value());
  // Decodes, but not HOST:PORT.
  for (const std::string bad : {"no-port", "host:0", "host:70000", "ho st:1",
                                "host:1/x", "[zz]:1", ":50051", "host:port"}) {
    EXPECT_FALSE(JobOwner(kLocal + JobIdSuffix(bad)).has_value()) << bad;
    EXPECT_FALSE(IsReplicaAddress(bad)) << bad;
  }
  EXPECT_FALSE(IsReplicaAddress(std::string(300, 'a') + ":1"));
}

TEST(ReplicaSetTest, SameHostOrSameServiceDomainOnly) {
  EXPECT_TRUE(SameReplicaSet("127.0.0.1:5001", "127.0.0.1:5002"));
  EXPECT_FALSE(SameReplicaSet("127.0.0.1:5001", "10.0.0.1:5001"));
  EXPECT_TRUE(SameReplicaSet("is-0.is.ns.svc.cluster.local:50051",
                             "is-3.is.ns.svc.cluster.local:50051"));
  EXPECT_TRUE(SameReplicaSet("IS-0.is.ns.svc:50051", "is-3.is.ns.svc:50051"));
  EXPECT_FALSE(SameReplicaSet("is-0.is.ns.svc.cluster.local:50051",
                              "evil.example.com:50051"));
  EXPECT_FALSE(SameReplicaSet("is-0.is.ns.svc.cluster.local:50051",
                              "is-1.other.ns.svc.cluster.local:50051"));
  // A one-label parent domain would admit every host under it.
  EXPECT_FALSE(SameReplicaSet("a.com:1", "b.com:1"));
  EXPECT_FALSE(SameReplicaSet("is-0.is.ns.svc:50051", "10.0.0.1:50051"));
  EXPECT_FALSE(SameReplicaSet("bad", "127.0.0.1:1"));
}

// The owner side of a forwarded Watch: streams statuses 1, 2, 3, ... (each
// with `payload` bytes of report) until its server shuts down.
class EndlessWatch : public grpc::ServerWriteReactor<v1::JobStatus> {
 public:
  explicit EndlessWatch(size_t payload) : payload_(payload) { Next(); }
  void OnWriteDone(bool ok) override {
    if (!ok) {
      Finish(grpc::Status(grpc::UNAVAILABLE, "owner stopping"));
      return;
    }
    Next();
  }
  void OnDone() override { delete this; }

 private:
  void Next() {
    status_.set_sequence(++sequence_);
    status_.set_report_json(std::string(payload_, 'x'));
    StartWrite(&status_);
  }
  const size_t payload_;
  int64_t sequence_ = 0;
  v1::JobStatus status_;
};

class OwnerService : public v1::InterSlice::CallbackService {
 public:
  explicit OwnerService(size_t payload) : payload_(payload) {}
  grpc::ServerWriteReactor<v1::JobStatus>* Watch(
      grpc::CallbackServerContext*, const v1::WatchRequest*) override {
    return new EndlessWatch(payload_);
  }

 private:
  const size_t payload_;
};

// A replica that does not hold the job: every Watch goes to `owner`.
class FrontService : public v1::InterSlice::CallbackService {
 public:
  FrontService(Forwarder* forwarder, std::string owner)
      : forwarder_(forwarder), owner_(std::move(owner)) {}
  grpc::ServerWriteReactor<v1::JobStatus>* Watch(
      grpc::CallbackServerContext* context,
      const v1::WatchRequest* request) override {
    return forwarder_->Watch(context, *request, owner_);
  }

 private:
  Forwarder* const forwarder_;
  const std::string owner_;
};

std::unique_ptr<grpc::Server> StartServer(grpc::Service* service, int* port) {
  grpc::ServerBuilder builder;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                           port);
  builder.RegisterService(service);
  return builder.BuildAndStart();
}

// Regression test for a use-after-free in the forwarding proxy: when the
// owner went away between two reads (its status arriving while no read was
// outstanding), the proxy could start a read on the finished upstream call
// ("pure virtual method called", seen under ASan in the replica test). The
// owner is stopped at random moments, with small messages (reads and writes
// complete at once) and large ones (writes held back by flow control while
// the caller pauses). Every relayed message arrives once, in order, and the
// call ends with an error, never a crash; the proxy stays usable.
TEST(ForwardedStreamTest, OwnerStoppingAtAnyMomentEndsTheCallCleanly) {
  Forwarder forwarder(grpc::InsecureChannelCredentials());
  std::mt19937 random(20261123);
  for (int round = 0; round < 40; ++round) {
    const size_t payload = round % 2 == 0 ? 16 : (size_t{1} << 20);
    OwnerService owner_service(payload);
    int owner_port = 0;
    std::unique_ptr<grpc::Server> owner =
        StartServer(&owner_service, &owner_port);
    ASSERT_NE(owner_port, 0);
    const std::string owner_address = absl::StrCat("127.0.0.1:", owner_port);
    FrontService front_service(&forwarder, owner_address);
    int front_port = 0;
    std::unique_ptr<grpc::Server> front =
        StartServer(&front_service, &front_port);
    ASSERT_NE(front_port, 0);

    auto stub = v1::InterSlice::NewStub(
        grpc::CreateChannel(absl::StrCat("127.0.0.1:", front_port),
                            grpc::InsecureChannelCredentials()));
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() +
                         std::chrono::seconds(30));
    v1::WatchRequest request;
    request.set_job_id("0123456789abcdef");
    auto reader = stub->Watch(&context, request);

    const int read_before_stop = 1 + static_cast<int>(random() % 20);
    v1::JobStatus status;
    int64_t last = 0;
    for (int i = 0; i < read_before_stop; ++i) {
      ASSERT_TRUE(reader->Read(&status)) << "round " << round;
      ASSERT_EQ(status.sequence(), last + 1) << "round " << round;
      last = status.sequence();
    }
    // Stop the owner while the proxy is between reads or writes; the
    // caller pauses so that large writes wait for flow control. (The random
    // pauses vary the interleaving from round to round; they synchronise
    // nothing.)
    std::thread stopper([&] {
      std::this_thread::sleep_for(std::chrono::microseconds(random() % 3000));
      owner->Shutdown(std::chrono::system_clock::now());
    });
    std::this_thread::sleep_for(std::chrono::microseconds(random() % 3000));
    while (reader->Read(&status)) {
      ASSERT_EQ(status.sequence(), last + 1) << "round " << round;
      last = status.sequence();
    }
    stopper.join();
    const grpc::Status end = reader->Finish();
    EXPECT_FALSE(end.ok()) << "round " << round;
    EXPECT_NE(end.error_code(), grpc::DEADLINE_EXCEEDED)
        << "round " << round << ": the proxy did not end the call";
    if (end.error_code() == grpc::UNAVAILABLE) {
      EXPECT_NE(end.error_message().find(owner_address), std::string::npos)
          << end.error_message();
    }
    front->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(5));
    owner->Wait();
  }
}

}  // namespace
}  // namespace interslice::server
