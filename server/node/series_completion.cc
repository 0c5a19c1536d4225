// SeriesAssembler: what a complete series becomes (series_assembler.h,
// "Completeness", "Re-sent, unchanged", "Segmentations"): its rule's job,
// or a held copy, or nothing when it was re-sent unchanged.
#include <sys/stat.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "nlohmann/json.hpp"
#include "server/base/log_safe.h"
#include "server/base/metrics.h"
#include "server/engine/job_manager.h"
#include "server/engine/spool.h"
#include "server/node/received_instance.h"
#include "server/node/series_assembler.h"
#include "server/node/series_folder.h"
#include "spdlog/spdlog.h"

namespace interslice::server::node {

namespace fs = std::filesystem;

void SeriesAssembler::Complete(const std::string& key, const Pending& p,
                               const std::string& dir) {
  if (metrics_ != nullptr) metrics_->DicomEvent("series_completed");
  if (DropIfResentUnchanged(key, p, dir)) return;
  SeriesFacts facts = ReadSeriesFacts(dir);
  facts.calling_ae = p.calling_ae;
  facts.called_ae = p.called_ae;
  // One generation of the rules for this series (held while its job is
  // made: `rule` points into it).
  const std::shared_ptr<const RuleSet> rules = this->rules();
  const Rule* rule = rules->FirstMatch(facts);
  const std::string from =
      absl::StrCat(LogSafe(p.calling_ae), " -> ", LogSafe(p.called_ae));
  if (rule == nullptr) {
    if (facts.own_result && metrics_ != nullptr) {
      metrics_->DicomEvent("own_results_not_run");
    }
    KeepUnmatched(key, dir);
    spdlog::warn(
        "dicom: no rule of rule set {} matched a series from {} ({} "
        "instance(s), modality {}): {}; kept for {} s, then removed",
        LogSafe(rules->path), from, p.instances, LogSafe(facts.modality),
        LogSafe(rules->ExplainNoMatch(facts)),
        options_.unmatched_retention_seconds);
    return;
  }
  const std::string origin = JobOrigin(p.calling_ae, p.called_ae, *rule);
  if (rule->job.has_fill()) {
    CompleteFill(key, p, dir, *rule, origin);
    return;
  }
  // The job's admission reserves these bytes again (its upload is these
  // files, hard-linked): hand our reservation over first, so that a series
  // near the quota can still become its own job.
  if (spool_ != nullptr) spool_->Release(p.bytes);
  absl::StatusOr<std::string> job = submitter_(rule->job, dir, origin, "");
  if (!job.ok()) {
    if (spool_ != nullptr) spool_->Add(p.bytes);
    // Back into series/ so that it is tried again after another stable
    // wait (a full queue, a drain) and survives a restart.
    PutBack(key, p, dir);
    spdlog::warn(
        "dicom: rule {} matched a series from {} but its job could "
        "not be made ({}); trying again after another stable wait",
        LogSafe(rule->name), from, LogSafe(job.status().message()));
    return;
  }
  // Held for the retention time: a segmentation drawn on it may follow,
  // and so may more instances of it (the next job then takes all of them).
  // Counted in the quota again although the job's copy shares its blocks.
  if (spool_ != nullptr) spool_->Add(p.bytes);
  KeepUnmatched(key, dir, *job);
  if (metrics_ != nullptr) metrics_->DicomEvent("jobs_created");
  spdlog::info(
      "dicom: job={} made by rule {} for a series from {} ({} "
      "instance(s){})",
      *job, LogSafe(rule->name), from, p.instances,
      p.carried > 0 ? absl::StrCat(", ", p.carried, " of them held from before")
                    : "");
}

void SeriesAssembler::PutBack(const std::string& key, const Pending& p,
                              const std::string& dir) {
  std::error_code ec;
  std::lock_guard<std::mutex> lock(mu_);
  const std::string back = SeriesDir(key);
  if (!fs::exists(back, ec) && ::rename(dir.c_str(), back.c_str()) == 0) {
    Pending again = p;
    again.last_arrival = options_.clock->Now();
    again.release_requested = false;
    pending_[key] = again;
  } else {
    // New instances arrived meanwhile: merge ours into their folder (theirs
    // are newer where both have an instance).
    for (const auto& f : fs::directory_iterator(dir, ec)) {
      if (f.path().extension() != ".dcm") continue;
      const fs::path target = fs::path(back) / f.path().filename();
      if (fs::exists(target, ec)) continue;
      fs::rename(f.path(), target, ec);
    }
    fs::remove_all(dir, ec);
    auto it = pending_.find(key);
    if (it != pending_.end()) {
      int64_t n = 0, bytes = 0;
      for (const auto& f : fs::directory_iterator(back, ec)) {
        if (f.path().extension() != ".dcm") continue;
        ++n;
        bytes += static_cast<int64_t>(f.file_size(ec));
      }
      // Counted so far: theirs and ours; now: what the folder holds.
      if (spool_ != nullptr) spool_->Add(bytes - it->second.bytes - p.bytes);
      it->second.instances = n;
      it->second.bytes = bytes;
      if (!it->second.waiting_since) it->second.waiting_since = p.waiting_since;
    }
  }
}

void SeriesAssembler::KeepUnmatched(const std::string& key,
                                    const std::string& dir,
                                    const std::string& job_id) {
  std::error_code ec;
  if (!job_id.empty()) {
    std::ofstream(fs::path(dir) / "job") << job_id << "\n";
  }
  const std::string previous = NewestHeld(key);
  const std::string kept =
      (fs::path(options_.root) / "unmatched" /
       absl::StrCat(key, "-", options_.clock->UnixMillis()))
          .string();
  fs::rename(dir, kept, ec);
  if (ec) return;
  // The older copy is a subset of this one (its instances were carried
  // over when the series grew): no longer needed.
  if (!previous.empty() && previous != kept) {
    const int64_t bytes = TreeSize(previous);
    fs::remove_all(previous, ec);
    if (spool_ != nullptr) spool_->Release(bytes);
  }
  // Instances that arrived while this copy was being completed form a new
  // series already: it takes the completed ones too.
  std::lock_guard<std::mutex> lock(mu_);
  auto it = pending_.find(key);
  if (it != pending_.end()) {
    const auto [n, bytes] = CarryInstances(kept, SeriesDir(key));
    it->second.instances += n;
    it->second.bytes += bytes;
    it->second.carried += n;
    if (spool_ != nullptr) spool_->Add(bytes);
  }
}

std::string SeriesAssembler::CompleteFill(const std::string& key,
                                          const Pending& p,
                                          const std::string& dir,
                                          const Rule& rule,
                                          const std::string& origin) {
  std::error_code ec;
  const std::string from =
      absl::StrCat(LogSafe(p.calling_ae), " -> ", LogSafe(p.called_ae));
  std::optional<SegmentationRef> ref = ReadSegmentationRef(dir);
  if (!ref.has_value()) {
    KeepUnmatched(key, dir);
    spdlog::warn(
        "dicom: rule {} matched a segmentation from {} that names no "
        "referenced series; kept for {} s, then removed",
        LogSafe(rule.name), from, options_.unmatched_retention_seconds);
    return "";
  }
  // The referenced series, by the keys it would have been filed under.
  std::string held;
  bool pending = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const std::string& study : ref->study_uids) {
      const std::string series_key = Key(p.called_ae, study, ref->series_uid);
      if (pending_.count(series_key) > 0) pending = true;
      for (const auto& entry :
           fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
        const std::string name = entry.path().filename().string();
        // <key>-<ms>: the newest copy (names sort by time within a key
        // only when the times have as many digits, which holds for years).
        if (absl::StartsWith(name, series_key + "-") &&
            entry.path().string() > held) {
          held = entry.path().string();
        }
      }
    }
  }
  if (held.empty()) {
    Pending again = p;
    const auto now = options_.clock->Now();
    if (!again.waiting_since) {
      again.waiting_since = now;
      spdlog::info(
          "dicom: a segmentation from {} (rule {}) waits for the series it "
          "references{}",
          from, LogSafe(rule.name),
          pending ? " (still being received)" : " (not received yet)");
    }
    const auto waited = now - *again.waiting_since;
    if (waited <
        std::chrono::duration<double>(options_.unmatched_retention_seconds)) {
      PutBack(key, again, dir);
      return "";
    }
    KeepUnmatched(key, dir);
    spdlog::warn(
        "dicom: a segmentation from {} (rule {}) waited {} s for the series "
        "it references in vain; kept for {} s, then removed",
        from, LogSafe(rule.name), options_.unmatched_retention_seconds,
        options_.unmatched_retention_seconds);
    return "";
  }
  if (spool_ != nullptr) spool_->Release(p.bytes);
  absl::StatusOr<std::string> job =
      submitter_(rule.job, held, origin, ref->file);
  if (!job.ok()) {
    if (spool_ != nullptr) spool_->Add(p.bytes);
    PutBack(key, p, dir);
    spdlog::warn(
        "dicom: rule {} matched a segmentation from {} but its fill job "
        "could not be made ({}); trying again after another stable wait",
        LogSafe(rule.name), from, LogSafe(job.status().message()));
    return "";
  }
  fs::remove_all(dir, ec);
  if (metrics_ != nullptr) metrics_->DicomEvent("jobs_created");
  spdlog::info(
      "dicom: job={} (fill) made by rule {} for a segmentation from {} on a "
      "series held in the spool",
      *job, LogSafe(rule.name), from);
  return *job;
}

bool SeriesAssembler::DropIfResentUnchanged(const std::string& key,
                                            const Pending& p,
                                            const std::string& dir) {
  const std::string held = NewestHeld(key);
  if (held.empty()) return false;
  std::string job_id;
  if (!(std::ifstream(fs::path(held) / "job") >> job_id)) {
    return false;  // held without a job: the rules may have been fixed
  }
  if (options_.job_ended_without_results &&
      options_.job_ended_without_results(job_id)) {
    spdlog::info(
        "dicom: a series from {} -> {} whose job={} ended without results "
        "arrived again: its job is made again",
        LogSafe(p.calling_ae), LogSafe(p.called_ae), job_id);
    return false;
  }
  const std::vector<std::string> ours = DicomFiles(dir);
  const std::vector<std::string> theirs = DicomFiles(held);
  if (ours.size() != theirs.size()) return false;
  int64_t resent = 0;
  for (size_t i = 0; i < ours.size(); ++i) {
    // Names are hashes of the SOP Instance UID: the same set of instances.
    if (fs::path(ours[i]).filename() != fs::path(theirs[i]).filename()) {
      return false;
    }
    struct stat mine {
    }, held_one{};
    if (::stat(ours[i].c_str(), &mine) != 0 ||
        ::stat(theirs[i].c_str(), &held_one) != 0) {
      return false;
    }
    // Carried over from the held copy (a hard link): the same file.
    if (mine.st_dev == held_one.st_dev && mine.st_ino == held_one.st_ino) {
      continue;
    }
    absl::StatusOr<std::string> a = DatasetSha256(ours[i]);
    absl::StatusOr<std::string> b = DatasetSha256(theirs[i]);
    if (!a.ok() || !b.ok() || *a != *b) return false;
    ++resent;
  }
  std::error_code ec;
  fs::remove_all(dir, ec);
  if (spool_ != nullptr) spool_->Release(p.bytes);
  if (metrics_ != nullptr) metrics_->DicomEvent("series_resent_unchanged");
  spdlog::info(
      "dicom: {} instance(s) from {} -> {} of a series whose job={} was made "
      "arrived again, re-sent, unchanged: no job made, the held series "
      "stays",
      resent, LogSafe(p.calling_ae), LogSafe(p.called_ae), job_id);
  return true;
}

}  // namespace interslice::server::node
