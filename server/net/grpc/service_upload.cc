// The upload RPCs: Submit (an upload that becomes a detached job) and
// Interpolate (an upload, then the job's progress, artifacts and summary on
// the same call). The disk side of an upload is UploadSink (upload_sink.h).
#include <chrono>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "job/wire.h"
#include "server/net/grpc/service.h"
#include "server/net/grpc/service_internal.h"
#include "server/net/grpc/status_map.h"
#include "server/net/grpc/upload_sink.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

using job::IsTerminalState;
using service_internal::ArtifactReader;
using service_internal::ErrorBidiReactor;
using service_internal::ErrorReadReactor;
using service_internal::kDefaultChunkBytes;

grpc::Status StatusOfFailedJob(const v1::JobStatus& s) {
  const int code =
      s.error_code() == 0 ? static_cast<int>(grpc::UNKNOWN) : s.error_code();
  return grpc::Status(static_cast<grpc::StatusCode>(code), s.error_message());
}

std::optional<std::chrono::steady_clock::time_point> CallDeadline(
    grpc::CallbackServerContext* context) {
  const auto deadline = context->deadline();
  if (deadline >= std::chrono::system_clock::time_point::max() -
                      std::chrono::hours(24 * 365)) {
    return std::nullopt;
  }
  return std::chrono::steady_clock::now() +
         std::chrono::duration_cast<std::chrono::steady_clock::duration>(
             deadline - std::chrono::system_clock::now());
}

// Whether an accepted upload message moved the upload forward (resets the
// idle clock): the header, or file data. Empty chunks do not count.
bool IsProgress(const v1::UploadRequest& message) {
  return message.has_header() ||
         (message.has_chunk() && !message.chunk().data().empty());
}

// Uploads are limited per identity when the call has one, else per IP.
std::string UploadPeerKey(grpc::CallbackServerContext* context,
                          const Caller& caller) {
  if (!caller.identity.empty()) return "id:" + caller.identity;
  return "ip:" + PeerAddress(context->peer());
}

// ---------------------------------------------------------------------------

class SubmitReactor : public grpc::ServerReadReactor<v1::UploadRequest> {
 public:
  SubmitReactor(InterSliceService* service,
                grpc::CallbackServerContext* context,
                v1::SubmitResponse* response, const Caller& caller)
      : service_(service),
        response_(response),
        sink_(std::make_shared<UploadSink>(
            service->manager(), service->spool(), service->metrics(),
            service->upload_limits(), false, std::nullopt, caller.identity)) {
    std::lock_guard<std::mutex> lock(mu_);
    absl::StatusOr<std::shared_ptr<UploadTicket>> ticket =
        service->uploads()->Begin(
            UploadPeerKey(context, caller),
            [this](const absl::Status& s, bool idle) { OnTimeout(s, idle); });
    if (!ticket.ok()) {
      service->metrics()->JobFinished("rejected");
      ending_ = true;
      Finish(ToGrpcStatus(ticket.status()));
      return;
    }
    ticket_ = *std::move(ticket);
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (ending_) return;  // a timeout is ending the call
    io_pending_ = true;
    service_->io()->Post([this, ok] { Step(!ok); });
  }
  void OnCancel() override {
    std::lock_guard<std::mutex> lock(mu_);
    cancelled_ = true;
  }
  void OnDone() override {
    if (ticket_) ticket_->Close();
    // A disk step may still be unlocking mu_ after its Finish().
    { std::lock_guard<std::mutex> lock(mu_); }
    delete this;
  }

 private:
  // Why the upload must stop although the last step succeeded, if it must.
  absl::Status InterruptionLocked() const {
    if (cancelled_) return absl::CancelledError("upload cancelled");
    return interruption_;
  }

  // One disk step (I/O executor): the message just read, or the end of the
  // upload (`end`: the client half-closed, or the call broke). While it
  // runs no read is pending, so it alone touches sink_ and request_.
  void Step(bool end) {
    absl::Status s;
    {
      std::lock_guard<std::mutex> lock(mu_);
      s = InterruptionLocked();
    }
    if (s.ok()) s = end ? sink_->Finish() : sink_->Consume(request_);
    if (s.ok() && !end && IsProgress(request_)) ticket_->Progress();
    std::unique_lock<std::mutex> lock(mu_);
    if (s.ok()) s = InterruptionLocked();
    if (s.ok() && !end) {
      io_pending_ = false;
      StartRead(&request_);
      return;
    }
    ending_ = true;
    lock.unlock();
    ticket_->Release();
    if (s.ok()) {
      response_->set_job_id(sink_->job()->id());
      *response_->mutable_status() = sink_->job()->Snapshot(false);
    } else {
      sink_->Abort();  // before the status: the client then finds no files
    }
    lock.lock();
    io_pending_ = false;
    Finish(ToGrpcStatus(s));
  }

  // The guard's thread: no data for the idle time, or over the total time.
  void OnTimeout(const absl::Status& status, bool idle) {
    std::lock_guard<std::mutex> lock(mu_);
    if (ending_) return;
    if (io_pending_) {
      // Our own disk step is slow, not the client: only the total limit
      // applies, when the step ends.
      if (!idle) interruption_ = status;
      return;
    }
    // A read is pending and the client sends nothing: end the call (the
    // pending read then completes with ok = false and is ignored).
    ending_ = true;
    io_pending_ = true;
    service_->io()->Post([this, status] {
      sink_->Abort();
      ticket_->Release();
      std::lock_guard<std::mutex> lock(mu_);
      io_pending_ = false;
      Finish(ToGrpcStatus(status));
    });
  }

  InterSliceService* const service_;
  v1::SubmitResponse* const response_;
  std::shared_ptr<UploadSink> sink_;
  std::shared_ptr<UploadTicket> ticket_;
  v1::UploadRequest request_;
  std::mutex mu_;
  bool io_pending_ = false;
  bool ending_ = false;  // Finish called or about to be: no more steps
  bool cancelled_ = false;
  absl::Status interruption_;
};

// One call: upload, then progress, then artifacts, then the summary.
class InterpolateReactor
    : public grpc::ServerBidiReactor<v1::UploadRequest,
                                     v1::InterpolateResponse> {
 public:
  InterpolateReactor(InterSliceService* service,
                     grpc::CallbackServerContext* context, const Caller& caller)
      : service_(service),
        sink_(std::make_shared<UploadSink>(
            service->manager(), service->spool(), service->metrics(),
            service->upload_limits(), true, CallDeadline(context),
            caller.identity)) {
    std::lock_guard<std::mutex> lock(mu_);
    absl::StatusOr<std::shared_ptr<UploadTicket>> ticket =
        service->uploads()->Begin(
            UploadPeerKey(context, caller),
            [this](const absl::Status& s, bool idle) { OnTimeout(s, idle); });
    if (!ticket.ok()) {
      service->metrics()->JobFinished("rejected");
      FinishLocked(ToGrpcStatus(ticket.status()));
      return;
    }
    ticket_ = *std::move(ticket);
    io_pending_ = false;
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (finished_ || upload_ending_) return;
    io_pending_ = true;
    if (ok) {
      service_->io()->Post([this] {
        absl::Status s = sink_->Consume(request_);
        if (s.ok() && IsProgress(request_)) ticket_->Progress();
        std::unique_lock<std::mutex> lock(mu_);
        if (s.ok() && !interruption_.ok()) s = interruption_;
        if (!s.ok() || cancelled_) {
          upload_ending_ = true;
          lock.unlock();
          sink_->Abort();
          ticket_->Release();
          lock.lock();
          io_pending_ = false;
          FinishLocked(cancelled_ ? grpc::Status::CANCELLED : ToGrpcStatus(s));
          return;
        }
        io_pending_ = false;
        StartRead(&request_);
      });
      return;
    }
    upload_ending_ = true;
    service_->io()->Post([this] {
      absl::Status s;
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (cancelled_) s = absl::CancelledError("call cancelled");
      }
      if (s.ok()) s = sink_->Finish();
      if (!s.ok()) sink_->Abort();
      ticket_->Release();  // the upload is over either way
      std::lock_guard<std::mutex> lock(mu_);
      io_pending_ = false;
      if (!s.ok()) {
        FinishLocked(ToGrpcStatus(s));
        return;
      }
      job_ = sink_->job();
      subscription_ = std::make_shared<Subscription>([this] {
        std::lock_guard<std::mutex> lock(mu_);
        WriteNextLocked();
      });
      job_->Subscribe(subscription_);
      WriteNextLocked();
    });
  }

  void OnWriteDone(bool ok) override {
    std::lock_guard<std::mutex> lock(mu_);
    write_in_flight_ = false;
    if (!ok) {
      FinishLocked(grpc::Status(grpc::CANCELLED, "the client went away"));
      return;
    }
    if (summary_sent_) {
      FinishLocked(grpc::Status::OK);
      return;
    }
    WriteNextLocked();
  }

  void OnCancel() override {
    std::lock_guard<std::mutex> lock(mu_);
    cancelled_ = true;
    FinishLocked(grpc::Status::CANCELLED);
  }

  void OnDone() override {
    if (subscription_) subscription_->Close();
    if (ticket_) ticket_->Close();
    // Deleting files blocks: leave it to the I/O executor. Discard cancels
    // the job if it still runs (a broken call cancels its job).
    std::shared_ptr<UploadSink> sink = sink_;
    JobManager* manager = service_->manager();
    service_->io()->Post([sink, manager] {
      sink->Abort();
      if (sink->enqueued()) manager->Discard(sink->job());
    });
    // A disk step may still be unlocking mu_ after its Finish().
    { std::lock_guard<std::mutex> lock(mu_); }
    delete this;
  }

 private:
  // The guard's thread: no data for the idle time, or over the total time.
  void OnTimeout(const absl::Status& status, bool idle) {
    std::lock_guard<std::mutex> lock(mu_);
    if (finished_ || upload_ending_) return;
    if (io_pending_) {
      // Our own disk step is slow, not the client: only the total limit
      // applies, when the step ends.
      if (!idle) interruption_ = status;
      return;
    }
    // A read is pending and the client sends nothing: end the call (the
    // pending read then completes with ok = false and is ignored).
    upload_ending_ = true;
    io_pending_ = true;
    service_->io()->Post([this, status] {
      sink_->Abort();
      ticket_->Release();
      std::lock_guard<std::mutex> lock(mu_);
      io_pending_ = false;
      FinishLocked(ToGrpcStatus(status));
    });
  }

  // Sends the next message if none is in flight. mu_ held.
  void WriteNextLocked() {
    if (finished_ || write_in_flight_ || io_pending_ || !job_) return;
    if (!accepted_sent_) {
      accepted_sent_ = true;
      response_.Clear();
      response_.mutable_accepted()->set_job_id(job_->id());
      StartWriteLocked();
      return;
    }
    if (reader_) {  // streaming artifacts
      ReadArtifactLocked();
      return;
    }
    const v1::JobStatus status = job_->Snapshot(true);
    if (IsTerminalState(status.state())) {
      if (status.state() != v1::JOB_STATE_SUCCEEDED) {
        FinishLocked(StatusOfFailedJob(status));
        return;
      }
      final_ = status;
      artifact_index_ = -1;
      NextArtifactLocked();
      return;
    }
    if (status.sequence() <= last_sequence_) return;
    last_sequence_ = status.sequence();
    response_.Clear();
    *response_.mutable_progress() = status.progress();
    StartWriteLocked();
  }

  void NextArtifactLocked() {
    ++artifact_index_;
    if (artifact_index_ >= final_.artifacts_size()) {
      reader_.reset();
      response_.Clear();
      v1::JobSummary* summary = response_.mutable_summary();
      summary->set_job_id(final_.job_id());
      summary->set_report_json(final_.report_json());
      *summary->mutable_artifacts() = final_.artifacts();
      summary_sent_ = true;
      StartWriteLocked();
      return;
    }
    const v1::ArtifactInfo& info = final_.artifacts(artifact_index_);
    reader_ = std::make_shared<ArtifactReader>(
        (fs::path(service_->spool()->OutputDir(final_.job_id())) / info.name())
            .string(),
        info, 0, kDefaultChunkBytes);
    ReadArtifactLocked();
  }

  void ReadArtifactLocked() {
    io_pending_ = true;
    service_->io()->Post([this] {
      absl::StatusOr<bool> more = reader_->Next(&chunk_);
      std::lock_guard<std::mutex> lock(mu_);
      io_pending_ = false;
      if (cancelled_ || finished_) {
        FinishLocked(grpc::Status::CANCELLED);
        return;
      }
      if (!more.ok()) {
        FinishLocked(ToGrpcStatus(more.status()));
        return;
      }
      if (!*more) {
        NextArtifactLocked();
        return;
      }
      service_->metrics()->BytesOut(static_cast<double>(chunk_.data().size()));
      response_.Clear();
      response_.mutable_artifact()->Swap(&chunk_);
      StartWriteLocked();
    });
  }

  void StartWriteLocked() {
    write_in_flight_ = true;
    StartWrite(&response_);
  }

  // Finish once; while a disk step runs, the step finishes instead (it
  // still uses this reactor).
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
  std::shared_ptr<UploadSink> sink_;
  std::shared_ptr<UploadTicket> ticket_;
  std::mutex mu_;
  v1::UploadRequest request_;
  v1::InterpolateResponse response_;
  v1::ArtifactChunk chunk_;
  std::shared_ptr<Job> job_;
  std::shared_ptr<Subscription> subscription_;
  std::shared_ptr<ArtifactReader> reader_;
  v1::JobStatus final_;
  int artifact_index_ = -1;
  int64_t last_sequence_ = 0;
  bool io_pending_ = false;
  bool write_in_flight_ = false;
  bool accepted_sent_ = false;
  bool summary_sent_ = false;
  bool finished_ = false;
  bool cancelled_ = false;
  bool upload_ending_ = false;  // no more upload reads or steps
  absl::Status interruption_;   // the total upload time ran out
};

}  // namespace

grpc::ServerBidiReactor<v1::UploadRequest, v1::InterpolateResponse>*
InterSliceService::Interpolate(grpc::CallbackServerContext* context) {
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    return new ErrorBidiReactor<v1::UploadRequest, v1::InterpolateResponse>(
        ToGrpcStatus(caller.status()));
  }
  return new InterpolateReactor(this, context, *caller);
}

grpc::ServerReadReactor<v1::UploadRequest>* InterSliceService::Submit(
    grpc::CallbackServerContext* context, v1::SubmitResponse* response) {
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    return new ErrorReadReactor<v1::UploadRequest>(
        ToGrpcStatus(caller.status()));
  }
  return new SubmitReactor(this, context, response, *caller);
}

}  // namespace interslice::server
