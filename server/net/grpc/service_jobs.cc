// The job RPCs: Watch, Fetch, Cancel and List, on jobs this replica holds
// (calls for another replica's jobs are forwarded, forwarding.h).
#include <cstdint>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "job/wire.h"
#include "server/base/audit.h"
#include "server/net/grpc/service.h"
#include "server/net/grpc/service_internal.h"
#include "server/net/grpc/status_map.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

constexpr int kMaxFetchChunkBytes = 1 << 20;

using job::IsTerminalState;
using service_internal::ArtifactReader;
using service_internal::ErrorWriteReactor;
using service_internal::kDefaultChunkBytes;

class WatchReactor : public grpc::ServerWriteReactor<v1::JobStatus> {
 public:
  WatchReactor(std::shared_ptr<Job> job, int64_t after_sequence)
      : job_(std::move(job)), last_sequence_(after_sequence) {
    subscription_ = std::make_shared<Subscription>([this] {
      std::lock_guard<std::mutex> lock(mu_);
      WriteNextLocked();
    });
    std::lock_guard<std::mutex> lock(mu_);
    job_->Subscribe(subscription_);
    first_ = true;
    WriteNextLocked();
  }

  void OnWriteDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    write_in_flight_ = false;
    if (!ok) {
      FinishLocked(grpc::Status(grpc::CANCELLED, "the client went away"));
      return;
    }
    if (terminal_sent_) {
      FinishLocked(grpc::Status::OK);
      return;
    }
    WriteNextLocked();
  }
  void OnCancel() override {
    std::lock_guard<std::mutex> lock(mu_);
    FinishLocked(grpc::Status::CANCELLED);
  }
  void OnDone() override {
    subscription_->Close();
    delete this;
  }

 private:
  void WriteNextLocked() {
    if (finished_ || write_in_flight_ || terminal_sent_) return;
    status_ = job_->Snapshot(true);
    const bool terminal = IsTerminalState(status_.state());
    if (!terminal && status_.sequence() <= last_sequence_) return;
    if (terminal && !first_ && status_.sequence() <= last_sequence_) return;
    first_ = false;
    last_sequence_ = status_.sequence();
    terminal_sent_ = terminal;
    write_in_flight_ = true;
    StartWrite(&status_);
  }
  void FinishLocked(const grpc::Status& status) {
    if (finished_) return;
    finished_ = true;
    Finish(status);
  }

  std::shared_ptr<Job> job_;
  std::shared_ptr<Subscription> subscription_;
  std::mutex mu_;
  v1::JobStatus status_;
  int64_t last_sequence_;
  bool first_ = true;
  bool write_in_flight_ = false;
  bool terminal_sent_ = false;
  bool finished_ = false;
};

class FetchReactor : public grpc::ServerWriteReactor<v1::ArtifactChunk> {
 public:
  FetchReactor(InterSliceService* service,
               std::shared_ptr<ArtifactReader> reader)
      : service_(service), reader_(std::move(reader)) {
    std::lock_guard<std::mutex> lock(mu_);
    ReadLocked();
  }
  void OnWriteDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    write_in_flight_ = false;
    if (!ok) {
      FinishLocked(grpc::Status(grpc::CANCELLED, "the client went away"));
      return;
    }
    ReadLocked();
  }
  void OnCancel() override {
    std::lock_guard<std::mutex> lock(mu_);
    FinishLocked(grpc::Status::CANCELLED);
  }
  void OnDone() override { delete this; }

 private:
  void ReadLocked() {
    if (finished_) return;
    io_pending_ = true;
    service_->io()->Post([this] {
      absl::StatusOr<bool> more = reader_->Next(&chunk_);
      std::lock_guard<std::mutex> lock(mu_);
      io_pending_ = false;
      if (cancelled_) {
        FinishLocked(grpc::Status::CANCELLED);
      } else if (!more.ok()) {
        FinishLocked(ToGrpcStatus(more.status()));
      } else if (!*more) {
        FinishLocked(grpc::Status::OK);
      } else {
        service_->metrics()->BytesOut(
            static_cast<double>(chunk_.data().size()));
        write_in_flight_ = true;
        StartWrite(&chunk_);
      }
    });
  }
  void FinishLocked(const grpc::Status& status) {
    if (finished_) return;
    if (io_pending_) {
      cancelled_ = true;
      return;
    }
    finished_ = true;
    Finish(status);
  }

  InterSliceService* const service_;
  std::shared_ptr<ArtifactReader> reader_;
  std::mutex mu_;
  v1::ArtifactChunk chunk_;
  bool io_pending_ = false;
  bool write_in_flight_ = false;
  bool cancelled_ = false;
  bool finished_ = false;
};

// The job `id` if it exists, is detached and `caller` may see it. Jobs of
// other identities are answered exactly as unknown ones.
std::shared_ptr<Job> FindVisibleJob(JobManager* manager, const std::string& id,
                                    const Caller& caller) {
  std::shared_ptr<Job> job = manager->Find(id);
  if (!job || job->ephemeral() ||
      !Authenticator::MayAccess(caller, job->owner())) {
    return nullptr;
  }
  return job;
}

}  // namespace

grpc::ServerWriteReactor<v1::JobStatus>* InterSliceService::Watch(
    grpc::CallbackServerContext* context, const v1::WatchRequest* request) {
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    return new ErrorWriteReactor<v1::JobStatus>(ToGrpcStatus(caller.status()));
  }
  if (std::optional<std::string> owner =
          ForwardTarget(*context, request->job_id())) {
    return forwarder_->Watch(context, *request, *owner);
  }
  std::shared_ptr<Job> job =
      FindVisibleJob(manager_, request->job_id(), *caller);
  if (!job) {
    return new ErrorWriteReactor<v1::JobStatus>(
        grpc::Status(grpc::NOT_FOUND, "no such job (it may have expired)"));
  }
  return new WatchReactor(std::move(job), request->after_sequence());
}

grpc::ServerWriteReactor<v1::ArtifactChunk>* InterSliceService::Fetch(
    grpc::CallbackServerContext* context, const v1::FetchRequest* request) {
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    return new ErrorWriteReactor<v1::ArtifactChunk>(
        ToGrpcStatus(caller.status()));
  }
  if (std::optional<std::string> owner =
          ForwardTarget(*context, request->job_id())) {
    return forwarder_->Fetch(context, *request, *owner);
  }
  std::shared_ptr<Job> job =
      FindVisibleJob(manager_, request->job_id(), *caller);
  if (!job) {
    return new ErrorWriteReactor<v1::ArtifactChunk>(
        grpc::Status(grpc::NOT_FOUND, "no such job (it may have expired)"));
  }
  const v1::JobStatus status = job->Snapshot(false);
  if (status.state() != v1::JOB_STATE_SUCCEEDED) {
    return new ErrorWriteReactor<v1::ArtifactChunk>(grpc::Status(
        grpc::FAILED_PRECONDITION,
        absl::StrCat("the job is ", v1::JobState_Name(status.state()),
                     "; only a SUCCEEDED job has artifacts")));
  }
  const v1::ArtifactInfo* info = nullptr;
  for (const v1::ArtifactInfo& a : status.artifacts()) {
    if (a.name() == request->artifact_name()) info = &a;
  }
  if (info == nullptr) {
    return new ErrorWriteReactor<v1::ArtifactChunk>(
        grpc::Status(grpc::NOT_FOUND, "the job has no artifact of that name"));
  }
  if (request->offset() < 0 || request->offset() > info->size_bytes()) {
    return new ErrorWriteReactor<v1::ArtifactChunk>(grpc::Status(
        grpc::OUT_OF_RANGE, "offset beyond the end of the artifact"));
  }
  int chunk =
      request->chunk_size() == 0 ? kDefaultChunkBytes : request->chunk_size();
  if (chunk < 0 || chunk > kMaxFetchChunkBytes) {
    return new ErrorWriteReactor<v1::ArtifactChunk>(grpc::Status(
        grpc::INVALID_ARGUMENT, "chunk_size must be in [0, 1 MiB]"));
  }
  AuditEvent fetched;
  fetched.event = "job.fetched";
  fetched.identity = caller->identity;
  fetched.source = context->peer();
  fetched.job = job->id();
  fetched.detail =
      absl::StrCat("artifact ", info->name(), " from byte ", request->offset());
  Audit(std::move(fetched));
  auto reader = std::make_shared<ArtifactReader>(
      (fs::path(spool_->OutputDir(job->id())) / info->name()).string(), *info,
      request->offset(), chunk);
  return new FetchReactor(this, std::move(reader));
}

grpc::ServerUnaryReactor* InterSliceService::Cancel(
    grpc::CallbackServerContext* context, const v1::CancelRequest* request,
    v1::JobStatus* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  const std::string id = request->job_id();
  if (std::optional<std::string> owner = ForwardTarget(*context, id)) {
    forwarder_->Cancel(context, reactor, *request, response, *owner);
    return reactor;
  }
  // Cancelling a queued job persists its record: off the reactor thread.
  io_->Post([this, reactor, response, id, caller = *caller,
             source = context->peer()] {
    if (!FindVisibleJob(manager_, id, caller)) {
      reactor->Finish(grpc::Status(grpc::NOT_FOUND, "no such job"));
      return;
    }
    AuditEvent e;
    e.event = "job.cancel_requested";
    e.identity = caller.identity;
    e.source = source;
    e.job = id;
    Audit(std::move(e));
    absl::StatusOr<v1::JobStatus> status = manager_->Cancel(id);
    if (status.ok()) *response = *status;
    reactor->Finish(ToGrpcStatus(status.status()));
  });
  return reactor;
}

grpc::ServerUnaryReactor* InterSliceService::List(
    grpc::CallbackServerContext* context, const v1::ListRequest* request,
    v1::ListResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // Only the caller's own jobs, unless an admin asks (or nobody is
  // authenticated: then every job is the anonymous user's, see MayAccess).
  const std::string* owner =
      caller->admin || caller->identity.empty() ? nullptr : &caller->identity;
  for (v1::JobStatus& s : manager_->List(request->include_finished(), owner)) {
    *response->add_jobs() = std::move(s);
  }
  AuditEvent listed;
  listed.event = "jobs.listed";
  listed.identity = caller->identity;
  listed.source = context->peer();
  listed.count = response->jobs_size();
  Audit(std::move(listed));
  reactor->Finish(grpc::Status::OK);
  return reactor;
}

}  // namespace interslice::server
