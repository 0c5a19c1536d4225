// Series assembly for the DICOM listener: received instances are grouped per
// (called AE, study, series) in the spool, and a complete series becomes a
// job through the first rule that matches it.
//
// On disk (<spool>/dicom-in/, inside the spool so that a series' files can
// be hard-linked into the job's upload folder):
//   incoming/<n>.part       instances being received (deleted at start-up)
//   completing/<key>-<n>/   a complete series being handed to its job
//                           (back to series/ after a restart)
//   series/<key>/           one per series being received: the instances
//                           (<sha256 of SOP Instance UID>.dcm: a re-sent
//                           instance replaces itself), origin.json, one
//                           open-<n> file per association storing into it
//                           right now, and incomplete.json once it is
//                           incomplete (below)
//   unmatched/<key>-<time>/ complete series held for the retention time:
//                           those no rule matched, and those whose job was
//                           made (a `job` file names the job)
// <key> is the SHA-256 of called AE, study and series UID (hex), so that no
// UID appears in a path or log line. Everything under series/ survives a
// restart: Open() takes it up again, and its waits start over.
//
// Completeness (issue 22: a broken transfer must never become a result):
// - Every instance arrives within an association (BeginTransfer ..
//   EndTransfer). An association that ends any other way than a normal
//   release (the peer aborts or vanishes, a timeout or protocol violation
//   cuts it, the server stops or dies) leaves every series it stored into
//   INCOMPLETE; so does a refused instance of the series (limits, disk
//   full), and a refused instance whose series could not be read (not
//   DICOM, disk full while it arrived) taints every series its association
//   stored into. A series with an open-<n> file at start-up was being
//   received when the server stopped: incomplete.
// - An incomplete series never makes a job. It waits for its missing part
//   (issue 39): a transfer that begins after it became incomplete, stores
//   into it and ends whole with nothing refused makes it complete again
//   only if it brought something the series did not hold (an instance it
//   lacked, or other content for one it held: the sender's retry of what
//   was missing), or re-sent every instance the series holds (the sender's
//   retry of the whole series). A transfer that only re-sends, unchanged,
//   some of what the series already holds proves nothing about the missing
//   part: the series stays incomplete (logged, counted as
//   series_resend_not_completing). If no instance of it arrives for
//   unmatched_retention_seconds it is dropped: logged (AE titles, instance
//   count, reason; no patient data), counted (series_incomplete_dropped)
//   and deleted.
// - A complete series makes its job when no transfer that stored into it
//   is still open and either no instance arrived for the rule set's
//   stable_seconds, or the last such transfer ended whole and the first
//   matching rule says that transfer held the whole series: an association
//   released normally, with complete_on_release; a STOW-RS request, with
//   complete_on_request (issue 39: a client may post one instance per
//   request, so by default a series is grouped across requests and
//   completes after the stable wait, whatever complete_on_release says).
// - Every instance is of a storable SOP class (intake.h,
//   StorableSopClasses): another is refused (UNIMPLEMENTED) at every door.
// - After its job is made the series is held in unmatched/ for the
//   retention time. Instances of it that arrive later join the held ones
//   (hard links) in a new series folder, so that the next job is made on
//   the whole series, never on the late instances alone; its results
//   replace the earlier job's as far as the derived UIDs allow (see
//   docs/dicom-node.md). Past the retention time a late instance starts a
//   series of its own.
// - Re-sent, unchanged (issue 25): when a series that grew from a held copy
//   whose job was made completes with exactly the held instances (the same
//   SOP Instance UIDs, and each data set byte for byte the same: SHA-256 of
//   the data set after the meta group, which our listener writes), its
//   result could not change: no job is made, one line is logged (AE titles,
//   count, "re-sent, unchanged"), series_resent_unchanged is counted, the
//   new folder is deleted and the held copy stays as it was. A changed or
//   new instance makes the job on the whole series as before. A held copy
//   without a job (no rule matched) is run again when re-sent: the rules
//   may have been fixed since.
// - Another frame of reference (issue 25): a late instance whose
//   FrameOfReferenceUID differs from that of the held copy of its series
//   (both present) is refused (INVALID_ARGUMENT: the C-STORE fails, the
//   sender keeps it), logged with the AE titles and counted
//   (instances_other_frame_of_reference). Refused rather than kept as a
//   series of its own: it carries the held series' Study and Series UIDs,
//   so a job of it alone would be a one-instance job named like the held
//   series' results, and joined to the held instances it would be a volume
//   of two geometries. As every refusal, it makes what its association
//   stores into that series incomplete (above).
//
// Kept series (issue 25): ListKept reports what unmatched/ holds, and
// RerunKept matches a held series against the rules in force now (after a
// SIGHUP reload) and makes its job through the same completion path as a
// series that just completed (same submitter and origin, so the same
// results-replace-by-parameters behaviour); the folder is then held again
// with a `job` file, as after any job.
//
// Segmentations (issue 13): a SEG or RTSTRUCT series is matched against the
// fill rules only (config.h). When one matches, the series its first
// instance references (SEG: ReferencedSeriesSequence; RTSTRUCT:
// ReferencedFrameOfReferenceSequence > RTReferencedStudySequence >
// RTReferencedSeriesSequence), received by the same called AE in the same
// study, must be held in the spool:
//   - in unmatched/ (the newest copy): the fill job is made on it at once
//     (its files hard-linked; the folder stays for other segmentations
//     until its retention ends);
//   - still in series/ (not complete yet), or not received (yet): the
//     segmentation waits in series/, tried again after every stable wait,
//     until it has waited unmatched_retention_seconds; then it goes to
//     unmatched/ (logged). The wait starts over after a restart.
//
// Received files are read with DCMTK only after the bounded scan of
// dataset_scan.h passed (at AddInstance), so no instance can exhaust the
// parser's stack here. Logs name AE titles, rule names, counts and the rule
// set file, never patient data or UIDs.
#ifndef INTERSLICE_SERVER_NODE_SERIES_ASSEMBLER_H_
#define INTERSLICE_SERVER_NODE_SERIES_ASSEMBLER_H_

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "interslice/v1/interslice.pb.h"
#include "server/base/clock.h"
#include "server/node/config.h"
#include "server/node/dataset_scan.h"
#include "server/node/intake.h"
#include "server/node/received_instance.h"
#include "server/node/series_folder.h"

namespace interslice::server {
class Spool;
class Metrics;
}  // namespace interslice::server

namespace interslice::server::node {

struct AssemblerOptions {
  std::string root;  // <spool>/dicom-in; created if missing
  int64_t max_instances_per_series = 10000;
  int64_t max_bytes_per_series = int64_t{4} << 30;
  // Unmatched series are deleted this long after they completed.
  double unmatched_retention_seconds = 24 * 3600;
  // The bounded scan every received instance passes before it is parsed.
  DatasetScanLimits scan_limits;
  // How often the stable wait is checked (tests shorten the rule set's
  // stable_seconds, not this).
  std::chrono::milliseconds poll_interval{200};
  // What the waits (stable, retention) are measured by; a test may move
  // its own (tests/testing/fake_clock.h) and call CompleteStableSeries.
  const Clock* clock = Clock::Real();
  // Whether the job `job_id` ended without results (failed or cancelled).
  // A series re-sent unchanged after such a job makes its job again: a
  // re-send is how a PACS operator retries. After any other job (queued,
  // running, succeeded, or no longer known to the server) an unchanged
  // re-send makes none. Unset: never asked (no job is made again).
  std::function<bool(const std::string& job_id)> job_ended_without_results;
};

// Makes the job for a complete series: `files_dir` holds its instances (the
// callee hard-links or copies them; the assembler deletes the folder after
// success). Returns the job id. Any error leaves the series to be tried
// again later (e.g. a full queue). A fill job (spec.fill set) gets the
// referenced series' folder as `files_dir` (kept as it is) and the SEG or
// RTSTRUCT file as `segmentation_file`; other jobs get "".
using JobSubmitter = std::function<absl::StatusOr<std::string>(
    const v1::JobSpec& spec, const std::string& files_dir,
    const std::string& origin, const std::string& segmentation_file)>;

// A series the node holds, as ListKept reports it: complete and kept in
// unmatched/ (state "kept"), or still in series/: waiting for its
// completion ("receiving") or for its missing part ("incomplete"); or one
// of the last series dropped as incomplete ("dropped": its files are gone,
// it is listed until the server restarts or 64 newer ones were dropped).
struct KeptSeries {
  std::string state = "kept";  // kept | receiving | incomplete | dropped
  std::string id;              // the folder's name, <key>-<unix ms>: opaque
  std::string calling_ae, called_ae, modality;
  int64_t instances = 0;
  // Kept: since it was kept; receiving: since its first instance arrived;
  // incomplete: since it became incomplete; dropped: since it was dropped.
  int64_t kept_since_unix_ms = 0;
  std::string job_id;  // the job made of it; empty: none
  // "job <id> made", or "no rule matched; the rules now: " and, per rule,
  // its first failing criterion (RuleSet::ExplainNoMatch); for a series in
  // series/, why it waits (the reason it is incomplete). No UIDs.
  std::string why;
  // Of its first instance: for admins only, never logged.
  std::string study_uid, series_uid;
};

// What RerunKept did with one kept series.
struct KeptRerun {
  std::string id;
  std::string job_id;  // the job made; empty when none was
  // No job: why (no rule of the set in force matches it, with each rule's
  // first failing criterion; or a fill rule matched a segmentation whose
  // referenced series is not held). No UIDs.
  std::string not_matched;
};

class SeriesAssembler : public Intake {
 public:
  // `spool` (may be null in tests) accounts received bytes against the
  // spool quota; `metrics` may be null.
  static absl::StatusOr<std::unique_ptr<SeriesAssembler>> Open(
      const AssemblerOptions& options, RuleSet rules, Spool* spool,
      Metrics* metrics, JobSubmitter submitter);
  ~SeriesAssembler() override;  // Stop()

  // Starts the thread that completes stable series and removes expired
  // unmatched ones.
  void Start();
  void Stop();

  // The rules in force. SetRules replaces them whole (a reload on SIGHUP,
  // server/app/server.cc); every completion takes one set for all it decides,
  // and a job made before keeps the spec it was made with.
  std::shared_ptr<const RuleSet> rules() const;
  void SetRules(RuleSet rules);
  // Intake (intake.h). The most bytes one instance may have is the
  // per-series limit: the listener cuts off (aborts) a reception that passes
  // it while it streams in, since no status can answer an instance before
  // all of it arrived.
  int64_t max_instance_bytes() const override {
    return options_.max_bytes_per_series;
  }
  const DatasetScanLimits& scan_limits() const override {
    return options_.scan_limits;
  }
  // A fresh path under incoming/.
  std::string StagingPath() override;
  uint64_t BeginTransfer(Door door, const std::string& calling_ae,
                         const std::string& called_ae) override;

  // Blocking. Takes the received file at `staged` (deleted in every case)
  // into its series: the bounded scan (dataset_scan.h), the header's UIDs,
  // fsync, rename, fsync of the folder, before returning OK (then, and only
  // then, the C-STORE may answer success). `received_bytes`: the data set's
  // bytes as they arrived (the listener counts them; -1: unknown); a file
  // holding fewer was cut short by a full disk.
  // RESOURCE_EXHAUSTED: the spool quota or a per-series limit is reached,
  // or the disk is full (the series is then incomplete); INVALID_ARGUMENT:
  // the data set is not well-formed within the scan's limits, or the header
  // lacks the series or SOP instance UID. Every refusal marks what the
  // instance belonged to incomplete: its series, or (series unknown) every
  // series of the association. Returns the series key.
  absl::StatusOr<std::string> AddInstance(uint64_t association,
                                          const std::string& staged,
                                          int64_t received_bytes) override;

  // An instance of `association` was refused before its series was known:
  // every series the association stores into is incomplete.
  void InstanceRefused(uint64_t association) override;

  // The transfer ended: whole (a normal release), or not (see above).
  void EndTransfer(uint64_t association, bool whole) override;

  // Blocking: complete every series whose stable wait is over now (the
  // background thread calls this; tests may too). Returns how many were
  // completed.
  int CompleteStableSeries();

  // Blocking: deletes unmatched series past their retention time (the
  // background thread calls this every 10 s; tests may too).
  void SweepUnmatched();

  // Blocking: drops incomplete series that received nothing for the
  // retention time (the background thread calls this every second; tests
  // may too).
  void DropStaleIncomplete();

  int pending_series();

  // Blocking (reads every header of every held series). The series in
  // series/ (receiving, incomplete) and the last ones dropped, then the
  // held ones, each group oldest first; `why` is explained against the
  // rules in force now.
  std::vector<KeptSeries> ListKept();
  // Cheap (no file is read; no modality, no UIDs): the series in series/
  // and the last ones dropped, oldest first. For the status page.
  std::vector<KeptSeries> WaitingSeries();
  // Blocking. Runs the kept series `id` (KeptSeries::id) again: matched
  // against the rules in force now and, when a rule matches, made into its
  // job exactly as a series that just completed (Complete's path). No rule
  // matches: OK with not_matched set, the series stays held as it was.
  // NOT_FOUND: no held series has that id (never had, or removed at the
  // end of its retention); FAILED_PRECONDITION: more instances of the
  // series are being received (it makes its job when they complete); a
  // submission error (a full queue, a drain) as the job manager gave it,
  // the series then held as it was.
  absl::StatusOr<KeptRerun> RerunKept(const std::string& id);
  // Blocking. RerunKept for every held series without a job, oldest first;
  // stops at the first error (its message says how many jobs were made
  // before it).
  absl::StatusOr<std::vector<KeptRerun>> RerunAllUnmatched();

 private:
  struct Pending {
    std::string called_ae, calling_ae;
    int64_t instances = 0;
    int64_t bytes = 0;
    std::chrono::steady_clock::time_point last_arrival;
    // Associations storing into it now.
    std::set<uint64_t> open;
    // The last transfer to end ended whole with nothing refused, through
    // `released_through` (complete_on_release, for an association, or
    // complete_on_request, for a STOW-RS request, may complete it).
    bool release_requested = false;
    Door released_through = Door::kAssociation;
    // Incomplete (see above): why, and the newest association id at that
    // moment (only a later association can make it complete again).
    std::optional<std::string> incomplete;
    uint64_t incomplete_after = 0;
    // Instances taken over from the held copy of the series (its job was
    // made or no rule matched it) when it grew later.
    int64_t carried = 0;
    // Unix ms: its first instance arrived (in this process's view: since
    // the restart for a series received before it); it became incomplete.
    int64_t first_arrival_unix_ms = 0;
    int64_t incomplete_since_unix_ms = 0;
    // A segmentation waiting for its referenced series: since when (the
    // first try); unset otherwise.
    std::optional<std::chrono::steady_clock::time_point> waiting_since;
    // The FrameOfReferenceUID of the held copy it grew from (empty: none,
    // or not given): a late instance of another one is refused.
    std::string held_frame_of_reference;
  };
  // What one transfer stored into one series: the instances (file names),
  // and whether any of them was new to the series (an instance it did not
  // hold, or held with other content).
  struct Contribution {
    std::set<std::string> instances;
    bool brought_new = false;
  };
  struct Association {
    Door door = Door::kAssociation;
    std::string calling_ae, called_ae;
    std::set<std::string> series;   // keys stored into
    std::set<std::string> refused;  // keys of which an instance was refused
    bool tainted = false;           // an instance of unknown series refused
    std::map<std::string, Contribution> contributed;  // by series key
  };

  SeriesAssembler(const AssemblerOptions& options, RuleSet rules, Spool* spool,
                  Metrics* metrics, JobSubmitter submitter);
  absl::Status Recover();
  void Loop();
  // Facts, rule and job for a series taken out of series/ into `dir`.
  void Complete(const std::string& key, const Pending& pending,
                const std::string& dir);
  // The fill rule `rule` matched the segmentation series in `dir`.
  // Returns the fill job's id, or "" when none was made (the segmentation
  // then waits for its series in series/, or is held without a job).
  std::string CompleteFill(const std::string& key, const Pending& pending,
                           const std::string& dir, const Rule& rule,
                           const std::string& origin);
  // A series that grew from a held copy whose job was made completed with
  // nothing new (see "Re-sent, unchanged"): logs, counts and deletes `dir`
  // and returns true; false when something changed or there is no such
  // held copy.
  bool DropIfResentUnchanged(const std::string& key, const Pending& pending,
                             const std::string& dir);
  // Back into series/ to be tried again after another stable wait (merged
  // with instances that arrived meanwhile).
  void PutBack(const std::string& key, const Pending& pending,
               const std::string& dir);
  // Moves a completed folder to unmatched/ (kept for the retention time),
  // with a `job` file naming its job when one was made; an older held copy
  // of the same series is deleted.
  void KeepUnmatched(const std::string& key, const std::string& dir,
                     const std::string& job_id = "");
  // With mu_ held: a whole transfer that began after the series became
  // incomplete ended; makes it complete again if `contribution` completed
  // it (see "Completeness").
  void ResumeIfCompleted(const std::string& key, Pending& pending,
                         const Contribution& contribution);
  // With mu_ held: the first instance of `transfer` in the series: its
  // open-<n> file, and the transfer counted as storing into it.
  // RESOURCE_EXHAUSTED when the file cannot be made (a full disk).
  absl::Status MarkTransferOpen(const std::string& key, Pending& pending,
                                uint64_t transfer, Association& association);
  // With mu_ held: marks the series incomplete (persisted) unless it is.
  void MarkIncomplete(const std::string& key, Pending& pending,
                      const std::string& reason);
  // With mu_ held: the first instance of a series that is not pending:
  // creates its folder, with the held copy's instances when there is one.
  // `held`: the newest held copy of the series (NewestHeld), or "".
  absl::Status StartSeries(const std::string& key, Pending& pending,
                           const Association& association,
                           const std::string& held);
  std::string SeriesDir(const std::string& key) const;
  std::string NewestHeld(const std::string& key) const;

  const AssemblerOptions options_;
  mutable std::mutex rules_mu_;
  std::shared_ptr<const RuleSet> rules_;  // guarded by rules_mu_
  Spool* const spool_;
  Metrics* const metrics_;
  const JobSubmitter submitter_;

  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::string, Pending> pending_;
  std::map<uint64_t, Association> associations_;
  // The last series dropped as incomplete (WaitingSeries), newest last.
  static constexpr size_t kRecentlyDroppedKept = 64;
  std::deque<KeptSeries> recently_dropped_;
  uint64_t next_association_ = 0;
  uint64_t next_staging_ = 0;
  uint64_t next_completion_ = 0;
  bool stopping_ = false;
  std::thread thread_;
  std::chrono::steady_clock::time_point last_sweep_;
};

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_SERIES_ASSEMBLER_H_
