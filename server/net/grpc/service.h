// The interslice.v1.InterSlice service on gRPC's callback API.
//
// Threading: reactor callbacks run on gRPC's threads and never block. Every
// step that touches the disk (admission, which creates the job folder;
// writing and hashing upload chunks; reading artifact chunks; persisting a
// cancellation) is posted to the I/O executor, and the reactor issues its
// next read or write when that step completes, so each stream has at most one
// read, one write and one disk step in flight, and uploads apply back
// pressure to the client. Job status reaches Watch and Interpolate streams
// through a Subscription that only wakes the reactor; the reactor sends the
// newest status when its previous write completes (older ones are coalesced).
//
// Uploads: UploadStream checks the stream, UploadGuard bounds the uploads in
// progress (in total and per client) and cancels stalled ones; a queue slot
// is taken only when an upload is complete. Jobs belong to the caller's
// identity (auth.h): other identities get NOT_FOUND, admins see every job.
#ifndef INTERSLICE_SERVER_NET_GRPC_SERVICE_H_
#define INTERSLICE_SERVER_NET_GRPC_SERVICE_H_

#include <atomic>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "interslice/v1/interslice.grpc.pb.h"
#include "server/base/executor.h"
#include "server/base/metrics.h"
#include "server/engine/job_manager.h"
#include "server/engine/spool.h"
#include "server/net/grpc/auth.h"
#include "server/net/grpc/forwarding.h"
#include "server/net/grpc/upload_guard.h"
#include "server/net/grpc/upload_stream.h"

namespace interslice::server {

class AuditLog;
struct AuditEvent;
namespace node {
class PeerRegistry;
class SeriesAssembler;
}  // namespace node

struct ServiceOptions {
  // Bearer tokens, one of which every call must carry; empty = none (the
  // identity then comes from a client certificate, if any).
  std::vector<NamedToken> tokens;
  // Identities that see and may act on every job.
  std::vector<std::string> admin_identities;
  int max_chunk_bytes = 1 << 20;
  UploadGuardOptions uploads;
  std::string version = "0.1.0";
  // The audit trail (server/base/audit.h); null = none. Outlives the service.
  AuditLog* audit = nullptr;
};

class InterSliceService final : public v1::InterSlice::CallbackService {
 public:
  InterSliceService(const ServiceOptions& options, JobManager* manager,
                    Spool* spool, Executor* io, Metrics* metrics)
      : options_(options),
        auth_(options.tokens, options.admin_identities),
        uploads_(std::make_unique<UploadGuard>(options.uploads)),
        manager_(manager),
        spool_(spool),
        io_(io),
        metrics_(metrics),
        dicom_queries_(std::make_unique<Executor>(kDicomQueryThreads)) {}

  grpc::ServerBidiReactor<v1::UploadRequest, v1::InterpolateResponse>*
  Interpolate(grpc::CallbackServerContext* context) override;
  grpc::ServerReadReactor<v1::UploadRequest>* Submit(
      grpc::CallbackServerContext* context,
      v1::SubmitResponse* response) override;
  grpc::ServerWriteReactor<v1::JobStatus>* Watch(
      grpc::CallbackServerContext* context,
      const v1::WatchRequest* request) override;
  grpc::ServerWriteReactor<v1::ArtifactChunk>* Fetch(
      grpc::CallbackServerContext* context,
      const v1::FetchRequest* request) override;
  grpc::ServerUnaryReactor* Cancel(grpc::CallbackServerContext* context,
                                   const v1::CancelRequest* request,
                                   v1::JobStatus* response) override;
  grpc::ServerUnaryReactor* List(grpc::CallbackServerContext* context,
                                 const v1::ListRequest* request,
                                 v1::ListResponse* response) override;
  grpc::ServerUnaryReactor* GetServerInfo(grpc::CallbackServerContext* context,
                                          const v1::ServerInfoRequest* request,
                                          v1::ServerInfo* response) override;
  grpc::ServerUnaryReactor* Find(grpc::CallbackServerContext* context,
                                 const v1::FindRequest* request,
                                 v1::FindResponse* response) override;
  // The DICOM listener's kept series (admins only; FAILED_PRECONDITION
  // without a listener). Both read the spool: run on the I/O executor.
  grpc::ServerUnaryReactor* ListKept(grpc::CallbackServerContext* context,
                                     const v1::ListKeptRequest* request,
                                     v1::ListKeptResponse* response) override;
  grpc::ServerUnaryReactor* RerunKept(grpc::CallbackServerContext* context,
                                      const v1::RerunKeptRequest* request,
                                      v1::RerunKeptResponse* response) override;

  // Calls for jobs this replica does not hold go to their owner through
  // `forwarder` (server/net/grpc/forwarding.h); without one they are unknown
  // jobs. Set before the server starts.
  void set_forwarder(Forwarder* forwarder) { forwarder_ = forwarder; }
  // The DICOM listener's series assembler (ListKept, RerunKept); null: no
  // listener. Set before the server starts; outlives the service's calls.
  void set_assembler(node::SeriesAssembler* assembler) {
    assembler_ = assembler;
  }
  // The DICOM peers (the Find RPC); null: none. Set before the server
  // starts; outlives the service's calls.
  void set_peers(const node::PeerRegistry* peers) { peers_ = peers; }

  // Shared with the reactors (service_upload.cc, service_jobs.cc).
  const ServiceOptions& options() const { return options_; }
  JobManager* manager() const { return manager_; }
  Spool* spool() const { return spool_; }
  Executor* io() const { return io_; }
  Metrics* metrics() const { return metrics_; }
  UploadGuard* uploads() const { return uploads_.get(); }
  UploadStreamLimits upload_limits() const;

 private:
  absl::StatusOr<Caller> Authenticate(
      grpc::CallbackServerContext* context) const;
  // Records `event` in the audit trail, if there is one.
  void Audit(AuditEvent event) const;
  // The owner to forward a call for `job_id` to, if it is not held here.
  std::optional<std::string> ForwardTarget(
      const grpc::CallbackServerContext& context,
      const std::string& job_id) const;

  const ServiceOptions options_;
  const Authenticator auth_;
  const std::unique_ptr<UploadGuard> uploads_;
  JobManager* const manager_;
  Spool* const spool_;
  Executor* const io_;
  Metrics* const metrics_;
  Forwarder* forwarder_ = nullptr;
  node::SeriesAssembler* assembler_ = nullptr;
  const node::PeerRegistry* peers_ = nullptr;
  // C-FINDs on DICOM peers block for up to their timeouts: threads of their
  // own, never the reactors' nor io_'s; at most kMaxDicomQueries queued or
  // running (then RESOURCE_EXHAUSTED).
  static constexpr int kDicomQueryThreads = 2;
  static constexpr int kMaxDicomQueries = 8;
  std::atomic<int> dicom_queries_in_flight_{0};
  const std::unique_ptr<Executor> dicom_queries_;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_SERVICE_H_
