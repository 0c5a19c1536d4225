#include "server/net/dimse/pending_moves.h"

#include <unistd.h>

#include <filesystem>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/node/received_instance.h"

namespace interslice::server::dimse {

using node::KeepReceivedFile;

namespace {

std::string Trim(const std::string& ae) {
  return std::string(absl::StripAsciiWhitespace(ae));
}

}  // namespace

absl::Status PendingMoves::Move::Accept(uint64_t association,
                                        const std::string& staged,
                                        int64_t size) {
  std::unique_lock<std::mutex> lock(mu_);
  auto refuse = [&](absl::Status why) {
    ::unlink(staged.c_str());
    // The first refusal is the move's error: its later instances are
    // refused too (the series cannot arrive whole any more).
    if (error_.ok() && !closed_) error_ = why;
    return why;
  };
  if (closed_) {
    return refuse(absl::FailedPreconditionError(
        "the C-MOVE this instance belongs to has ended"));
  }
  if (!error_.ok()) return refuse(error_);
  open_.insert(association);
  if (instances_ + 1 > max_instances_) {
    return refuse(absl::ResourceExhaustedError(
        absl::StrCat("the series on the peer has more than ", max_instances_,
                     " instances (the server's limit per job)")));
  }
  if (bytes_ + size > max_bytes_) {
    return refuse(absl::ResourceExhaustedError(
        absl::StrCat("the series on the peer is larger than ", max_bytes_,
                     " bytes (the server's upload limit per job)")));
  }
  // Named by arrival, never by the peer's UIDs.
  const std::string target = (std::filesystem::path(dest_dir_) /
                              absl::StrFormat("pacs-%06d.dcm", instances_ + 1))
                                 .string();
  if (absl::Status kept = KeepReceivedFile(staged, target); !kept.ok()) {
    return refuse(kept);
  }
  kept_.push_back(target);
  ++instances_;
  bytes_ += size;
  cv_.notify_all();
  return absl::OkStatus();
}

void PendingMoves::Move::AssociationEnded(uint64_t association) {
  std::lock_guard<std::mutex> lock(mu_);
  if (open_.erase(association) > 0) cv_.notify_all();
}

bool PendingMoves::Move::WaitSettled(
    int64_t expected, std::chrono::steady_clock::time_point deadline) {
  std::unique_lock<std::mutex> lock(mu_);
  return cv_.wait_until(lock, deadline, [&] {
    return open_.empty() && (instances_ >= expected || !error_.ok());
  });
}

int64_t PendingMoves::Move::instances() {
  std::lock_guard<std::mutex> lock(mu_);
  return instances_;
}

int64_t PendingMoves::Move::bytes() {
  std::lock_guard<std::mutex> lock(mu_);
  return bytes_;
}

absl::Status PendingMoves::Move::error() {
  std::lock_guard<std::mutex> lock(mu_);
  return error_;
}

bool PendingMoves::Move::ended() {
  std::lock_guard<std::mutex> lock(mu_);
  return closed_;
}

void PendingMoves::Move::RemoveKept() {
  std::lock_guard<std::mutex> lock(mu_);
  for (const std::string& path : kept_) ::unlink(path.c_str());
  kept_.clear();
}

absl::StatusOr<std::shared_ptr<PendingMoves::Move>> PendingMoves::Register(
    const std::string& calling_ae, const std::string& study_uid,
    const std::string& series_uid, const std::string& dest_dir,
    int64_t max_instances, int64_t max_bytes,
    const std::function<absl::Status()>& may_wait) {
  const Key key{Trim(calling_ae), study_uid, series_uid};
  for (;;) {
    std::shared_ptr<Move> busy;
    {
      std::lock_guard<std::mutex> lock(mu_);
      Expire();
      if (auto it = moves_.find(key); it != moves_.end()) {
        std::lock_guard<std::mutex> move_lock(it->second->mu_);
        if (!it->second->closed_) busy = it->second;
      }
      if (busy == nullptr) {
        auto move = std::make_shared<Move>(dest_dir, max_instances, max_bytes);
        moves_[key] = move;
        return move;
      }
    }
    if (!may_wait) {
      return absl::FailedPreconditionError(
          "another job is moving the same series from this peer right now; "
          "try again when it has finished");
    }
    if (absl::Status wait = may_wait(); !wait.ok()) return wait;
    // Without the registry's lock: the listener goes on meanwhile.
    std::unique_lock<std::mutex> move_lock(busy->mu_);
    busy->cv_.wait_for(move_lock, std::chrono::milliseconds(200),
                       [&] { return busy->closed_; });
  }
}

void PendingMoves::Close(const std::shared_ptr<Move>& move) {
  std::lock_guard<std::mutex> lock(move->mu_);
  move->closed_ = true;
  move->closed_at_ = std::chrono::steady_clock::now();
  move->cv_.notify_all();
}

void PendingMoves::Expire() {
  const auto now = std::chrono::steady_clock::now();
  for (auto it = moves_.begin(); it != moves_.end();) {
    std::unique_lock<std::mutex> move_lock(it->second->mu_);
    const bool expired =
        it->second->closed_ && now - it->second->closed_at_ > kClosedGrace;
    move_lock.unlock();
    it = expired ? moves_.erase(it) : std::next(it);
  }
}

bool PendingMoves::Expects(const std::string& calling_ae) {
  const std::string ae = Trim(calling_ae);
  std::lock_guard<std::mutex> lock(mu_);
  Expire();
  auto it = moves_.lower_bound(Key{ae, "", ""});
  return it != moves_.end() && std::get<0>(it->first) == ae;
}

std::shared_ptr<PendingMoves::Move> PendingMoves::Find(
    const std::string& calling_ae, const std::string& study_uid,
    const std::string& series_uid) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = moves_.find(Key{Trim(calling_ae), study_uid, series_uid});
  return it == moves_.end() ? nullptr : it->second;
}

}  // namespace interslice::server::dimse
