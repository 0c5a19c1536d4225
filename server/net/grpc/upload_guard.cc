#include "server/net/grpc/upload_guard.h"

#include <algorithm>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace interslice::server {
namespace {

constexpr auto kTick = std::chrono::milliseconds(100);

int64_t NowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

}  // namespace

std::string PeerAddress(std::string_view peer) {
  std::string_view rest;
  if (peer.substr(0, 5) == "ipv4:") {
    rest = peer.substr(5);
    const size_t colon = rest.rfind(':');
    return std::string(rest.substr(0, colon));
  }
  if (peer.substr(0, 5) == "ipv6:") {
    rest = peer.substr(5);
    std::string_view open = "[", close = "]";
    if (rest.substr(0, 3) == "%5B" || rest.substr(0, 3) == "%5b") {
      open = rest.substr(0, 3);
      close = rest.substr(0, 3) == "%5B" ? "%5D" : "%5d";
    }
    if (rest.substr(0, open.size()) == open) {
      const size_t end = rest.find(close, open.size());
      if (end != std::string_view::npos) {
        return std::string(rest.substr(open.size(), end - open.size()));
      }
    }
  }
  return std::string(peer);
}

struct UploadTicket::Registry {
  std::mutex mu;
  int active = 0;
  std::map<std::string, int> per_peer;
  std::vector<std::weak_ptr<UploadTicket>> tickets;
};

UploadTicket::UploadTicket(std::shared_ptr<Registry> registry, std::string peer,
                           TimeoutCallback callback)
    : registry_(std::move(registry)),
      peer_(std::move(peer)),
      start_(std::chrono::steady_clock::now()),
      last_progress_ns_(NowNs()),
      callback_(std::move(callback)) {}

void UploadTicket::Progress() { last_progress_ns_ = NowNs(); }

void UploadTicket::Release() {
  std::lock_guard<std::mutex> lock(registry_->mu);
  if (released_) return;
  released_ = true;
  --registry_->active;
  auto it = registry_->per_peer.find(peer_);
  if (it != registry_->per_peer.end() && --it->second <= 0) {
    registry_->per_peer.erase(it);
  }
}

void UploadTicket::Close() {
  Release();
  std::lock_guard<std::mutex> lock(callback_mu_);
  callback_ = nullptr;
}

void UploadTicket::Fire(const absl::Status& status, bool idle) {
  std::lock_guard<std::mutex> lock(callback_mu_);
  if (callback_) callback_(status, idle);
}

UploadGuard::UploadGuard(const UploadGuardOptions& options)
    : options_(options),
      registry_(std::make_shared<UploadTicket::Registry>()),
      thread_([this] { Loop(); }) {}

UploadGuard::~UploadGuard() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

absl::StatusOr<std::shared_ptr<UploadTicket>> UploadGuard::Begin(
    const std::string& peer, UploadTicket::TimeoutCallback on_timeout) {
  std::shared_ptr<UploadTicket> ticket(
      new UploadTicket(registry_, peer, std::move(on_timeout)));
  std::lock_guard<std::mutex> lock(registry_->mu);
  // Not counted yet: make its destructor's Release() a no-op if refused.
  ticket->released_ = true;
  if (registry_->active >= options_.max_concurrent) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "too many uploads in progress on the server (limit ",
        options_.max_concurrent, ", --max-concurrent-uploads); retry later"));
  }
  int& mine = registry_->per_peer[peer];
  if (mine >= options_.max_per_peer) {
    return absl::ResourceExhaustedError(
        absl::StrCat("too many uploads in progress from this client (limit ",
                     options_.max_per_peer,
                     " per client, --max-uploads-per-peer); finish one first"));
  }
  ++mine;
  ++registry_->active;
  ticket->released_ = false;
  registry_->tickets.push_back(ticket);
  return ticket;
}

int UploadGuard::active() {
  std::lock_guard<std::mutex> lock(registry_->mu);
  return registry_->active;
}

void UploadGuard::Loop() {
  const auto idle_ns =
      static_cast<int64_t>(options_.idle_timeout_seconds * 1e9);
  const auto total =
      std::chrono::duration<double>(options_.total_timeout_seconds);
  const absl::Status stalled = absl::DeadlineExceededError(absl::StrFormat(
      "upload stalled: no data for %g s; the server cancelled it",
      options_.idle_timeout_seconds));
  const absl::Status too_long = absl::DeadlineExceededError(absl::StrFormat(
      "upload took longer than the server's limit of %g s; the server "
      "cancelled it",
      options_.total_timeout_seconds));
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    cv_.wait_for(lock, kTick);
    if (stopping_) break;
    std::vector<std::pair<std::shared_ptr<UploadTicket>, bool>> due;
    {
      std::lock_guard<std::mutex> registry_lock(registry_->mu);
      const int64_t now_ns = NowNs();
      const auto now = std::chrono::steady_clock::now();
      auto& tickets = registry_->tickets;
      for (auto it = tickets.begin(); it != tickets.end();) {
        std::shared_ptr<UploadTicket> t = it->lock();
        if (!t || t->released_) {
          it = tickets.erase(it);
          continue;
        }
        if (idle_ns > 0 && now_ns - t->last_progress_ns_ >= idle_ns) {
          t->last_progress_ns_ = now_ns;  // next report one period later
          due.emplace_back(t, true);
        }
        if (total.count() > 0 && !t->total_fired_ && now - t->start_ >= total) {
          t->total_fired_ = true;
          due.emplace_back(t, false);
        }
        ++it;
      }
    }
    lock.unlock();
    for (const auto& [ticket, idle] : due) {
      ticket->Fire(idle ? stalled : too_long, idle);
    }
    due.clear();  // tickets may be the last reference: drop them unlocked
    lock.lock();
  }
}

}  // namespace interslice::server
