#include "server/base/audit.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <string_view>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "nlohmann/json.hpp"
#include "server/base/log_safe.h"
#include "server/base/redact.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace {

namespace fs = std::filesystem;

std::string NowRfc3339() {
  const auto now = std::chrono::system_clock::now();
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(
                      now.time_since_epoch())
                      .count();
  const std::time_t seconds = static_cast<std::time_t>(ms / 1000);
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  return absl::StrFormat("%04d-%02d-%02dT%02d:%02d:%02d.%03dZ",
                         utc.tm_year + 1900, utc.tm_mon + 1, utc.tm_mday,
                         utc.tm_hour, utc.tm_min, utc.tm_sec,
                         static_cast<int>(ms % 1000));
}

const char* OutcomeName(AuditOutcome outcome) {
  switch (outcome) {
    case AuditOutcome::kSuccess:
      return "success";
    case AuditOutcome::kMinorFailure:
      return "minor failure";
    case AuditOutcome::kSeriousFailure:
      return "serious failure";
  }
  return "success";
}

std::string Line(const AuditEvent& e) {
  nlohmann::ordered_json j;
  j["time"] = NowRfc3339();
  j["event"] = e.event;
  j["atna"] = AtnaEventFor(e.event);
  j["outcome"] = OutcomeName(e.outcome);
  // Every string goes through LogSafe: identities and AE titles come from
  // the network, and one line must stay one line.
  if (!e.identity.empty()) j["identity"] = LogSafe(e.identity);
  if (!e.source.empty()) j["source"] = LogSafe(e.source);
  if (!e.job.empty()) j["job"] = LogSafe(e.job);
  if (!e.peer.empty()) j["peer"] = LogSafe(e.peer);
  if (e.count >= 0) j["count"] = e.count;
  if (!e.detail.empty()) j["detail"] = LogSafe(RedactPhi(e.detail));
  return j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace) +
         "\n";
}

}  // namespace

const char* AtnaEventFor(const std::string& event) {
  // DICOM PS3.15 A.5.3 (Audit Message event IDs, DCM code values).
  static const std::pair<std::string_view, const char*> kTable[] = {
      {"server.started", "110100 Application Activity"},
      {"server.stopped", "110100 Application Activity"},
      {"config.reloaded", "110100 Application Activity"},
      {"auth.refused", "110114 User Authentication"},
      {"job.submitted", "110107 Import"},
      {"job.succeeded", "110103 DICOM Instances Accessed"},
      {"job.failed", "110103 DICOM Instances Accessed"},
      {"job.cancelled", "110103 DICOM Instances Accessed"},
      {"job.cancel_requested", "110103 DICOM Instances Accessed"},
      {"job.fetched", "110106 Export"},
      {"jobs.listed", "110112 Query"},
      {"kept.listed", "110112 Query"},
      {"kept.rerun", "110103 DICOM Instances Accessed"},
      {"status.viewed", "110112 Query"},
      {"find.queried", "110112 Query"},
      {"delivery.delivered", "110104 DICOM Instances Transferred"},
      {"delivery.failed", "110104 DICOM Instances Transferred"},
      {"association.accepted", "110102 Begin Transferring DICOM Instances"},
      {"association.ended", "110104 DICOM Instances Transferred"},
      {"association.refused", "110113 Security Alert"},
      {"stow.received", "110104 DICOM Instances Transferred"},
      {"audit.dropped", "110101 Audit Log Used"},
  };
  for (const auto& [name, atna] : kTable) {
    if (name == event) return atna;
  }
  return "110100 Application Activity";
}

absl::StatusOr<std::unique_ptr<AuditLog>> AuditLog::Open(
    const AuditOptions& options) {
  if (options.path.empty()) {
    return absl::InvalidArgumentError("--audit-log needs a file path");
  }
  if (options.max_bytes < 4096) {
    return absl::InvalidArgumentError(
        "--audit-max-bytes must be at least 4096");
  }
  if (options.keep < 1 || options.keep > 1000) {
    return absl::InvalidArgumentError(
        "--audit-keep must be between 1 and 1000");
  }
  if (options.max_queued < 1) {
    return absl::InvalidArgumentError("the audit queue needs room");
  }
  std::unique_ptr<AuditLog> log(new AuditLog(options));
  log->fd_ = ::open(options.path.c_str(),
                    O_WRONLY | O_APPEND | O_CREAT | O_CLOEXEC, 0600);
  if (log->fd_ < 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("cannot open the audit log ", options.path, ": ",
                     std::strerror(errno)));
  }
  struct stat st {};
  if (::fstat(log->fd_, &st) == 0) log->size_ = st.st_size;
  log->writer_ = std::thread([raw = log.get()] { raw->WriterLoop(); });
  return log;
}

AuditLog::~AuditLog() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stop_ = true;
  }
  wake_.notify_all();
  if (writer_.joinable()) writer_.join();
  if (fd_ >= 0) ::close(fd_);
}

void AuditLog::Record(AuditEvent event) {
  std::string line = Line(event);
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (static_cast<int>(queue_.size()) >= options_.max_queued) {
      ++dropped_;
      ++dropped_total_;
      return;
    }
    queue_.push_back(std::move(line));
    ++recorded_;
  }
  wake_.notify_one();
}

void AuditLog::Flush() {
  std::unique_lock<std::mutex> lock(mu_);
  const int64_t target = recorded_;
  written_.wait(lock, [&] { return done_ >= target || !writer_.joinable(); });
}

int64_t AuditLog::dropped_total() const {
  std::lock_guard<std::mutex> lock(mu_);
  return dropped_total_;
}

void AuditLog::WriterLoop() {
  std::unique_lock<std::mutex> lock(mu_);
  for (;;) {
    wake_.wait(lock, [&] { return stop_ || !queue_.empty(); });
    if (queue_.empty() && stop_) break;
    std::deque<std::string> batch;
    batch.swap(queue_);
    const int64_t dropped = std::exchange(dropped_, 0);
    lock.unlock();
    if (dropped > 0) {
      AuditEvent note;
      note.event = "audit.dropped";
      note.outcome = AuditOutcome::kMinorFailure;
      note.count = dropped;
      note.detail = "events not recorded: the audit queue was full";
      WriteLine(Line(note));
    }
    for (const std::string& line : batch) WriteLine(line);
    lock.lock();
    done_ += static_cast<int64_t>(batch.size());
    written_.notify_all();
  }
  written_.notify_all();
}

void AuditLog::WriteLine(const std::string& line) {
  if (size_ > 0 &&
      size_ + static_cast<int64_t>(line.size()) > options_.max_bytes) {
    Rotate();
  }
  if (fd_ < 0) return;
  // One write of a whole line to an O_APPEND file: readers (and a second
  // process appending to the same file) never see half a line.
  const ssize_t n = ::write(fd_, line.data(), line.size());
  if (n == static_cast<ssize_t>(line.size())) {
    size_ += n;
    return;
  }
  if (!write_error_logged_) {
    write_error_logged_ = true;
    spdlog::error("audit: cannot write to {}: {}", options_.path,
                  n < 0 ? std::strerror(errno) : "short write");
  }
}

void AuditLog::Rotate() {
  const std::string& base = options_.path;
  std::error_code ignored;
  fs::remove(absl::StrCat(base, ".", options_.keep), ignored);
  for (int i = options_.keep - 1; i >= 1; --i) {
    const std::string from = absl::StrCat(base, ".", i);
    if (fs::exists(from, ignored)) {
      fs::rename(from, absl::StrCat(base, ".", i + 1), ignored);
    }
  }
  std::error_code error;
  fs::rename(base, base + ".1", error);
  const int fd =
      ::open(base.c_str(), O_WRONLY | O_APPEND | O_CREAT | O_CLOEXEC, 0600);
  if (fd < 0) {
    // Keep appending to the old file (now PATH.1) rather than lose events.
    if (!write_error_logged_) {
      write_error_logged_ = true;
      spdlog::error("audit: cannot start a new {}: {}", base,
                    std::strerror(errno));
    }
    return;
  }
  ::close(fd_);
  fd_ = fd;
  size_ = 0;
}

}  // namespace interslice::server
