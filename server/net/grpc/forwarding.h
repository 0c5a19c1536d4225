// Replicas that answer for each other's jobs.
//
// A detached job lives in the spool of the replica that accepted it (its
// owner). Job ids name that owner: "<16 hex digits>.<owner>", where <owner> is
// the owner's advertised HOST:PORT in lowercase RFC 4648 base32 without
// padding, so an id is safe as a file name (the spool's folder names) and in
// URLs, and is case-insensitive-filesystem safe. Ids of 16 hex digits alone
// (before replicas existed) name no owner and are served where they are.
//
// A replica that gets Watch, Fetch or Cancel for a job it does not hold
// forwards the call to the owner (a server-side proxy, not a client
// redirect: any gRPC client, a script with grpcurl or a balancer in front of
// the replicas works unchanged, and clients outside a cluster need not reach
// the pods' own addresses). The forwarded call carries the caller's bearer
// token and deadline, and cancellation propagates both ways. It is marked so
// that it is never forwarded again (no loops). When the owner cannot be
// reached the answer is UNAVAILABLE naming the owner; the job is not lost:
// it comes back when the owner returns with its spool.
//
// Only owners in the same replica set are contacted: the same host as this
// replica's advertised address, or a host in the same DNS domain after its
// first label (a StatefulSet's pods "NAME-<i>.SERVICE.NS.svc..."). A forged
// id naming any other address is answered as an unknown job, so callers
// cannot make a replica connect to arbitrary hosts.
//
// Threading: nothing here blocks. Forwarded streams relay one message at a
// time between gRPC's callback reactors (back pressure both ways).
#ifndef INTERSLICE_SERVER_NET_GRPC_FORWARDING_H_
#define INTERSLICE_SERVER_NET_GRPC_FORWARDING_H_

#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>

#include "grpcpp/security/credentials.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::server {

// "." + base32(advertise): appended to new job ids (see above).
std::string JobIdSuffix(std::string_view advertise);

// The owner's HOST:PORT named by a job id; nullopt for ids that name none
// (legacy ids) or carry anything but a well-formed HOST:PORT.
std::optional<std::string> JobOwner(std::string_view job_id);

// Whether `address` is a HOST:PORT a job id can name (a DNS name, IPv4
// address or bracketed IPv6 address, and a port in [1, 65535]).
bool IsReplicaAddress(std::string_view address);

// Whether `owner` is in the same replica set as `self` (see above).
bool SameReplicaSet(std::string_view self, std::string_view owner);

// Metadata key marking a forwarded call (its value: the forwarder's address).
inline constexpr char kForwardedByKey[] = "interslice-forwarded-by";

class Forwarder {
 public:
  // `credentials`: how to reach other replicas (plaintext or TLS, as this
  // server's own listener).
  explicit Forwarder(std::shared_ptr<grpc::ChannelCredentials> credentials)
      : credentials_(std::move(credentials)) {}

  // This replica's advertised HOST:PORT (known once the port is bound).
  void SetAdvertise(std::string advertise);
  std::string advertise() const;

  // The owner to forward a call for `job_id` to, or nullopt to answer here:
  // call only for ids this replica does not hold. Forwarded calls and ids of
  // other replica sets are answered here (as unknown jobs).
  std::optional<std::string> Route(const grpc::CallbackServerContext& context,
                                   std::string_view job_id) const;

  // The call, relayed to `owner`.
  grpc::ServerWriteReactor<v1::JobStatus>* Watch(
      grpc::CallbackServerContext* context, const v1::WatchRequest& request,
      const std::string& owner);
  grpc::ServerWriteReactor<v1::ArtifactChunk>* Fetch(
      grpc::CallbackServerContext* context, const v1::FetchRequest& request,
      const std::string& owner);
  // Finishes `reactor` (the call's default reactor) when the owner answers.
  void Cancel(grpc::CallbackServerContext* context,
              grpc::ServerUnaryReactor* reactor,
              const v1::CancelRequest& request, v1::JobStatus* response,
              const std::string& owner);

 private:
  // One channel per owner, kept (channels reconnect by themselves), at most
  // kMaxChannels: ids are client text, so names within the replica set
  // could otherwise grow the cache without bound. Calls in flight keep their
  // channel alive when it is dropped from the cache.
  static constexpr size_t kMaxChannels = 64;
  std::shared_ptr<v1::InterSlice::Stub> StubFor(const std::string& owner);
  // A ClientContext for the forwarded call: the caller's deadline,
  // cancellation and token, and the forwarded mark.
  std::unique_ptr<grpc::ClientContext> ForwardContext(
      grpc::CallbackServerContext* context) const;

  const std::shared_ptr<grpc::ChannelCredentials> credentials_;
  mutable std::mutex mu_;
  std::string advertise_;
  std::map<std::string, std::shared_ptr<v1::InterSlice::Stub>> stubs_;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_FORWARDING_H_
