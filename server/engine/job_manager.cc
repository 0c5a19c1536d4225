// JobManager (server/engine/job_manager.h): recovery of the spool, the
// queue and its workers, deliveries, cancellation, listing, draining,
// shutdown and the ticker. Admission is in admission.cc, running one job in
// job_runner.cc.
#include "server/engine/job_manager.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "job/job.h"
#include "job/wire.h"
#include "server/base/audit.h"
#include "server/base/redact.h"
#include "server/engine/artifacts.h"
#include "server/engine/job_manager_internal.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace job_manager_internal {

void AuditJob(AuditLog* audit, const std::shared_ptr<Job>& job,
              const char* event, AuditOutcome outcome,
              const std::string& detail) {
  if (audit == nullptr) return;
  AuditEvent e;
  e.event = event;
  e.outcome = outcome;
  e.identity = job->owner();
  const v1::JobStatus status = job->Snapshot(false);
  e.source = status.origin();
  // The peer the job pulls its series from (spec.pacs_source; issue 39: the
  // trail did not say where a job's images came from).
  e.peer = status.source().pacs_peer();
  e.job = job->id();
  e.detail = detail;
  audit->Record(std::move(e));
}

}  // namespace job_manager_internal

namespace {

using job::IsTerminalState;
using job_manager_internal::AuditJob;

// A delivery of the job's results to a DICOM peer is still to be made: the
// results must stay.
bool HasPendingDelivery(const JobRecord& record) {
  for (const v1::Delivery& d : record.status().deliveries()) {
    if (d.state() == v1::Delivery::PENDING) return true;
  }
  return false;
}

std::chrono::steady_clock::time_point SteadyFromUnixMillis(int64_t ms) {
  const int64_t delta = ms - UnixMillisNow();
  return std::chrono::steady_clock::now() + std::chrono::milliseconds(delta);
}

}  // namespace

int64_t UnixMillisNow() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

JobManager::JobManager(const ManagerOptions& options, Spool* spool,
                       Metrics* metrics)
    : options_(options), spool_(spool), metrics_(metrics) {}

JobManager::~JobManager() { Shutdown(std::chrono::milliseconds(0)); }

absl::Status JobManager::Recover() {
  absl::StatusOr<std::vector<JobRecord>> records = spool_->LoadRecords();
  if (!records.ok()) return records.status();
  std::sort(records->begin(), records->end(),
            [](const JobRecord& a, const JobRecord& b) {
              return a.status().created_unix_ms() <
                     b.status().created_unix_ms();
            });
  int requeued = 0, aborted = 0, kept = 0;
  for (JobRecord& record : *records) {
    const std::string id = record.status().job_id();
    if (record.ephemeral()) {
      spool_->RemoveJob(id);
      continue;
    }
    std::shared_ptr<Job> job(new Job(id, false, record.owner()));
    // The kind once, from the record (one written by an older version may
    // not make one: the job then fails when it runs, saying why).
    if (absl::StatusOr<std::unique_ptr<job::JobKind>> kind =
            job::MakeJobFromWire(record.spec());
        kind.ok()) {
      job->kind_ = *std::move(kind);
    } else {
      job->kind_error_ = kind.status();
    }
    const v1::JobState state = record.status().state();
    const bool interrupted = state == v1::JOB_STATE_RUNNING;
    if (interrupted && record.attempts() < options_.max_attempts) {
      // Killed mid-job (kill -9, power cut, OOM killer): the upload is
      // still in the spool, so run it again; the attempts already counted
      // bound how often.
      v1::JobStatus* s = record.mutable_status();
      s->set_state(v1::JOB_STATE_QUEUED);
      s->set_started_unix_ms(0);
      s->mutable_progress()->set_stage("queued");
      s->set_sequence(s->sequence() + 1);
      spool_->RemoveOutputs(id);
      job->record_ = record;
      if (absl::Status st = spool_->WriteRecord(record); !st.ok()) {
        spdlog::error("job={} cannot persist recovery: {}", id,
                      RedactPhi(st.message()));
      }
      spdlog::warn(
          "job={} was running when the server stopped; running it again "
          "(start {} of at most {})",
          id, record.attempts() + 1, options_.max_attempts);
      ++kept;
    } else if (interrupted || state == v1::JOB_STATE_UPLOADING) {
      v1::JobStatus* s = record.mutable_status();
      s->set_state(v1::JOB_STATE_FAILED);
      s->set_error_code(static_cast<int>(absl::StatusCode::kAborted));
      s->set_error_message(
          interrupted
              ? absl::StrFormat(
                    "the server stopped while the job was running, %d "
                    "time(s); it is not run again (it may be what stops the "
                    "server)",
                    record.attempts())
              : "the server stopped while the job was being uploaded; "
                "submit it again");
      s->set_finished_unix_ms(UnixMillisNow());
      s->set_expires_unix_ms(UnixMillisNow() +
                             options_.retention_seconds * 1000);
      s->set_sequence(s->sequence() + 1);
      spool_->RemoveUploads(id);
      spool_->RemoveOutputs(id);
      job->record_ = record;
      if (absl::Status st = spool_->WriteRecord(record); !st.ok()) {
        spdlog::error("job={} cannot persist recovery: {}", id,
                      RedactPhi(st.message()));
      }
      ++aborted;
    } else {
      job->record_ = record;
      ++kept;
    }
    if (record.deadline_unix_ms() > 0) {
      job->token_.SetDeadline(SteadyFromUnixMillis(record.deadline_unix_ms()));
    }
    if (outbox_ != nullptr && HasPendingDelivery(job->record_)) {
      // Results not yet on every destination: the outbox carries on where
      // it stopped (attempts and next try kept).
      const std::vector<std::string> files = DicomArtifactFiles(
          job->record_.status().artifacts(), spool_->OutputDir(id));
      for (const v1::Delivery& d : job->record_.status().deliveries()) {
        outbox_->Add(id, d, files, job->record_.status().finished_unix_ms());
      }
    }
    std::lock_guard<std::mutex> lock(mu_);
    jobs_[id] = job;
    if (job->record_.status().state() == v1::JOB_STATE_QUEUED) {
      queue_.push_back(job);
      ++requeued;
      --kept;
    }
  }
  spdlog::info(
      "spool recovered: {} queued job(s) requeued, {} interrupted "
      "job(s) marked failed, {} finished job(s) kept",
      requeued, aborted, kept);
  return absl::OkStatus();
}

void JobManager::Start() {
  std::lock_guard<std::mutex> lock(mu_);
  for (int i = 0; i < options_.workers; ++i) {
    workers_.emplace_back([this] { WorkerLoop(); });
  }
  ticker_ = std::thread([this] { TickerLoop(); });
  PublishGauges();
}

void JobManager::Discard(const std::shared_ptr<Job>& job) {
  bool remove_now = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    std::lock_guard<std::mutex> job_lock(job->mu_);
    if (job->discard_) return;
    job->discard_ = true;
    job->token_.Cancel();
    auto it = std::find(queue_.begin(), queue_.end(), job);
    if (it != queue_.end()) queue_.erase(it);
    if (!job->running_ && !HasPendingDelivery(job->record_)) {
      remove_now = true;
      jobs_.erase(job->id());
    }
    PublishGauges();
  }
  if (remove_now) RemoveFinished(job);
}

void JobManager::RemoveFinished(const std::shared_ptr<Job>& job) {
  int64_t bytes = 0;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    const v1::JobState s = job->record_.status().state();
    bytes = IsTerminalState(s) ? job->record_.result_bytes()
                               : job->record_.upload_bytes();
  }
  if (outbox_ != nullptr) outbox_->Forget(job->id());
  spool_->RemoveJob(job->id());
  spool_->Release(bytes);
}

void JobManager::UpdateDelivery(const std::string& job_id,
                                const v1::Delivery& delivery) {
  std::shared_ptr<Job> job = Find(job_id);
  if (job == nullptr) return;  // deleted meanwhile
  bool ended = false;          // this update ends the delivery (audited once)
  job->Update([&](JobRecord& r) {
    for (v1::Delivery& d : *r.mutable_status()->mutable_deliveries()) {
      if (d.peer() != delivery.peer()) continue;
      ended = d.state() != delivery.state() &&
              (delivery.state() == v1::Delivery::DELIVERED ||
               delivery.state() == v1::Delivery::FAILED);
      d = delivery;
    }
  });
  if (ended && options_.audit != nullptr) {
    const bool delivered = delivery.state() == v1::Delivery::DELIVERED;
    AuditEvent e;
    e.event = delivered ? "delivery.delivered" : "delivery.failed";
    e.outcome =
        delivered ? AuditOutcome::kSuccess : AuditOutcome::kSeriousFailure;
    e.identity = job->owner();
    e.job = job_id;
    e.peer = delivery.peer();
    e.count = delivery.instances_sent();
    e.detail = delivered ? absl::StrCat(delivery.instances_sent(), " of ",
                                        delivery.instances_total(),
                                        " instance(s) accepted")
                         : delivery.last_error();
    options_.audit->Record(std::move(e));
  }
  Persist(job);
  bool remove = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    std::lock_guard<std::mutex> job_lock(job->mu_);
    // An Interpolate job whose call has ended waited only for this.
    if (job->discard_ && !job->running_ && !HasPendingDelivery(job->record_) &&
        jobs_.erase(job_id) > 0) {
      remove = true;
    }
  }
  if (remove) RemoveFinished(job);
}

void JobManager::SetJobIdSuffix(std::string suffix) {
  std::lock_guard<std::mutex> lock(mu_);
  job_id_suffix_ = std::move(suffix);
}

std::shared_ptr<Job> JobManager::Find(const std::string& id) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = jobs_.find(id);
  return it == jobs_.end() ? nullptr : it->second;
}

absl::StatusOr<v1::JobStatus> JobManager::Cancel(const std::string& id) {
  std::shared_ptr<Job> job;
  bool was_queued = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return absl::NotFoundError("no such job");
    job = it->second;
    auto q = std::find(queue_.begin(), queue_.end(), job);
    if (q != queue_.end()) {
      queue_.erase(q);
      was_queued = true;
      PublishGauges();
    }
  }
  job->token_.Cancel();
  if (was_queued) {
    job->Update([this](JobRecord& r) {
      v1::JobStatus* s = r.mutable_status();
      s->set_state(v1::JOB_STATE_CANCELLED);
      s->set_error_code(static_cast<int>(absl::StatusCode::kCancelled));
      s->set_error_message("cancelled by request");
      s->set_finished_unix_ms(UnixMillisNow());
      s->set_expires_unix_ms(UnixMillisNow() +
                             options_.retention_seconds * 1000);
      s->mutable_progress()->set_stage("done");
    });
    spool_->RemoveUploads(id);
    spool_->Release(job->record_.upload_bytes());
    Persist(job);
    metrics_->JobFinished("cancelled");
    spdlog::info("job={} cancelled while queued", id);
    AuditJob(options_.audit, job, "job.cancelled", AuditOutcome::kMinorFailure,
             "cancelled while queued");
  } else if (!IsTerminalState(job->Snapshot(false).state())) {
    job->Update(
        [](JobRecord& r) { r.mutable_status()->set_cancel_requested(true); });
    spdlog::info("job={} cancellation requested", id);
  }
  return job->Snapshot(true);
}

std::vector<v1::JobStatus> JobManager::List(bool include_finished,
                                            const std::string* owner) {
  std::vector<std::shared_ptr<Job>> jobs;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const auto& [id, job] : jobs_) {
      if (job->ephemeral()) continue;
      if (owner != nullptr && job->owner() != *owner) continue;
      jobs.push_back(job);
    }
  }
  std::vector<v1::JobStatus> out;
  for (const auto& job : jobs) {
    v1::JobStatus s = job->Snapshot(false);
    if (!include_finished && IsTerminalState(s.state())) continue;
    out.push_back(std::move(s));
  }
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) {
    return a.created_unix_ms() > b.created_unix_ms();
  });
  return out;
}

void JobManager::BeginDrain() {
  std::vector<std::shared_ptr<Subscription>> to_fire;
  std::vector<std::string> ended;
  int64_t upload_bytes = 0;
  {
    std::lock_guard<std::mutex> lock(mu_);
    draining_ = true;
    // Queued Interpolate jobs would only be cancelled at the end of the
    // grace period, their callers told nothing useful: end them now, so
    // that the callers can retry on another replica at once. The state
    // changes under mu_, so that a concurrent Discard sees a terminal job
    // and does not release its upload bytes a second time.
    const int64_t now = UnixMillisNow();
    for (auto it = queue_.begin(); it != queue_.end();) {
      const std::shared_ptr<Job> job = *it;
      if (!job->ephemeral()) {
        ++it;
        continue;
      }
      std::lock_guard<std::mutex> job_lock(job->mu_);
      v1::JobStatus* s = job->record_.mutable_status();
      s->set_state(v1::JOB_STATE_FAILED);
      s->set_error_code(static_cast<int>(absl::StatusCode::kUnavailable));
      s->set_error_message(
          "the server is shutting down and did not start the job; retry on "
          "another replica");
      s->set_finished_unix_ms(now);
      s->set_expires_unix_ms(now + options_.retention_seconds * 1000);
      s->mutable_progress()->set_stage("done");
      s->set_sequence(s->sequence() + 1);
      upload_bytes += job->record_.upload_bytes();
      to_fire.insert(to_fire.end(), job->subscriptions_.begin(),
                     job->subscriptions_.end());
      ended.push_back(job->id());
      it = queue_.erase(it);
    }
    PublishGauges();
  }
  spool_->Release(upload_bytes);
  for (const auto& subscription : to_fire) subscription->Fire();
  for (const std::string& id : ended) {
    metrics_->JobFinished("failed");
    spdlog::info("job={} not started: the server is shutting down", id);
  }
}

bool JobManager::draining() {
  std::lock_guard<std::mutex> lock(mu_);
  return draining_;
}

int JobManager::queued() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(queue_.size());
}

int JobManager::running() {
  std::lock_guard<std::mutex> lock(mu_);
  return running_;
}

void JobManager::Shutdown(std::chrono::milliseconds grace) {
  std::unique_lock<std::mutex> lock(mu_);
  if (stopping_) return;
  draining_ = true;
  if (running_ > 0) {
    spdlog::info("draining: waiting up to {} ms for {} running job(s)",
                 grace.count(), running_);
  }
  cv_.wait_for(lock, grace, [this] { return running_ == 0; });
  stopping_ = true;
  for (const auto& [id, job] : jobs_) {
    std::lock_guard<std::mutex> job_lock(job->mu_);
    if (job->running_) {
      job->shutdown_cancelled_ = true;
      job->token_.Cancel();
      spdlog::info(
          "job={} cancelled by shutdown; it will run again after a "
          "restart",
          id);
    }
  }
  lock.unlock();
  cv_.notify_all();
  for (std::thread& t : workers_) t.join();
  workers_.clear();
  if (ticker_.joinable()) ticker_.join();
}

void JobManager::PublishGauges() {
  metrics_->SetQueueDepth(uploading_ + static_cast<double>(queue_.size()));
  metrics_->SetRunning(running_);
}

void JobManager::Persist(const std::shared_ptr<Job>& job) {
  if (job->ephemeral()) return;
  JobRecord record;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    record = job->record_;
  }
  if (absl::Status s = spool_->WriteRecord(record); !s.ok()) {
    spdlog::error("job={} cannot persist its record: {}", job->id(),
                  RedactPhi(s.message()));
  }
}

void JobManager::WorkerLoop() {
  for (;;) {
    std::shared_ptr<Job> job;
    {
      std::unique_lock<std::mutex> lock(mu_);
      cv_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
      if (stopping_) return;
      job = queue_.front();
      queue_.pop_front();
      std::lock_guard<std::mutex> job_lock(job->mu_);
      job->running_ = true;
      ++running_;
      PublishGauges();
    }
    RunOne(job);
    bool remove = false;
    {
      std::lock_guard<std::mutex> lock(mu_);
      std::lock_guard<std::mutex> job_lock(job->mu_);
      job->running_ = false;
      --running_;
      if (job->discard_ && !HasPendingDelivery(job->record_)) {
        remove = true;
        jobs_.erase(job->id());
      }
      if (job->shutdown_cancelled_) jobs_.erase(job->id());
      PublishGauges();
    }
    if (remove) RemoveFinished(job);
    cv_.notify_all();  // Shutdown waits for running_ == 0
  }
}

void JobManager::TickerLoop() {
  int ticks = 0;
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    cv_.wait_for(lock, std::chrono::seconds(1));
    if (stopping_) break;
    // Heartbeat: queue positions and elapsed time, so that watchers hear
    // from a job at least once a second.
    std::vector<std::pair<std::shared_ptr<Job>, int>> active;
    int position = 0;
    for (const auto& job : queue_) active.emplace_back(job, position++);
    for (const auto& [id, job] : jobs_) {
      std::lock_guard<std::mutex> job_lock(job->mu_);
      if (job->running_) active.emplace_back(job, -1);
    }
    std::vector<std::shared_ptr<Job>> expired;
    if (++ticks % 10 == 0) {
      const int64_t now = UnixMillisNow();
      for (auto it = jobs_.begin(); it != jobs_.end();) {
        std::shared_ptr<Job> job = it->second;
        std::lock_guard<std::mutex> job_lock(job->mu_);
        const v1::JobStatus& s = job->record_.status();
        // Results still owed to a DICOM peer outlive retention until the
        // delivery ends (delivered, or failed after give_up_after).
        if (!job->ephemeral() && !job->running_ && IsTerminalState(s.state()) &&
            s.expires_unix_ms() > 0 && s.expires_unix_ms() < now &&
            !HasPendingDelivery(job->record_)) {
          expired.push_back(job);
          it = jobs_.erase(it);
        } else {
          ++it;
        }
      }
    }
    lock.unlock();
    for (const auto& [job, pos] : active) {
      Job* j = job.get();
      const int position = pos;
      job->Update([j, position](JobRecord& r) {  // runs under j->mu_
        v1::Progress* p = r.mutable_status()->mutable_progress();
        p->set_queue_position(position);
        if (position < 0) {
          p->set_elapsed_seconds(
              std::chrono::duration<double>(std::chrono::steady_clock::now() -
                                            j->started_)
                  .count());
        }
      });
    }
    for (const auto& job : expired) {
      spdlog::info("job={} expired; its files were deleted", job->id());
      RemoveFinished(job);
    }
    lock.lock();
  }
}

}  // namespace interslice::server
