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
//                           instance replaces itself) and origin.json
//   unmatched/<key>-<time>/ series no rule matched, kept for the retention
//                           time
// <key> is the SHA-256 of called AE, study and series UID (hex), so that no
// UID appears in a path or log line. Everything under series/ survives a
// restart: Open() takes it up again, and its stable wait starts over.
//
// Completeness: a series is complete when no instance of it arrived for the
// rule set's stable_seconds, or as soon as the association that sent it
// releases normally when the rule that matches it has complete_on_release.
// Then the first matching rule's job is submitted (files hard-linked into
// the job's upload folder) and the series folder is removed; instances of
// the same series that arrive after that form a new series folder and a new
// job later (logged), never touching the running one. Instances of an
// aborted association stay with their series.
//
// Segmentations (issue 13): a SEG or RTSTRUCT series is matched against the
// fill rules only (config.h). When one matches, the series its first
// instance references (SEG: ReferencedSeriesSequence; RTSTRUCT:
// ReferencedFrameOfReferenceSequence > RTReferencedStudySequence >
// RTReferencedSeriesSequence), received by the same called AE in the same
// study, must be held in the spool:
//   - in unmatched/ (complete and no rule matched it, or, when the rule set
//     has fill rules, complete and its job made: such series are kept there
//     too; the newest copy): the fill job is made on it at once (its files
//     hard-linked; the folder stays for other segmentations until its
//     retention ends);
//   - still in series/ (not complete yet), or not received (yet): the
//     segmentation waits in series/, tried again after every stable wait,
//     until it has waited unmatched_retention_seconds; then it goes to
//     unmatched/ (logged). The wait starts over after a restart.
// Without fill rules, a series whose job was made is deleted at once.
//
// Logs name AE titles, rule names, counts and the rule set file, never
// patient data or UIDs.
#ifndef INTERSLICE_SERVER_DICOM_SERIES_ASSEMBLER_H_
#define INTERSLICE_SERVER_DICOM_SERIES_ASSEMBLER_H_

#include <chrono>
#include <condition_variable>
#include <cstdint>
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
#include "server/dicom/config.h"

namespace interslice::server {
class Spool;
class Metrics;
}  // namespace interslice::server

namespace interslice::server::dicom {

struct AssemblerOptions {
  std::string root;  // <spool>/dicom-in; created if missing
  int64_t max_instances_per_series = 10000;
  int64_t max_bytes_per_series = int64_t{4} << 30;
  // Unmatched series are deleted this long after they completed.
  double unmatched_retention_seconds = 24 * 3600;
  // How often the stable wait is checked (tests shorten the rule set's
  // stable_seconds, not this).
  std::chrono::milliseconds poll_interval{200};
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

// The identity of a received instance (from its header).
struct InstanceIds {
  std::string study_uid, series_uid, sop_instance_uid;
};

class SeriesAssembler {
 public:
  // `spool` (may be null in tests) accounts received bytes against the
  // spool quota; `metrics` may be null.
  static absl::StatusOr<std::unique_ptr<SeriesAssembler>> Open(
      const AssemblerOptions& options, RuleSet rules, Spool* spool,
      Metrics* metrics, JobSubmitter submitter);
  ~SeriesAssembler();  // Stop()

  // Starts the thread that completes stable series and removes expired
  // unmatched ones.
  void Start();
  void Stop();

  const RuleSet& rules() const { return rules_; }
  // The most bytes one instance may have: the per-series limit. The
  // listener cuts off (aborts) a reception that passes it while it streams
  // in, since no status can answer an instance before all of it arrived.
  int64_t max_instance_bytes() const { return options_.max_bytes_per_series; }

  // A fresh path under incoming/ for an instance about to be received.
  std::string StagingPath();

  // Blocking. Takes the received file at `staged` (deleted in every case)
  // into its series: fsync, rename, fsync of the folder, before returning
  // OK (then, and only then, the C-STORE may answer success).
  // RESOURCE_EXHAUSTED: the spool quota or a per-series limit is reached;
  // INVALID_ARGUMENT: the header lacks study/series/SOP instance UIDs or is
  // not DICOM. Returns the series key.
  absl::StatusOr<std::string> AddInstance(const std::string& calling_ae,
                                          const std::string& called_ae,
                                          const std::string& staged);

  // An association released normally after storing into `series_keys`:
  // complete those whose matching rule has complete_on_release.
  void AssociationReleased(const std::set<std::string>& series_keys);

  // Blocking: complete every series whose stable wait is over now (the
  // background thread calls this; tests may too). Returns how many were
  // completed.
  int CompleteStableSeries();

  // Blocking: deletes unmatched series past their retention time (the
  // background thread calls this every 10 s; tests may too).
  void SweepUnmatched();

  int pending_series();

 private:
  struct Pending {
    std::string called_ae, calling_ae;
    int64_t instances = 0;
    int64_t bytes = 0;
    std::chrono::steady_clock::time_point last_arrival;
    bool release_requested = false;
    // A segmentation waiting for its referenced series: since when (the
    // first try); unset otherwise.
    std::optional<std::chrono::steady_clock::time_point> waiting_since;
  };

  SeriesAssembler(const AssemblerOptions& options, RuleSet rules, Spool* spool,
                  Metrics* metrics, JobSubmitter submitter);
  absl::Status Recover();
  void Loop();
  // Facts, rule and job for a series taken out of series/ into `dir`.
  void Complete(const std::string& key, const Pending& pending,
                const std::string& dir);
  // The fill rule `rule` matched the segmentation series in `dir`.
  void CompleteFill(const std::string& key, const Pending& pending,
                    const std::string& dir, const Rule& rule,
                    const std::string& origin);
  // Back into series/ to be tried again after another stable wait (merged
  // with instances that arrived meanwhile).
  void PutBack(const std::string& key, const Pending& pending,
               const std::string& dir);
  // Moves a completed folder to unmatched/ (kept for the retention time).
  void KeepUnmatched(const std::string& key, const std::string& dir);
  std::string SeriesDir(const std::string& key) const;

  const AssemblerOptions options_;
  const RuleSet rules_;
  Spool* const spool_;
  Metrics* const metrics_;
  const JobSubmitter submitter_;

  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::string, Pending> pending_;
  // Series whose job was made: a later instance of one starts a new series
  // (logged as such).
  std::set<std::string> submitted_;
  uint64_t next_staging_ = 0;
  uint64_t next_completion_ = 0;
  bool stopping_ = false;
  std::thread thread_;
  std::chrono::steady_clock::time_point last_sweep_;
};

// Reads the rule-relevant facts of the series in `dir` (every *.dcm header);
// calling/called AE are left empty.
SeriesFacts ReadSeriesFacts(const std::string& dir);

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_SERIES_ASSEMBLER_H_
