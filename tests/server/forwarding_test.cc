// Job ids that name their owner, and which owners a replica forwards to.
#include "server/forwarding.h"

#include <gtest/gtest.h>

#include <string>

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

}  // namespace
}  // namespace interslice::server
