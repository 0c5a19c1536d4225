// SeriesAssembler: the series held in unmatched/ (series_assembler.h, "Kept
// series"): listed, run again against the rules in force, swept at the end
// of their retention.
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

std::vector<KeptSeries> SeriesAssembler::WaitingSeries() {
  std::vector<KeptSeries> waiting;
  std::lock_guard<std::mutex> lock(mu_);
  for (const auto& [key, p] : pending_) {
    KeptSeries k;
    k.id = key;
    k.state = p.incomplete.has_value() ? "incomplete" : "receiving";
    k.calling_ae = p.calling_ae;
    k.called_ae = p.called_ae;
    k.instances = p.instances;
    k.kept_since_unix_ms = p.incomplete.has_value() ? p.incomplete_since_unix_ms
                                                    : p.first_arrival_unix_ms;
    k.why =
        p.incomplete.has_value()
            ? absl::StrCat("incomplete: ", *p.incomplete,
                           "; it waits for its missing part")
            : (p.open.empty() ? "waits for its stable time" : "being received");
    waiting.push_back(std::move(k));
  }
  waiting.insert(waiting.end(), recently_dropped_.begin(),
                 recently_dropped_.end());
  std::sort(waiting.begin(), waiting.end(),
            [](const KeptSeries& a, const KeptSeries& b) {
              return std::tie(a.kept_since_unix_ms, a.id) <
                     std::tie(b.kept_since_unix_ms, b.id);
            });
  return waiting;
}

std::vector<KeptSeries> SeriesAssembler::ListKept() {
  const std::shared_ptr<const RuleSet> rules = this->rules();
  std::vector<KeptSeries> kept;
  std::error_code ec;
  // The series still in series/ (waiting for completion, or incomplete) and
  // the ones dropped as incomplete lately (issue 39: an operator saw none
  // of them). Their facts are read outside the lock; one that completes
  // meanwhile is simply no longer listed here.
  std::vector<KeptSeries> waiting = WaitingSeries();
  for (KeptSeries& k : waiting) {
    if (k.state == "dropped") continue;  // its folder is gone
    const std::vector<std::string> files = DicomFiles(SeriesDir(k.id));
    if (!files.empty()) {
      const InstanceIds ids = ReadInstanceIds(files.front());
      k.study_uid = ids.study_uid;
      k.series_uid = ids.series_uid;
      k.modality = ReadSeriesFacts(SeriesDir(k.id)).modality;
    }
  }
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string id = entry.path().filename().string();
    if (!IsKeptId(id)) continue;
    const std::string dir = entry.path().string();
    KeptSeries k;
    k.id = id;
    if (!absl::SimpleAtoi(id.substr(33), &k.kept_since_unix_ms)) continue;
    std::tie(k.calling_ae, k.called_ae) = ReadOrigin(dir);
    std::ifstream(fs::path(dir) / "job") >> k.job_id;
    const std::vector<std::string> files = DicomFiles(dir);
    if (files.empty()) continue;  // removed meanwhile
    k.instances = static_cast<int64_t>(files.size());
    const InstanceIds ids = ReadInstanceIds(files.front());
    k.study_uid = ids.study_uid;
    k.series_uid = ids.series_uid;
    SeriesFacts facts = ReadSeriesFacts(dir);
    facts.calling_ae = k.calling_ae;
    facts.called_ae = k.called_ae;
    k.modality = facts.modality;
    k.why = k.job_id.empty() ? absl::StrCat("no rule matched; the rules now: ",
                                            rules->ExplainNoMatch(facts))
                             : absl::StrCat("job ", k.job_id, " made");
    kept.push_back(std::move(k));
  }
  std::sort(kept.begin(), kept.end(),
            [](const KeptSeries& a, const KeptSeries& b) {
              return std::tie(a.kept_since_unix_ms, a.id) <
                     std::tie(b.kept_since_unix_ms, b.id);
            });
  waiting.insert(waiting.end(), std::make_move_iterator(kept.begin()),
                 std::make_move_iterator(kept.end()));
  return waiting;
}

absl::StatusOr<KeptRerun> SeriesAssembler::RerunKept(const std::string& id) {
  const absl::Status not_found = absl::NotFoundError(
      "no kept series has that id (see `interslice kept list`; a kept series "
      "is removed at the end of its retention time)");
  if (!IsKeptId(id)) return not_found;
  const std::string key = id.substr(0, 32);
  const std::string held =
      (fs::path(options_.root) / "unmatched" / id).string();
  std::error_code ec;
  if (!fs::is_directory(held, ec)) return not_found;
  Pending p;
  std::tie(p.calling_ae, p.called_ae) = ReadOrigin(held);
  for (const std::string& file : DicomFiles(held)) {
    ++p.instances;
    p.bytes += static_cast<int64_t>(fs::file_size(file, ec));
  }
  if (p.instances == 0) return not_found;
  SeriesFacts facts = ReadSeriesFacts(held);
  facts.calling_ae = p.calling_ae;
  facts.called_ae = p.called_ae;
  // One generation of the rules, as in Complete.
  const std::shared_ptr<const RuleSet> rules = this->rules();
  const Rule* rule = rules->FirstMatch(facts);
  const std::string from =
      absl::StrCat(LogSafe(p.calling_ae), " -> ", LogSafe(p.called_ae));
  KeptRerun out;
  out.id = id;
  if (rule == nullptr) {
    out.not_matched =
        absl::StrCat("no rule matched: ", rules->ExplainNoMatch(facts));
    spdlog::info(
        "dicom: a kept series from {} ({} instance(s), modality {}) run "
        "again: still no rule of rule set {} matched: {}",
        from, p.instances, LogSafe(facts.modality), LogSafe(rules->path),
        LogSafe(rules->ExplainNoMatch(facts)));
    return out;
  }
  // Out of unmatched/ as CompleteStableSeries takes a series out of
  // series/: a late instance then starts a new folder, which KeepUnmatched
  // gives these instances once the job is made.
  std::string dir;
  {
    std::lock_guard<std::mutex> lock(mu_);
    dir = (fs::path(options_.root) / "completing" /
           absl::StrCat(key, "-", ++next_completion_))
              .string();
    if (pending_.count(key) > 0) {
      return absl::FailedPreconditionError(
          "more instances of this series are being received: it makes its "
          "job by the rules when they are complete");
    }
    if (::rename(held.c_str(), dir.c_str()) != 0) return not_found;
  }
  const std::string origin = JobOrigin(p.calling_ae, p.called_ae, *rule);
  spdlog::info(
      "dicom: a kept series from {} ({} instance(s)) run again on request: "
      "rule {} of rule set {} matches",
      from, p.instances, LogSafe(rule->name), LogSafe(rules->path));
  if (rule->job.has_fill()) {
    out.job_id = CompleteFill(key, p, dir, *rule, origin);
    if (out.job_id.empty()) {
      out.not_matched = absl::StrCat(
          "rule '", rule->name,
          "' matches this segmentation, but no job was made: the series it "
          "references is not held (see the server's log)");
    }
    return out;
  }
  // As Complete: the job's admission reserves the bytes again.
  if (spool_ != nullptr) spool_->Release(p.bytes);
  absl::StatusOr<std::string> job = submitter_(rule->job, dir, origin, "");
  if (!job.ok()) {
    if (spool_ != nullptr) spool_->Add(p.bytes);
    bool back = false;
    {
      std::lock_guard<std::mutex> lock(mu_);
      // Held again under its own name (its retention unchanged), unless a
      // late instance started the series again meanwhile: then it joins.
      back =
          pending_.count(key) == 0 && ::rename(dir.c_str(), held.c_str()) == 0;
    }
    if (!back) PutBack(key, p, dir);
    spdlog::warn(
        "dicom: rule {} matched a kept series from {} run again, but its job "
        "could not be made ({}); {}",
        LogSafe(rule->name), from, LogSafe(job.status().message()),
        back ? "it stays kept" : "it waits with the instances received since");
    return job.status();
  }
  if (spool_ != nullptr) spool_->Add(p.bytes);
  KeepUnmatched(key, dir, *job);
  if (metrics_ != nullptr) metrics_->DicomEvent("jobs_created");
  spdlog::info(
      "dicom: job={} made by rule {} for a kept series from {} ({} "
      "instance(s)), run again on request",
      *job, LogSafe(rule->name), from, p.instances);
  out.job_id = *job;
  return out;
}

absl::StatusOr<std::vector<KeptRerun>> SeriesAssembler::RerunAllUnmatched() {
  // Ids only (oldest first): RerunKept reads each series itself.
  std::vector<std::pair<int64_t, std::string>> ids;
  std::error_code ec;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string id = entry.path().filename().string();
    int64_t since = 0;
    if (!IsKeptId(id) || !absl::SimpleAtoi(id.substr(33), &since) ||
        fs::exists(entry.path() / "job", ec)) {
      continue;
    }
    ids.emplace_back(since, id);
  }
  std::sort(ids.begin(), ids.end());
  std::vector<KeptRerun> out;
  std::vector<std::string> made;
  for (const auto& [since, id] : ids) {
    absl::StatusOr<KeptRerun> r = RerunKept(id);
    if (absl::IsNotFound(r.status())) continue;  // its retention ended
    if (!r.ok()) {
      return absl::Status(
          r.status().code(),
          absl::StrCat("kept series ", id, ": ", r.status().message(), " (",
                       made.size(), " job(s) made before it",
                       made.empty() ? "" : ": ", absl::StrJoin(made, ", "),
                       ")"));
    }
    if (!r->job_id.empty()) made.push_back(r->job_id);
    out.push_back(*std::move(r));
  }
  return out;
}

void SeriesAssembler::SweepUnmatched() {
  std::error_code ec;
  const int64_t now_ms = options_.clock->UnixMillis();
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string name = entry.path().filename().string();
    const size_t dash = name.rfind('-');
    int64_t made_ms = 0;
    if (dash == std::string::npos ||
        !absl::SimpleAtoi(name.substr(dash + 1), &made_ms)) {
      continue;
    }
    if (now_ms - made_ms <
        static_cast<int64_t>(options_.unmatched_retention_seconds * 1000)) {
      continue;
    }
    const int64_t bytes = TreeSize(entry.path().string());
    fs::remove_all(entry.path(), ec);
    if (spool_ != nullptr) spool_->Release(bytes);
    spdlog::info(
        "dicom: an unmatched series reached its retention time and "
        "was removed");
  }
}

}  // namespace interslice::server::node
