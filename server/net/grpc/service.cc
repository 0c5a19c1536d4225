#include "server/net/grpc/service.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>

#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "job/job.h"
#include "job/wire.h"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/redact.h"
#include "server/net/grpc/status_map.h"
#include "server/node/peer.h"
#include "server/node/peer_registry.h"
#include "server/node/series_assembler.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

#define INTERSLICE_SINK_RETURN_IF_ERROR(expr) \
  do {                                        \
    absl::Status _s = (expr);                 \
    if (!_s.ok()) return _s;                  \
  } while (0)

constexpr int kDefaultChunkBytes = 64 * 1024;
constexpr int kMaxFetchChunkBytes = 1 << 20;

using job::IsTerminalState;

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

// Reactors that only report an error (authentication, bad request).
template <typename Request>
class ErrorReadReactor : public grpc::ServerReadReactor<Request> {
 public:
  explicit ErrorReadReactor(const grpc::Status& status) {
    this->Finish(status);
  }
  void OnDone() override { delete this; }
};

template <typename Response>
class ErrorWriteReactor : public grpc::ServerWriteReactor<Response> {
 public:
  explicit ErrorWriteReactor(const grpc::Status& status) {
    this->Finish(status);
  }
  void OnDone() override { delete this; }
};

template <typename Request, typename Response>
class ErrorBidiReactor : public grpc::ServerBidiReactor<Request, Response> {
 public:
  explicit ErrorBidiReactor(const grpc::Status& status) {
    this->Finish(status);
  }
  void OnDone() override { delete this; }
};

// Receives one upload (header, then the files' chunks) into the spool, as
// UploadStream directs. Blocking: called on the I/O executor only, one call
// at a time per upload.
class UploadSink {
 public:
  UploadSink(JobManager* manager, Spool* spool, Metrics* metrics,
             const UploadStreamLimits& limits, bool ephemeral,
             std::optional<std::chrono::steady_clock::time_point> deadline,
             std::string owner)
      : manager_(manager),
        spool_(spool),
        metrics_(metrics),
        stream_(limits),
        ephemeral_(ephemeral),
        deadline_(deadline),
        owner_(std::move(owner)) {}
  ~UploadSink() { CloseFile(); }

  absl::Status Consume(const v1::UploadRequest& message) {
    UploadStep step;
    INTERSLICE_SINK_RETURN_IF_ERROR(stream_.Next(message, &step));
    if (step.header) {
      absl::StatusOr<std::shared_ptr<Job>> job =
          manager_->Admit(stream_.header(), ephemeral_, deadline_, owner_);
      if (!job.ok()) return job.status();
      job_ = *job;
      // The kind Admit made says which uploads, if any, it takes by name (a
      // fill's segmentation and label names).
      named_ = job_->kind()->named_uploads();
      received_.assign(named_.size(), false);
      return absl::OkStatus();
    }
    if (step.open_file) {
      INTERSLICE_SINK_RETURN_IF_ERROR(
          OpenFile(step.file_index, message.chunk().file_name()));
    }
    if (!step.data.empty()) {
      INTERSLICE_SINK_RETURN_IF_ERROR(Write(step.offset, step.data));
    }
    if (step.close_file) INTERSLICE_SINK_RETURN_IF_ERROR(SyncAndCloseFile());
    return absl::OkStatus();
  }

  // The client half-closed: the upload must be complete.
  absl::Status Finish() {
    INTERSLICE_SINK_RETURN_IF_ERROR(stream_.Finish());
    for (size_t n = 0; n < named_.size(); ++n) {
      if (received_[n]) continue;
      // The client's file names may carry patient data: not echoed.
      return absl::InvalidArgumentError(absl::StrCat(
          named_[n].field, " names none of the ", stream_.header().file_count(),
          " uploaded files (compared exactly with FileChunk.file_name)"));
    }
    FsyncDir(spool_->UploadDir(job_->id()));
    metrics_->BytesIn(static_cast<double>(stream_.bytes_received()));
    absl::Status s = manager_->Enqueue(job_);
    if (s.ok()) enqueued_ = true;
    return s;
  }

  // Deletes whatever was received unless the job was queued. Idempotent.
  void Abort() {
    CloseFile();
    if (job_ && !enqueued_ && !aborted_) {
      aborted_ = true;
      manager_->Abandon(job_);
    }
  }

  const std::shared_ptr<Job>& job() const { return job_; }
  bool enqueued() const { return enqueued_; }

 private:
  static void FsyncDir(const std::string& dir) {
    const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
    if (fd >= 0) {
      ::fsync(fd);
      ::close(fd);
    }
  }

  absl::Status OpenFile(int index, const std::string& client_name) {
    CloseFile();
    // Index-based names: the client's names may carry patient data, and the
    // reader's error messages quote file names.
    char name[32];
    std::snprintf(name, sizeof(name), "%06d.dcm", index);
    std::string path =
        (fs::path(spool_->UploadDir(job_->id())) / name).string();
    // A file the job takes by name (a fill's segmentation, its label names)
    // goes where its kind says, out of the series' folder level.
    const auto named = std::find_if(
        named_.begin(), named_.end(),
        [&](const auto& n) { return n.client_name == client_name; });
    if (named != named_.end()) {
      const size_t n = static_cast<size_t>(named - named_.begin());
      if (received_[n]) {
        return absl::InvalidArgumentError(absl::StrCat(
            "two uploaded files carry the name given as ", named->field));
      }
      received_[n] = true;
      const fs::path target =
          fs::path(spool_->UploadDir(job_->id())) / named->path;
      std::error_code ec;
      fs::create_directories(target.parent_path(), ec);
      if (ec) return absl::InternalError("cannot create an upload folder");
      path = target.string();
    }
    fd_ = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
    if (fd_ < 0) return absl::InternalError("cannot create an upload file");
    return absl::OkStatus();
  }

  absl::Status Write(int64_t offset, std::string_view data) {
    size_t done = 0;
    while (done < data.size()) {
      const ssize_t n =
          ::pwrite(fd_, data.data() + done, data.size() - done,
                   static_cast<off_t>(offset + static_cast<int64_t>(done)));
      if (n < 0) {
        if (errno == EINTR) continue;
        return absl::ResourceExhaustedError(
            "cannot write the upload to the spool (disk full?)");
      }
      done += static_cast<size_t>(n);
    }
    return absl::OkStatus();
  }

  absl::Status SyncAndCloseFile() {
    const bool synced = ::fsync(fd_) == 0;
    CloseFile();
    if (!synced) return absl::InternalError("cannot flush an upload file");
    return absl::OkStatus();
  }

  void CloseFile() {
    if (fd_ >= 0) {
      ::close(fd_);
      fd_ = -1;
    }
  }

  JobManager* const manager_;
  Spool* const spool_;
  Metrics* const metrics_;
  UploadStream stream_;
  // The uploads the job's kind takes by name, and which of them arrived.
  std::vector<job::NamedUpload> named_;
  std::vector<bool> received_;
  const bool ephemeral_;
  const std::optional<std::chrono::steady_clock::time_point> deadline_;
  const std::string owner_;
  std::shared_ptr<Job> job_;
  int fd_ = -1;
  bool enqueued_ = false;
  bool aborted_ = false;
};

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

// Reads one artifact chunk by chunk (on the I/O executor).
class ArtifactReader {
 public:
  ArtifactReader(std::string path, v1::ArtifactInfo info, int64_t offset,
                 int chunk_bytes)
      : path_(std::move(path)),
        info_(std::move(info)),
        offset_(offset),
        chunk_bytes_(chunk_bytes) {}

  // Fills `chunk` with the next piece; false at the end. Blocking.
  absl::StatusOr<bool> Next(v1::ArtifactChunk* chunk) {
    if (!opened_) {
      in_.open(path_, std::ios::binary);
      if (!in_) return absl::DataLossError("an artifact is missing");
      in_.seekg(offset_);
      opened_ = true;
    } else if (offset_ >= info_.size_bytes()) {
      return false;
    }
    chunk->Clear();
    if (first_) *chunk->mutable_info() = info_;
    first_ = false;
    const int64_t n =
        std::min<int64_t>(chunk_bytes_, info_.size_bytes() - offset_);
    std::string* data = chunk->mutable_data();
    data->resize(static_cast<size_t>(n));
    in_.read(data->data(), n);
    if (in_.gcount() != n) return absl::DataLossError("an artifact is short");
    chunk->set_offset(offset_);
    offset_ += n;
    return true;
  }

 private:
  const std::string path_;
  const v1::ArtifactInfo info_;
  int64_t offset_;
  const int chunk_bytes_;
  std::ifstream in_;
  bool opened_ = false;
  bool first_ = true;
};

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

UploadStreamLimits InterSliceService::upload_limits() const {
  UploadStreamLimits limits;
  limits.max_chunk_bytes = options_.max_chunk_bytes;
  limits.max_upload_bytes = manager_->options().max_upload_bytes;
  return limits;
}

absl::StatusOr<Caller> InterSliceService::Authenticate(
    grpc::CallbackServerContext* context) const {
  absl::StatusOr<Caller> caller = IdentifyCaller(auth_, *context);
  if (!caller.ok()) {
    spdlog::warn("refused a call from {}: missing or wrong bearer token",
                 LogSafe(context->peer()));
    AuditEvent e;
    e.event = "auth.refused";
    e.outcome = AuditOutcome::kMinorFailure;
    e.source = context->peer();
    e.detail = "missing or wrong bearer token";
    Audit(std::move(e));
  }
  return caller;
}

void InterSliceService::Audit(AuditEvent event) const {
  if (options_.audit != nullptr) options_.audit->Record(std::move(event));
}

std::optional<std::string> InterSliceService::ForwardTarget(
    const grpc::CallbackServerContext& context,
    const std::string& job_id) const {
  if (forwarder_ == nullptr || manager_->Find(job_id) != nullptr) {
    return std::nullopt;
  }
  return forwarder_->Route(context, job_id);
}

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

grpc::ServerUnaryReactor* InterSliceService::Find(
    grpc::CallbackServerContext* context, const v1::FindRequest* request,
    v1::FindResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // A PACS's index lists every patient's studies: not any one caller's.
  if (!caller->admin && !caller->identity.empty()) {
    reactor->Finish(grpc::Status(
        grpc::PERMISSION_DENIED,
        "Find lists a DICOM peer's studies: admin identities only"));
    return reactor;
  }
  std::shared_ptr<node::PeerClient> peer;
  if (peers_ != nullptr) peer = peers_->Find(request->peer());
  if (peer == nullptr) {
    reactor->Finish(ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("peer: unknown DICOM peer \"", request->peer(),
                     "\" (see the server's --dicom-peers file)"))));
    return reactor;
  }
  node::FindQuery query{request->patient_id(), request->study_date(),
                        request->modality(), request->accession_number()};
  if (absl::Status s = node::CheckFindQuery(query); !s.ok()) {
    reactor->Finish(ToGrpcStatus(s));
    return reactor;
  }
  const auto cap = [](int32_t asked, int fallback, int most) {
    if (asked <= 0) return fallback;
    return std::min<int>(asked, most);
  };
  node::FindLimits limits;
  limits.max_studies = cap(request->max_studies(), 100, 1000);
  limits.max_series = cap(request->max_series(), 1000, 10000);
  if (dicom_queries_in_flight_.fetch_add(1) >= kMaxDicomQueries) {
    dicom_queries_in_flight_.fetch_sub(1);
    reactor->Finish(grpc::Status(
        grpc::RESOURCE_EXHAUSTED,
        absl::StrCat("already ", kMaxDicomQueries,
                     " DICOM queries in progress; try again shortly")));
    return reactor;
  }
  dicom_queries_->Post([this, reactor, response, peer, query, limits] {
    const auto started = std::chrono::steady_clock::now();
    absl::StatusOr<node::FindResult> found = peer->Find(query, limits);
    dicom_queries_in_flight_.fetch_sub(1);
    const double seconds = std::chrono::duration<double>(
                               std::chrono::steady_clock::now() - started)
                               .count();
    if (!found.ok()) {
      spdlog::info("find on peer {} failed after {:.2f} s: {}",
                   LogSafe(peer->name()), seconds,
                   RedactPhi(found.status().message()));
      reactor->Finish(ToGrpcStatus(found.status()));
      return;
    }
    int series = 0;
    for (node::FoundStudy& s : found->studies) {
      v1::FoundStudy* study = response->add_studies();
      study->set_study_instance_uid(std::move(s.study_instance_uid));
      study->set_patient_id(std::move(s.patient_id));
      study->set_study_date(std::move(s.study_date));
      study->set_accession_number(std::move(s.accession_number));
      study->set_study_description(std::move(s.study_description));
      study->set_modalities_in_study(std::move(s.modalities));
      for (node::FoundSeries& r : s.series) {
        v1::FoundSeries* out = study->add_series();
        out->set_series_instance_uid(std::move(r.series_instance_uid));
        out->set_modality(std::move(r.modality));
        out->set_series_number(std::move(r.series_number));
        out->set_series_description(std::move(r.series_description));
        out->set_instances(r.instances);
        ++series;
      }
    }
    response->set_truncated(found->truncated);
    response->set_max_studies(limits.max_studies);
    response->set_max_series(limits.max_series);
    // Counts only: no keys, no UIDs.
    spdlog::info("find on peer {}: {} study(ies), {} series{} in {:.2f} s",
                 LogSafe(peer->name()), response->studies_size(), series,
                 found->truncated ? " (truncated at the caps)" : "", seconds);
    reactor->Finish(grpc::Status::OK);
  });
  return reactor;
}

grpc::ServerUnaryReactor* InterSliceService::ListKept(
    grpc::CallbackServerContext* context, const v1::ListKeptRequest* request,
    v1::ListKeptResponse* response) {
  (void)request;
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // Every sender's series, UIDs included: not any one caller's.
  if (!caller->admin && !caller->identity.empty()) {
    reactor->Finish(grpc::Status(
        grpc::PERMISSION_DENIED,
        "ListKept lists the DICOM listener's series: admin identities only"));
    return reactor;
  }
  if (assembler_ == nullptr) {
    reactor->Finish(grpc::Status(
        grpc::FAILED_PRECONDITION,
        "the server has no DICOM listener (--dicom-listen): nothing is kept"));
    return reactor;
  }
  io_->Post([this, reactor, response, identity = caller->identity,
             source = context->peer()] {
    for (node::KeptSeries& k : assembler_->ListKept()) {
      v1::ListKeptResponse::Series* s = response->add_series();
      s->set_id(std::move(k.id));
      s->set_calling_ae(std::move(k.calling_ae));
      s->set_called_ae(std::move(k.called_ae));
      s->set_modality(std::move(k.modality));
      s->set_instance_count(k.instances);
      s->set_kept_since_unix_ms(k.kept_since_unix_ms);
      s->set_why(std::move(k.why));
      s->set_job_id(std::move(k.job_id));
      s->set_study_instance_uid(std::move(k.study_uid));
      s->set_series_instance_uid(std::move(k.series_uid));
      s->set_state(std::move(k.state));
    }
    AuditEvent listed;
    listed.event = "kept.listed";
    listed.identity = identity;
    listed.source = source;
    listed.count = response->series_size();
    Audit(std::move(listed));
    reactor->Finish(grpc::Status::OK);
  });
  return reactor;
}

grpc::ServerUnaryReactor* InterSliceService::RerunKept(
    grpc::CallbackServerContext* context, const v1::RerunKeptRequest* request,
    v1::RerunKeptResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  // It makes jobs of any sender's series.
  if (!caller->admin && !caller->identity.empty()) {
    reactor->Finish(grpc::Status(
        grpc::PERMISSION_DENIED,
        "RerunKept runs the DICOM listener's series: admin identities only"));
    return reactor;
  }
  if (request->all_unmatched() == !request->id().empty()) {
    reactor->Finish(
        grpc::Status(grpc::INVALID_ARGUMENT,
                     "give either the id of one kept series or all_unmatched"));
    return reactor;
  }
  if (assembler_ == nullptr) {
    reactor->Finish(grpc::Status(
        grpc::FAILED_PRECONDITION,
        "the server has no DICOM listener (--dicom-listen): nothing is kept"));
    return reactor;
  }
  io_->Post([this, reactor, response, id = request->id(),
             all = request->all_unmatched(), identity = caller->identity,
             source = context->peer()] {
    absl::StatusOr<std::vector<node::KeptRerun>> reruns;
    if (all) {
      reruns = assembler_->RerunAllUnmatched();
    } else if (absl::StatusOr<node::KeptRerun> one = assembler_->RerunKept(id);
               one.ok()) {
      reruns = std::vector<node::KeptRerun>{*std::move(one)};
    } else {
      reruns = one.status();
    }
    AuditEvent event;
    event.event = "kept.rerun";
    event.identity = identity;
    event.source = source;
    if (!reruns.ok()) {
      event.outcome = AuditOutcome::kMinorFailure;
      event.detail = std::string(reruns.status().message());
      Audit(std::move(event));
      reactor->Finish(ToGrpcStatus(reruns.status()));
      return;
    }
    for (const node::KeptRerun& r : *reruns) {
      if (!r.job_id.empty()) response->add_job_ids(r.job_id);
      if (!r.not_matched.empty()) {
        response->add_not_matched(absl::StrCat(r.id, ": ", r.not_matched));
      }
    }
    event.count = response->job_ids_size();
    event.detail =
        absl::StrCat(all ? "all unmatched" : "one series", ": ",
                     response->job_ids_size(), " job(s) made, ",
                     response->not_matched_size(), " without a matching rule");
    Audit(std::move(event));
    reactor->Finish(grpc::Status::OK);
  });
  return reactor;
}

grpc::ServerUnaryReactor* InterSliceService::GetServerInfo(
    grpc::CallbackServerContext* context, const v1::ServerInfoRequest* request,
    v1::ServerInfo* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok()) {
    reactor->Finish(ToGrpcStatus(caller.status()));
    return reactor;
  }
  response->set_version(options_.version);
  response->set_api("interslice.v1");
  for (const TransferSyntaxInfo& syntax : DecodableTransferSyntaxes()) {
    v1::TransferSyntax* t = response->add_transfer_syntaxes();
    t->set_uid(syntax.uid);
    t->set_name(syntax.name);
  }
  const ManagerOptions& m = manager_->options();
  v1::Limits* limits = response->mutable_limits();
  limits->set_max_upload_bytes(m.max_upload_bytes);
  limits->set_max_output_voxels(m.max_output_voxels);
  limits->set_max_queued_jobs(m.max_queued_jobs);
  limits->set_workers(m.workers);
  limits->set_threads_per_job(m.threads_per_job);
  limits->set_max_chunk_bytes(options_.max_chunk_bytes);
  limits->set_result_retention_seconds(m.retention_seconds);
  limits->set_spool_quota_bytes(spool_->quota_bytes());
  limits->set_max_concurrent_uploads(options_.uploads.max_concurrent);
  limits->set_max_uploads_per_client(options_.uploads.max_per_peer);
  limits->set_upload_idle_timeout_seconds(
      options_.uploads.idle_timeout_seconds);
  limits->set_upload_timeout_seconds(options_.uploads.total_timeout_seconds);
  for (const char* s : {"linear", "cg", "direct", "morph"})
    response->add_methods(s);
  for (const char* s : {"nii", "nrrd", "nii-uncompressed"}) {
    response->add_volume_formats(s);
  }
  for (const char* s : {"stl", "ply", "obj"}) response->add_mesh_formats(s);
  const auto* descriptor =
      v1::ServerInfo::descriptor()->file()->FindServiceByName("InterSlice");
  for (int i = 0; i < descriptor->method_count(); ++i) {
    response->add_rpcs(descriptor->method(i)->name());
  }
  response->set_auth_required(auth_.tokens_required());
  response->set_draining(manager_->draining());
  reactor->Finish(grpc::Status::OK);
  return reactor;
}

}  // namespace interslice::server
