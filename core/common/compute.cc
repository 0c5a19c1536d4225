#include "core/common/compute.h"

namespace interslice {

absl::Status CancellationToken::Check() const {
  if (cancelled_.load(std::memory_order_relaxed)) {
    return absl::CancelledError("cancelled");
  }
  const auto deadline = deadline_ns_.load(std::memory_order_relaxed);
  if (deadline != 0 &&
      std::chrono::steady_clock::now().time_since_epoch().count() >= deadline) {
    return absl::DeadlineExceededError("deadline exceeded");
  }
  return absl::OkStatus();
}

}  // namespace interslice
