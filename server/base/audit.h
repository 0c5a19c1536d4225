// The audit trail: who did what with which job, and which DICOM peers
// connected or were refused, as append-only JSON lines (docs/audit.md).
//
// Contract:
// - One JSON object per line, written with one write(2) to a file opened
//   O_APPEND (never truncated, never rewritten). Fields: "time" (UTC,
//   RFC 3339 with milliseconds), "event" (e.g. "job.submitted"), "atna" (the
//   DICOM PS3.15 A.5 / IHE ATNA audit event it corresponds to, e.g.
//   "110107 Import"), "outcome" ("success", "minor failure", "serious
//   failure": ATNA's EventOutcomeIndicator 0 / 4 / 8), and where known
//   "identity" (the authenticated caller, or "dicom:CALLING->CALLED" for a
//   DICOM association), "source" (the network address), "job", "peer" (a
//   configured DICOM peer's name), "count" and "detail".
// - No patient data: callers pass job ids, AE titles, addresses, counts and
//   one-line reasons; "detail" is passed through RedactPhi
//   (server/base/redact.h) so that a UID in an error message is replaced by
//   "<uid>".
// - Record() never blocks on the disk: events go to a bounded queue that
//   one writer thread drains (gRPC reactor threads call it). If the queue
//   is full the event is counted as dropped and the next written line says
//   how many were dropped ("audit.dropped"); a write error is logged once
//   and counted, and the trail goes on with the next event.
// - Rotation: when the file reaches max_bytes it is renamed PATH.1 (PATH.1
//   to PATH.2 and so on; the oldest beyond `keep` files is deleted) and a
//   new PATH is started.
// - Thread-safe. The destructor writes what is queued and stops the writer.
#ifndef INTERSLICE_SERVER_BASE_AUDIT_H_
#define INTERSLICE_SERVER_BASE_AUDIT_H_

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "absl/status/statusor.h"

namespace interslice::server {

enum class AuditOutcome { kSuccess, kMinorFailure, kSeriousFailure };

struct AuditEvent {
  std::string event;  // "job.submitted", "association.refused", ...
  AuditOutcome outcome = AuditOutcome::kSuccess;
  std::string identity;
  std::string source;
  std::string job;
  std::string peer;
  int64_t count = -1;  // < 0: not written
  std::string detail;
};

struct AuditOptions {
  std::string path;                       // required
  int64_t max_bytes = int64_t{64} << 20;  // rotate at this size (>= 4096)
  int keep = 10;                          // rotated files kept (>= 1)
  int max_queued = 10000;                 // events waiting to be written
};

class AuditLog {
 public:
  // Opens (creates, mode 0600) or appends to options.path and starts the
  // writer. INVALID_ARGUMENT for bad options, or the open's error.
  static absl::StatusOr<std::unique_ptr<AuditLog>> Open(
      const AuditOptions& options);
  ~AuditLog();
  AuditLog(const AuditLog&) = delete;
  AuditLog& operator=(const AuditLog&) = delete;

  void Record(AuditEvent event);

  // Blocks until every event recorded so far is written (tests, shutdown).
  void Flush();

  int64_t dropped_total() const;

 private:
  explicit AuditLog(const AuditOptions& options) : options_(options) {}
  void WriterLoop();
  void WriteLine(const std::string& line);
  void Rotate();

  const AuditOptions options_;
  int fd_ = -1;
  int64_t size_ = 0;
  bool write_error_logged_ = false;

  mutable std::mutex mu_;
  std::condition_variable wake_, written_;
  std::deque<std::string> queue_;
  int64_t dropped_ = 0, dropped_total_ = 0;
  int64_t recorded_ = 0, done_ = 0;
  bool stop_ = false;
  std::thread writer_;
};

// The ATNA event an audit event name corresponds to ("110107 Import"), for
// the "atna" field and docs/audit.md.
const char* AtnaEventFor(const std::string& event);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_BASE_AUDIT_H_
