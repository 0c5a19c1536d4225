// Admission and time limits for uploads in progress (Interpolate and Submit
// streams before their job is queued): how many at once in total and per
// client, how long an upload may go without receiving data, and how long it
// may take in all. A queue slot is taken only when an upload is complete
// (JobManager::Enqueue), so slow or stalled uploads cannot keep real jobs
// out of the queue; they only compete with other uploads, and a stalled one
// is cancelled.
//
// Threading: Begin, Progress and Release never block (a mutex, no I/O), so
// reactors may call them. Timeouts are detected by the guard's own thread
// (it wakes every 100 ms) and reported through the ticket's callback, which
// runs on that thread.
#ifndef INTERSLICE_SERVER_NET_GRPC_UPLOAD_GUARD_H_
#define INTERSLICE_SERVER_NET_GRPC_UPLOAD_GUARD_H_

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"

namespace interslice::server {

struct UploadGuardOptions {
  // Uploads in progress at once, from all clients (>= 1).
  int max_concurrent = 32;
  // Uploads in progress at once from one client (>= 1): one identity when
  // the call is authenticated, else one IP address.
  int max_per_peer = 4;
  // Cancel an upload that received no file data for this long; 0 = never.
  double idle_timeout_seconds = 30;
  // Cancel an upload still incomplete after this long; 0 = never.
  double total_timeout_seconds = 0;
};

// The IP address of a gRPC peer string without the port:
// "ipv4:10.0.0.1:5000" -> "10.0.0.1", "ipv6:[::1]:5000" -> "::1" (also
// percent-encoded, "ipv6:%5B::1%5D:5000"). Anything else is returned whole.
std::string PeerAddress(std::string_view grpc_peer);

class UploadGuard;

// One upload in progress. Shared by the reactor and the guard.
class UploadTicket {
 public:
  // Called with DEADLINE_EXCEEDED when the upload stalls (`idle` true;
  // again after every further idle period while it stays stalled) or runs
  // over the total limit (`idle` false; once).
  using TimeoutCallback =
      std::function<void(const absl::Status& status, bool idle)>;

  ~UploadTicket() { Release(); }
  UploadTicket(const UploadTicket&) = delete;
  UploadTicket& operator=(const UploadTicket&) = delete;

  // File data arrived: restarts the idle clock.
  void Progress();
  // The upload ended (complete, failed or cancelled): frees its slots and
  // stops its clocks. Idempotent; never blocks.
  void Release();
  // Release(), and switches the callback off, waiting for a call in
  // progress; afterwards it never runs. Must not be called from the
  // callback or with a lock the callback takes.
  void Close();

 private:
  friend class UploadGuard;
  struct Registry;
  UploadTicket(std::shared_ptr<Registry> registry, std::string peer,
               TimeoutCallback callback);
  void Fire(const absl::Status& status, bool idle);

  const std::shared_ptr<Registry> registry_;
  const std::string peer_;
  const std::chrono::steady_clock::time_point start_;
  std::atomic<int64_t> last_progress_ns_;  // steady clock
  bool released_ = false;                  // Registry::mu
  bool total_fired_ = false;               // guard thread only
  std::mutex callback_mu_;
  TimeoutCallback callback_;
};

class UploadGuard {
 public:
  explicit UploadGuard(const UploadGuardOptions& options);
  ~UploadGuard();  // stops the thread; tickets may outlive the guard
  UploadGuard(const UploadGuard&) = delete;
  UploadGuard& operator=(const UploadGuard&) = delete;

  const UploadGuardOptions& options() const { return options_; }

  // A slot for a new upload from `peer` (a PeerAddress or an identity), or
  // RESOURCE_EXHAUSTED saying which limit was reached.
  absl::StatusOr<std::shared_ptr<UploadTicket>> Begin(
      const std::string& peer, UploadTicket::TimeoutCallback on_timeout);

  // Uploads in progress.
  int active();

 private:
  void Loop();

  const UploadGuardOptions options_;
  std::shared_ptr<UploadTicket::Registry> registry_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool stopping_ = false;
  std::thread thread_;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_NET_GRPC_UPLOAD_GUARD_H_
