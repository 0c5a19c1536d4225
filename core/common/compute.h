// Execution context passed into every long-running core function: how many
// threads it may use, how it learns that it should stop, and where it reports
// progress. Nothing in core/ keeps global parallelism or cancellation state.
#ifndef INTERSLICE_CORE_COMMON_COMPUTE_H_
#define INTERSLICE_CORE_COMMON_COMPUTE_H_

#include <atomic>
#include <chrono>
#include <functional>
#include <string>

#include "absl/status/status.h"

namespace interslice {

// A cancellation flag with an optional deadline. Thread-safe; cheap to poll
// (one relaxed atomic load, plus a steady_clock read when a deadline is set).
class CancellationToken {
 public:
  CancellationToken() = default;
  CancellationToken(const CancellationToken&) = delete;
  CancellationToken& operator=(const CancellationToken&) = delete;

  void Cancel() { cancelled_.store(true, std::memory_order_relaxed); }
  // After `deadline`, IsCancelled() returns true and Check() reports
  // DEADLINE_EXCEEDED.
  void SetDeadline(std::chrono::steady_clock::time_point deadline) {
    deadline_ns_.store(deadline.time_since_epoch().count(),
                       std::memory_order_relaxed);
  }
  bool IsCancelled() const { return !Check().ok(); }
  // OK while work may continue; CANCELLED or DEADLINE_EXCEEDED otherwise.
  absl::Status Check() const;

 private:
  std::atomic<bool> cancelled_{false};
  std::atomic<std::chrono::steady_clock::rep> deadline_ns_{0};
};

// What a pipeline stage reports while it runs.
struct ProgressEvent {
  std::string stage;      // "read", "contour", "stack", "solve", ...
  double fraction = 0.0;  // of this stage, in [0, 1]
  int iteration = -1;     // solver iteration (solve stage only), else -1
  double relative_residual = -1.0;  // |r_k| / |r_0| (solve stage only)
  double energy = -1.0;             // curvature energy (solve stage only)
};

using ProgressCallback = std::function<void(const ProgressEvent&)>;

struct ComputeContext {
  // Worker threads for this call; 0 means all hardware threads. Results do not
  // depend on this number (reductions use a fixed partitioning and order).
  int threads = 0;
  // Polled at least once per solver iteration or per slice; may be null.
  const CancellationToken* cancel = nullptr;
  // Called from the calling thread or a worker thread, never concurrently;
  // may be empty.
  ProgressCallback progress;

  absl::Status CheckCancelled() const {
    return cancel == nullptr ? absl::OkStatus() : cancel->Check();
  }
  void Report(const ProgressEvent& event) const {
    if (progress) progress(event);
  }
};

}  // namespace interslice

#endif  // INTERSLICE_CORE_COMMON_COMPUTE_H_
