// A job of the job manager (server/engine/job_manager.h, which includes
// this header) and the callbacks that watch it.
//
// Lock order: JobManager::mu_ before Job::mu_; subscriptions are fired with
// neither held.
#ifndef INTERSLICE_SERVER_ENGINE_JOB_H_
#define INTERSLICE_SERVER_ENGINE_JOB_H_

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/common/compute.h"
#include "interslice/v1/interslice.pb.h"
#include "job/job.h"
#include "server/engine/spool.h"

namespace interslice::server {

// A callback that can be switched off: a reactor closes it before it is
// deleted, and Close() waits for a Fire() in progress, so the callback never
// runs on a dead reactor.
class Subscription {
 public:
  explicit Subscription(std::function<void()> fn) : fn_(std::move(fn)) {}
  void Fire() {
    std::lock_guard<std::mutex> lock(mu_);
    if (fn_) fn_();
  }
  void Close() {
    closed_ = true;
    std::lock_guard<std::mutex> lock(mu_);
    fn_ = nullptr;
  }
  // Lock-free, so that Job may prune closed subscriptions under its own
  // lock without ordering against Fire().
  bool closed() const { return closed_; }

 private:
  std::atomic<bool> closed_{false};
  std::mutex mu_;
  std::function<void()> fn_;
};

class Job {
 public:
  const std::string& id() const { return id_; }
  bool ephemeral() const { return ephemeral_; }
  // The identity that submitted the job ("" without authentication);
  // persisted in the spool record.
  const std::string& owner() const { return owner_; }
  // The status now; report_json only if `with_report`.
  v1::JobStatus Snapshot(bool with_report = true) const;
  // Watchers: fired after every status change (from worker, ticker or
  // service threads).
  void Subscribe(std::shared_ptr<Subscription> subscription);
  // The job's kind, made from its spec once (at admission, or when the
  // spool is recovered) and run from there; null when the spec is not one
  // this version runs (the job then fails with kind_error()).
  job::JobKind* kind() const { return kind_.get(); }
  const absl::Status& kind_error() const { return kind_error_; }

 private:
  friend class JobManager;
  Job(std::string id, bool ephemeral, std::string owner)
      : id_(std::move(id)), ephemeral_(ephemeral), owner_(std::move(owner)) {}
  // Applies `change` to the record, bumps the sequence and fires watchers.
  void Update(const std::function<void(JobRecord&)>& change);

  const std::string id_;
  const bool ephemeral_;
  const std::string owner_;
  std::unique_ptr<job::JobKind> kind_;
  absl::Status kind_error_;
  mutable std::mutex mu_;
  JobRecord record_;
  CancellationToken token_;
  std::vector<std::shared_ptr<Subscription>> subscriptions_;
  std::chrono::steady_clock::time_point started_;
  bool running_ = false;
  bool discard_ = false;             // ephemeral: delete once idle
  bool shutdown_cancelled_ = false;  // stopped by a drain: re-queue on disk
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_ENGINE_JOB_H_
