// JobManager (server/engine/job_manager.h): running one job. Its start,
// retrieval from a DICOM peer, its kind run in a worker process (or in this
// process), and how it ended: published, failed or back in the queue.
#include <unistd.h>

#include <algorithm>
#include <filesystem>

#include "absl/strings/str_cat.h"
#include "job/job.h"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/redact.h"
#include "server/engine/artifacts.h"
#include "server/engine/job_manager.h"
#include "server/engine/job_manager_internal.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

using job_manager_internal::AuditJob;

const char* OutcomeName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_SUCCEEDED:
      return "succeeded";
    case v1::JOB_STATE_CANCELLED:
      return "cancelled";
    default:
      return "failed";
  }
}

}  // namespace

void JobManager::RecordSource(Job& job, const job::SourceSeries& source) {
  job.Update([&source](JobRecord& r) {
    v1::JobStatus* s = r.mutable_status();
    s->set_modality(source.modality);
    s->set_instance_count(static_cast<int32_t>(
        std::min<int64_t>(source.instance_count, INT32_MAX)));
    s->set_study_instance_uid(source.study_instance_uid);
    s->set_series_instance_uid(source.series_instance_uid);
  });
}

void JobManager::RunOne(const std::shared_ptr<Job>& job) {
  const std::string& id = job->id();
  v1::JobSpec wire;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    wire = job->record_.spec();
    job->started_ = std::chrono::steady_clock::now();
  }
  job->Update([](JobRecord& r) {
    // Counted (and persisted below) before the job starts: if it takes the
    // server down, the restart sees this start.
    r.set_attempts(r.attempts() + 1);
    v1::JobStatus* s = r.mutable_status();
    s->set_state(v1::JOB_STATE_RUNNING);
    s->set_started_unix_ms(UnixMillisNow());
    s->mutable_progress()->set_stage("read");
    s->mutable_progress()->set_stage_percent(0);
    s->mutable_progress()->set_queue_position(-1);
  });
  Persist(job);
  spdlog::info("job={} started", id);

  absl::StatusOr<job::JobResult> result = Execute(job, wire);

  bool shutdown_cancelled;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    shutdown_cancelled = job->shutdown_cancelled_;
  }
  if (!result.ok() && shutdown_cancelled && !job->ephemeral()) {
    // Stopped by a drain, not by its owner: keep the upload and run it
    // after the restart.
    spool_->RemoveOutputs(id);
    job->Update([](JobRecord& r) {
      // A drain is not a crash: this start does not count.
      r.set_attempts(std::max(0, r.attempts() - 1));
      r.mutable_status()->set_state(v1::JOB_STATE_QUEUED);
      r.mutable_status()->set_started_unix_ms(0);
      r.mutable_status()->mutable_progress()->set_stage("queued");
    });
    Persist(job);
    return;
  }

  const int64_t upload_bytes = job->record_.upload_bytes();
  spool_->RemoveUploads(id);
  spool_->Release(upload_bytes);
  if (result.ok()) {
    // Before publishing: the status, the quota and the deliveries see only
    // what is kept (server/engine/spool.h).
    JobRecord record;
    {
      std::lock_guard<std::mutex> lock(job->mu_);
      record = job->record_;
    }
    if (const int64_t bytes = RemoveArtifactsNotAskedFor(record, &*result);
        bytes > 0) {
      spdlog::info("job={} kept only what it was asked for: {} bytes not kept",
                   id, bytes);
    }
  }
  const int64_t now = UnixMillisNow();
  const int64_t expires = now + options_.retention_seconds * 1000;
  absl::Status published =
      result.ok() ? Publish(job, *result, now, expires) : result.status();
  if (!published.ok()) FailJob(job, published, now, expires);
}

absl::StatusOr<job::JobResult> JobManager::Execute(
    const std::shared_ptr<Job>& job, const v1::JobSpec& wire) {
  const std::string& id = job->id();
  // The job's kind, made once (Admit, Recover); then pointed at its folders.
  absl::Status ready =
      job->kind() != nullptr ? absl::OkStatus() : job->kind_error();
  // A series named on a DICOM peer is retrieved into the upload folder
  // first; then the job runs as if it had been uploaded.
  if (ready.ok() && wire.has_pacs_source() &&
      !wire.pacs_source().peer().empty()) {
    job->Update([](JobRecord& r) {
      r.mutable_status()->mutable_progress()->set_stage("retrieve");
    });
    ready = RetrieveFromPeer(job, wire.pacs_source());
  }
  if (!ready.ok()) return ready;
  job::JobKind& work = *job->kind();
  bool omit_files_dicom_objects_carry;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    omit_files_dicom_objects_carry = DeliversOnlyDicomToPeers(job->record_);
  }
  const std::string upload_dir = spool_->UploadDir(id);
  const std::string output_dir = spool_->OutputDir(id);
  ComputeContext context;
  context.threads = options_.threads_per_job;
  context.cancel = &job->token_;
  const auto started = std::chrono::steady_clock::now();
  const bool in_process = !options_.isolate_jobs;
  const float threshold = wire.threshold();
  context.progress = [job, started, in_process,
                      threshold](const ProgressEvent& e) {
    const std::chrono::duration<double> elapsed =
        std::chrono::steady_clock::now() - started;
    job->Update([&](JobRecord& r) {
      v1::Progress* p = r.mutable_status()->mutable_progress();
      p->set_stage(e.stage);
      p->set_stage_percent(100.0 * e.fraction);
      p->set_iteration(e.iteration);
      p->set_relative_residual(e.relative_residual);
      p->set_energy(e.energy);
      p->set_elapsed_seconds(elapsed.count());
    });
    if (in_process) InjectTestFault(e.stage, threshold);
  };
  // A deadline that passed while queued fails fast, without reading.
  if (absl::Status early = job->token_.Check(); !early.ok()) return early;
  if (options_.isolate_jobs) {
    spool::v1::WorkerRequest request;
    *request.mutable_spec() = wire;
    {
      std::lock_guard<std::mutex> lock(job->mu_);
      request.set_deadline_unix_ms(job->record_.deadline_unix_ms());
    }
    request.set_input_dir(upload_dir);
    request.set_output_dir(output_dir);
    request.set_max_output_voxels(options_.max_output_voxels);
    request.set_threads(options_.threads_per_job);
    request.set_server_pid(::getpid());
    request.set_omit_files_dicom_objects_carry(omit_files_dicom_objects_carry);
    WorkerOutcome outcome;
    absl::StatusOr<job::JobResult> result = RunInWorkerProcess(
        request, context, options_.worker, &outcome,
        [job](const job::SourceSeries& source) { RecordSource(*job, source); });
    if (outcome.crashed) {
      spdlog::error(
          "job={} worker process crashed (signal {}) during stage {}; the "
          "job failed, the server carries on",
          id, outcome.signal,
          outcome.last_stage.empty() ? "start" : outcome.last_stage);
    }
    return result;
  }
  if (absl::Status s =
          work.UseSpool(upload_dir, output_dir, options_.max_output_voxels);
      !s.ok()) {
    return s;
  }
  if (omit_files_dicom_objects_carry) work.OmitFilesDicomObjectsCarry();
  // As the worker process does (job_worker.cc): which series, for the
  // status; the job's own read reports a folder without one.
  if (absl::StatusOr<job::SourceSeries> source = job::DescribeSourceSeries(
          upload_dir, wire.series_instance_uid(),
          ComputeContext{.threads = context.threads, .cancel = context.cancel});
      source.ok()) {
    RecordSource(*job, *source);
  }
  return work.Run(context);
}

absl::Status JobManager::Publish(const std::shared_ptr<Job>& job,
                                 const job::JobResult& result, int64_t now,
                                 int64_t expires) {
  const std::string& id = job->id();
  for (const StageTiming& s : result.stages) {
    metrics_->StageSeconds(s.stage, s.seconds);
  }
  int64_t result_bytes = 0;
  absl::StatusOr<std::vector<v1::ArtifactInfo>> artifacts = DescribeArtifacts(
      result.artifacts, options_.threads_per_job, &result_bytes);
  if (!artifacts.ok()) return artifacts.status();
  spool_->Add(result_bytes);
  const std::string& json = result.report_json;
  // One delivery per destination, of every DICOM file the job wrote.
  std::vector<std::string> dicom_files;
  std::vector<v1::Delivery> deliveries;
  std::vector<std::string> send_to;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    send_to.assign(job->record_.spec().send_to().begin(),
                   job->record_.spec().send_to().end());
  }
  if (outbox_ != nullptr && !send_to.empty()) {
    dicom_files = DicomArtifactFiles(*artifacts, spool_->OutputDir(id));
    for (const std::string& peer : send_to) {
      v1::Delivery d;
      d.set_peer(peer);
      d.set_state(v1::Delivery::PENDING);
      d.set_instances_total(static_cast<int32_t>(dicom_files.size()));
      deliveries.push_back(d);
    }
  }
  job->Update([&](JobRecord& r) {
    for (const v1::Delivery& d : deliveries) {
      *r.mutable_status()->add_deliveries() = d;
    }
    v1::JobStatus* s = r.mutable_status();
    s->set_state(v1::JOB_STATE_SUCCEEDED);
    s->set_finished_unix_ms(now);
    s->set_expires_unix_ms(expires);
    s->mutable_progress()->set_stage("done");
    s->mutable_progress()->set_stage_percent(100);
    for (const auto& a : *artifacts) *s->add_artifacts() = a;
    s->set_report_json(json);
    r.set_result_bytes(result_bytes);
  });
  Persist(job);
  for (const v1::Delivery& d : deliveries) {
    outbox_->Add(id, d, dicom_files, now);
  }
  metrics_->JobFinished("succeeded");
  spdlog::info("job={} succeeded: {} artifact(s), {} bytes", id,
               artifacts->size(), result_bytes);
  AuditJob(options_.audit, job, "job.succeeded", AuditOutcome::kSuccess,
           absl::StrCat(artifacts->size(), " artifact(s), ", result_bytes,
                        " bytes"));
  return absl::OkStatus();
}

void JobManager::FailJob(const std::shared_ptr<Job>& job,
                         const absl::Status& cause, int64_t now,
                         int64_t expires) {
  const std::string& id = job->id();
  // A write that failed for want of space: RESOURCE_EXHAUSTED "disk full"
  // rather than INTERNAL with a server path (asked before the outputs go).
  const absl::Status error =
      DiskFullAsResourceExhausted(cause, spool_->FileSystemFull());
  spool_->RemoveOutputs(id);
  const bool cancelled = error.code() == absl::StatusCode::kCancelled;
  const std::string message = RedactPhi(error.message());
  job->Update([&](JobRecord& r) {
    v1::JobStatus* s = r.mutable_status();
    s->set_state(cancelled ? v1::JOB_STATE_CANCELLED : v1::JOB_STATE_FAILED);
    s->set_error_code(static_cast<int>(error.code()));
    s->set_error_message(message);
    s->set_finished_unix_ms(now);
    s->set_expires_unix_ms(expires);
    s->mutable_progress()->set_stage("done");
    r.set_result_bytes(0);
  });
  Persist(job);
  metrics_->JobFinished(OutcomeName(job->Snapshot(false).state()));
  spdlog::info("job={} {}: {} ({})", id, cancelled ? "cancelled" : "failed",
               absl::StatusCodeToString(error.code()), message);
  AuditJob(
      options_.audit, job, cancelled ? "job.cancelled" : "job.failed",
      cancelled ? AuditOutcome::kMinorFailure : AuditOutcome::kSeriousFailure,
      absl::StrCat(absl::StatusCodeToString(error.code()), ": ", message));
}

absl::Status JobManager::RetrieveFromPeer(const std::shared_ptr<Job>& job,
                                          const v1::PacsSeriesSource& source) {
  const std::string& id = job->id();
  if (series_source_ == nullptr) {
    return absl::FailedPreconditionError("the server has no DICOM peers");
  }
  // A rerun after a restart starts from an empty folder.
  spool_->RemoveUploads(id);
  std::error_code ec;
  fs::create_directories(spool_->UploadDir(id), ec);
  const auto started = std::chrono::steady_clock::now();
  absl::StatusOr<RetrievedSeries> result = series_source_->Retrieve(
      source, spool_->UploadDir(id),
      std::min(options_.max_upload_bytes, spool_->quota_bytes()), &job->token_);
  if (!result.ok()) {
    spool_->RemoveUploads(id);
    spdlog::info("job={} retrieval from peer {} failed: {}", id,
                 LogSafe(source.peer()), RedactPhi(result.status().message()));
    return result.status();
  }
  // Accounted like an upload (released when the job ends).
  spool_->Add(result->bytes);
  job->Update([&](JobRecord& r) { r.set_upload_bytes(result->bytes); });
  spdlog::info(
      "job={} retrieved {} instance(s), {} bytes from peer {} in "
      "{:.2f} s",
      id, result->instances, result->bytes, LogSafe(source.peer()),
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started)
          .count());
  return absl::OkStatus();
}

}  // namespace interslice::server
