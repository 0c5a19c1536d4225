// Jobs: admission control, a bounded queue, worker threads running RunJob,
// status fan-out to watchers, spool persistence and retention.
//
// Threading: `workers` threads each run one job at a time with
// ComputeContext{threads = threads_per_job, cancel = the job's token}. A
// ticker thread bumps the status of queued and running jobs once a second
// (so watchers see progress at least that often, even during stages that
// report rarely) and deletes expired results. Methods marked "blocking" touch
// the disk and must not be called from a gRPC reactor callback; the service
// runs them on its I/O executor.
//
// Lock order: JobManager::mu_ before Job::mu_; subscriptions are fired with
// neither held.
#ifndef INTERSLICE_SERVER_ENGINE_JOB_MANAGER_H_
#define INTERSLICE_SERVER_ENGINE_JOB_MANAGER_H_

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "interslice/v1/interslice.pb.h"
#include "job/job.h"
#include "server/base/metrics.h"
#include "server/engine/job.h"
#include "server/engine/job_worker.h"
#include "server/engine/peer_services.h"
#include "server/engine/spool.h"

namespace interslice::server {

class AuditLog;

struct ManagerOptions {
  // Run each job's compute in a supervised worker process (see
  // server/engine/job_worker.h), so that a crash inside a decoder fails that
  // job only. false runs jobs on the worker threads of this process.
  bool isolate_jobs = true;
  WorkerOptions worker;
  // A detached job that was running when the server stopped (killed, power
  // cut) runs again after the restart, up to this many starts in all; then
  // it fails with the reason (a job that takes the server down must not
  // crash-loop it).
  int max_attempts = 3;
  int workers = 1;
  int threads_per_job = 1;
  int max_queued_jobs = 16;
  int64_t max_upload_bytes = int64_t{2} << 30;
  int64_t max_output_voxels = int64_t{1} << 30;
  int64_t retention_seconds = 24 * 3600;
  // Where job submissions, outcomes and deliveries are recorded (may be
  // null: no audit trail). Outlives the manager.
  AuditLog* audit = nullptr;
};

class JobManager {
 public:
  JobManager(const ManagerOptions& options, Spool* spool, Metrics* metrics);
  ~JobManager();  // Shutdown(0) if still running

  const ManagerOptions& options() const { return options_; }

  // The DICOM node's peers (engine/peer_services.h), both null when the
  // server has none: then JobSpec.send_to and pacs_source are
  // INVALID_ARGUMENT. Set before Recover(): Recover() hands the outbox the
  // deliveries still PENDING, a successful job with send_to hands it one
  // delivery per peer, and results are kept past retention while a
  // delivery is PENDING. `source` retrieves JobSpec.pacs_source.
  void SetPeerServices(ResultOutbox* outbox, PeerSeriesSource* source) {
    outbox_ = outbox;
    series_source_ = source;
  }
  // Blocking. The outbox reports a delivery's new state: stored in the
  // job's status (JobStatus.deliveries, matched by peer) and spool record.
  // An Interpolate job whose call ended is deleted once none is PENDING.
  void UpdateDelivery(const std::string& job_id, const v1::Delivery& delivery);

  // Blocking. Reloads the spool: finished jobs stay fetchable, queued jobs
  // are queued again, jobs that were running when the process died are
  // marked FAILED (ABORTED) rather than retried, so that a job that crashes
  // the server cannot crash it again in a loop.
  absl::Status Recover();
  void Start();

  // Blocking. Checks the header (limits, spool quota, spec; and that the
  // queue is not full already, so that a client does not upload in vain),
  // reserves the upload's spool space and creates the job's folder.
  // RESOURCE_EXHAUSTED, INVALID_ARGUMENT, UNIMPLEMENTED or UNAVAILABLE
  // (draining). No queue slot is taken yet: uploads in progress are bounded
  // by the service (UploadGuard). `deadline`: Interpolate's call deadline;
  // detached jobs use options.deadline_seconds. `owner`: the caller's
  // identity.
  absl::StatusOr<std::shared_ptr<Job>> Admit(
      const v1::UploadHeader& header, bool ephemeral,
      std::optional<std::chrono::steady_clock::time_point> deadline,
      const std::string& owner);
  // Blocking. The upload is complete and verified: take a queue slot,
  // persist and queue. RESOURCE_EXHAUSTED when the queue is full,
  // UNAVAILABLE for an Interpolate job while draining; on error the caller
  // abandons the job.
  absl::Status Enqueue(const std::shared_ptr<Job>& job);
  // Blocking. A detached job on DICOM files that are already in the spool
  // (a complete series the DICOM listener received, in `files_dir`): admitted
  // and queued like an upload (same limits and errors), its files
  // hard-linked into the job's upload folder (`files_dir` is left as it
  // is; the caller deletes it). `origin` is recorded in the job's status.
  // Returns the job id.
  // `named_files`: exactly the files the job's kind takes by name
  // (job::JobKind::named_uploads), each under the name the spec gives it ->
  // its path here (hard-linked where the kind keeps it; left as it is). A
  // fill job (spec.fill set) takes the received SEG or RTSTRUCT under
  // spec.fill.segmentation_file; the series in `files_dir` is its
  // reference. Interpolation jobs: none. INVALID_ARGUMENT for a missing or
  // extra file.
  absl::StatusOr<std::string> SubmitLocalFiles(
      const v1::JobSpec& spec, const std::string& files_dir,
      const std::string& owner, const std::string& origin,
      const std::map<std::string, std::string>& named_files = {});
  // Blocking. The upload failed: delete everything.
  void Abandon(const std::shared_ptr<Job>& job);
  // Blocking. An Interpolate call ended: cancel the job if it still runs and
  // delete its files (now, or when its worker lets go of it).
  void Discard(const std::shared_ptr<Job>& job);

  std::shared_ptr<Job> Find(const std::string& id);
  // Appended to the ids of new jobs: names this replica as their owner
  // (server/net/grpc/forwarding.h).
  void SetJobIdSuffix(std::string suffix);
  // Blocking (persists a cancelled queued job).
  absl::StatusOr<v1::JobStatus> Cancel(const std::string& id);
  // Detached jobs, newest first, without report_json; only those of
  // `owner` unless it is null.
  std::vector<v1::JobStatus> List(bool include_finished,
                                  const std::string* owner = nullptr);

  // Refuse new jobs from now on. Queued Interpolate jobs end at once with
  // UNAVAILABLE (their callers can retry elsewhere); queued detached jobs
  // stay queued on disk.
  void BeginDrain();
  bool draining();
  // Blocking: waits up to `grace` for running jobs, then cancels them
  // (detached ones go back to QUEUED on disk and run after a restart), then
  // stops the threads.
  void Shutdown(std::chrono::milliseconds grace);

  int queued();
  int running();

 private:
  void WorkerLoop();
  void TickerLoop();
  // Runs a queued job and records how it ended.
  void RunOne(const std::shared_ptr<Job>& job);
  // The job's work: retrieval from a peer if it names one, then its kind run
  // in a worker process (or in this process without isolation).
  absl::StatusOr<job::JobResult> Execute(const std::shared_ptr<Job>& job,
                                         const v1::JobSpec& wire);
  // Records a successful result: artifacts hashed and listed, deliveries
  // queued. An error (an unreadable artifact) leaves the job to FailJob.
  absl::Status Publish(const std::shared_ptr<Job>& job,
                       const job::JobResult& result, int64_t now,
                       int64_t expires);
  // The series the job reads, into its status (JobStatus 18..21).
  static void RecordSource(Job& job, const job::SourceSeries& source);
  void FailJob(const std::shared_ptr<Job>& job, const absl::Status& error,
               int64_t now, int64_t expires);
  void Persist(const std::shared_ptr<Job>& job);
  void PublishGauges();  // with mu_ held
  void RemoveFinished(const std::shared_ptr<Job>& job);
  // JobSpec.pacs_source into the job's upload folder.
  absl::Status RetrieveFromPeer(const std::shared_ptr<Job>& job,
                                const v1::PacsSeriesSource& source);

  const ManagerOptions options_;
  ResultOutbox* outbox_ = nullptr;
  PeerSeriesSource* series_source_ = nullptr;
  Spool* const spool_;
  Metrics* const metrics_;

  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::string, std::shared_ptr<Job>> jobs_;
  std::deque<std::shared_ptr<Job>> queue_;
  int uploading_ = 0;  // admitted, upload not complete
  std::string job_id_suffix_;
  int reserved_ = 0;  // queue slots taken by jobs being persisted
  int running_ = 0;
  bool draining_ = false;
  bool stopping_ = false;
  std::vector<std::thread> workers_;
  std::thread ticker_;
};

int64_t UnixMillisNow();

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_ENGINE_JOB_MANAGER_H_
