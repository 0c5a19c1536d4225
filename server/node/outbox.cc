#include "server/node/outbox.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "spdlog/spdlog.h"

namespace interslice::server::node {
namespace fs = std::filesystem;
namespace {

int64_t NowMillis() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace

std::vector<std::string> ListDicomFiles(const std::string& dir) {
  std::vector<std::string> files;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end;
       it.increment(ec)) {
    if (!it->is_regular_file(ec)) continue;
    std::ifstream in(it->path(), std::ios::binary);
    char magic[132] = {};
    if (in.read(magic, sizeof(magic)) &&
        std::string(magic + 128, 4) == "DICM") {
      files.push_back(it->path().string());
    }
  }
  std::sort(files.begin(), files.end());
  return files;
}

DeliveryQueue::DeliveryQueue(const PeerRegistry* peers, DeliveryOptions options,
                             OnUpdate on_update, DeliveryCounters counters)
    : peers_(peers),
      options_(std::move(options)),
      on_update_(std::move(on_update)),
      counters_(std::move(counters)) {}

DeliveryQueue::~DeliveryQueue() { Stop(); }

void DeliveryQueue::Start() {
  std::lock_guard<std::mutex> lock(mu_);
  if (thread_.joinable()) return;
  stopping_ = false;
  thread_ = std::thread([this] { Loop(); });
}

void DeliveryQueue::Stop() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

absl::Status DeliveryQueue::CheckPeers(
    const std::vector<std::string>& names) const {
  return peers_->CheckPeers(names);
}

void DeliveryQueue::Add(const std::string& job_id, v1::Delivery state,
                        std::vector<std::string> files,
                        int64_t first_added_unix_ms) {
  if (state.state() == v1::Delivery::DELIVERED ||
      state.state() == v1::Delivery::FAILED) {
    return;
  }
  state.set_state(v1::Delivery::PENDING);
  state.set_instances_total(static_cast<int32_t>(files.size()));
  {
    std::lock_guard<std::mutex> lock(mu_);
    Entry& entry = entries_[{job_id, state.peer()}];
    entry.job_id = job_id;
    entry.state = std::move(state);
    entry.files = std::move(files);
    entry.first_added_unix_ms = first_added_unix_ms;
  }
  cv_.notify_all();
}

void DeliveryQueue::Forget(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mu_);
  for (auto it = entries_.begin(); it != entries_.end();) {
    it = it->first.first == job_id ? entries_.erase(it) : std::next(it);
  }
}

int DeliveryQueue::pending() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(entries_.size());
}

void DeliveryQueue::Loop() {
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    const int64_t now = NowMillis();
    int64_t next = std::numeric_limits<int64_t>::max();
    auto due = entries_.end();
    for (auto it = entries_.begin(); it != entries_.end(); ++it) {
      const int64_t at = it->second.state.next_attempt_unix_ms();
      if (at <= now) {
        due = it;
        break;
      }
      next = std::min(next, at);
    }
    if (due == entries_.end()) {
      if (next == std::numeric_limits<int64_t>::max()) {
        cv_.wait(lock);
      } else {
        cv_.wait_for(lock, std::chrono::milliseconds(next - now));
      }
      continue;
    }
    const auto key = due->first;
    Entry entry = due->second;
    lock.unlock();
    Try(entry);
    lock.lock();
    auto it = entries_.find(key);
    if (it == entries_.end()) continue;  // forgotten meanwhile
    if (entry.state.state() == v1::Delivery::PENDING) {
      it->second.state = entry.state;
    } else {
      entries_.erase(it);
    }
    lock.unlock();
    on_update_(entry.job_id, entry.state);
    lock.lock();
  }
}

void DeliveryQueue::Try(Entry& entry) {
  v1::Delivery& d = entry.state;
  d.set_attempts(d.attempts() + 1);
  // Recorded before the try: a process killed during it (kill -9, power
  // cut) still counts the attempt after its restart.
  on_update_(entry.job_id, d);
  const std::shared_ptr<PeerClient> peer = peers_->Find(d.peer());
  const auto started = std::chrono::steady_clock::now();
  absl::StatusOr<StoreResult> result =
      peer == nullptr
          ? absl::FailedPreconditionError(absl::StrCat(
                "peer ", d.peer(), " is no longer in the peers file"))
          : peer->Store(entry.files);
  const int64_t now = NowMillis();
  const int total = static_cast<int>(entry.files.size());
  d.set_instances_total(total);
  if (result.ok()) {
    d.set_instances_sent(result->accepted);
    if (counters_.sent && result->accepted > 0) {
      counters_.sent(d.peer(), result->accepted);
    }
    if (counters_.failed && result->refused > 0) {
      counters_.failed(d.peer(), result->refused);
    }
  } else if (counters_.failed) {
    counters_.failed(d.peer(), total);
  }
  if (result.ok() && result->refused == 0 && result->accepted == total) {
    d.set_state(v1::Delivery::DELIVERED);
    d.clear_last_error();
    d.set_next_attempt_unix_ms(0);
    const double seconds = std::chrono::duration<double>(
                               std::chrono::steady_clock::now() - started)
                               .count();
    spdlog::info(
        "job={} delivered to peer {}: {} instance(s) in {:.2f} s ({:.1f} "
        "instances/s), attempt {}",
        entry.job_id, d.peer(), total, seconds,
        seconds > 0 ? total / seconds : 0.0, d.attempts());
    return;
  }
  d.set_last_error(result.ok() ? absl::StrCat(result->refused, " of ", total,
                                              " instance(s) refused: ",
                                              result->first_refusal)
                               : std::string(result.status().message()));
  if (now - entry.first_added_unix_ms >= options_.give_up_after.count()) {
    d.set_state(v1::Delivery::FAILED);
    d.set_next_attempt_unix_ms(0);
    spdlog::warn(
        "job={} delivery to peer {} failed for good after {} "
        "attempt(s): {}",
        entry.job_id, d.peer(), d.attempts(), d.last_error());
    return;
  }
  // Exponential backoff, capped.
  int64_t backoff = options_.initial_backoff.count();
  for (int i = 1; i < d.attempts() && backoff < options_.max_backoff.count();
       ++i) {
    backoff *= 2;
  }
  backoff = std::min<int64_t>(backoff, options_.max_backoff.count());
  d.set_state(v1::Delivery::PENDING);
  d.set_next_attempt_unix_ms(now + backoff);
  spdlog::warn(
      "job={} delivery to peer {} failed (attempt {}), next try in "
      "{} ms: {}",
      entry.job_id, d.peer(), d.attempts(), backoff, d.last_error());
}

}  // namespace interslice::server::node
