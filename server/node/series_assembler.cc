#include "server/node/series_assembler.h"

#include <fcntl.h>
#include <unistd.h>

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
#include "server/node/series_folder.h"
#include "spdlog/spdlog.h"

namespace interslice::server::node {

namespace fs = std::filesystem;

SeriesAssembler::SeriesAssembler(const AssemblerOptions& options, RuleSet rules,
                                 Spool* spool, Metrics* metrics,
                                 JobSubmitter submitter)
    : options_(options),
      rules_(std::make_shared<const RuleSet>(std::move(rules))),
      spool_(spool),
      metrics_(metrics),
      submitter_(std::move(submitter)) {}

std::shared_ptr<const RuleSet> SeriesAssembler::rules() const {
  std::lock_guard<std::mutex> lock(rules_mu_);
  return rules_;
}

void SeriesAssembler::SetRules(RuleSet rules) {
  auto next = std::make_shared<const RuleSet>(std::move(rules));
  std::lock_guard<std::mutex> lock(rules_mu_);
  rules_ = std::move(next);
}

absl::StatusOr<std::unique_ptr<SeriesAssembler>> SeriesAssembler::Open(
    const AssemblerOptions& options, RuleSet rules, Spool* spool,
    Metrics* metrics, JobSubmitter submitter) {
  std::unique_ptr<SeriesAssembler> a(new SeriesAssembler(
      options, std::move(rules), spool, metrics, std::move(submitter)));
  if (absl::Status s = a->Recover(); !s.ok()) return s;
  return a;
}

SeriesAssembler::~SeriesAssembler() { Stop(); }

std::string SeriesAssembler::SeriesDir(const std::string& key) const {
  return (fs::path(options_.root) / "series" / key).string();
}

absl::Status SeriesAssembler::Recover() {
  std::error_code ec;
  for (const char* sub : {"incoming", "series", "completing", "unmatched"}) {
    fs::create_directories(fs::path(options_.root) / sub, ec);
    if (ec) {
      return absl::InternalError(
          absl::StrCat("cannot create the DICOM spool folder ", options_.root,
                       "/", sub, ": ", ec.message()));
    }
  }
  // Partial receptions: never acknowledged, so never kept.
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "incoming", ec)) {
    fs::remove_all(entry.path(), ec);
  }
  // Series being handed to a job when the server stopped: back to series/
  // (merged with instances that arrived since), to be completed again.
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "completing", ec)) {
    const std::string name = entry.path().filename().string();
    const std::string back = SeriesDir(name.substr(0, name.rfind('-')));
    if (!fs::exists(back, ec)) {
      fs::rename(entry.path(), back, ec);
      continue;
    }
    for (const auto& f : fs::directory_iterator(entry.path(), ec)) {
      if (f.path().extension() == ".dcm") {
        fs::rename(f.path(), fs::path(back) / f.path().filename(), ec);
      }
    }
    fs::remove_all(entry.path(), ec);
  }
  const auto now = options_.clock->Now();
  int recovered = 0, interrupted = 0;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "series", ec)) {
    if (!entry.is_directory()) continue;
    const std::string key = entry.path().filename().string();
    Pending p;
    std::ifstream origin(entry.path() / "origin.json");
    nlohmann::json j = nlohmann::json::parse(origin, nullptr, false);
    if (j.is_object()) {
      p.called_ae = j.value("called_ae", "");
      p.calling_ae = j.value("calling_ae", "");
    }
    bool was_open = false;
    for (const auto& f : fs::directory_iterator(entry.path(), ec)) {
      const std::string name = f.path().filename().string();
      if (absl::StartsWith(name, kOpenPrefix)) {
        was_open = true;
        fs::remove(f.path(), ec);
        continue;
      }
      if (f.path().extension() != ".dcm") continue;
      ++p.instances;
      p.bytes += static_cast<int64_t>(f.file_size(ec));
    }
    if (p.called_ae.empty() || (p.instances == 0 && !was_open)) {
      fs::remove_all(entry.path(), ec);
      continue;
    }
    // The waits start over: the server cannot know how long it was down,
    // and a sender may still be retrying.
    p.last_arrival = now;
    p.first_arrival_unix_ms = options_.clock->UnixMillis();
    std::ifstream incomplete(entry.path() / kIncompleteFile);
    nlohmann::json k = nlohmann::json::parse(incomplete, nullptr, false);
    if (k.is_object()) {
      p.incomplete = k.value("reason", "incomplete");
      p.incomplete_since_unix_ms = k.value("since_unix_ms", int64_t{0});
    }
    if (const std::string held = NewestHeld(key); !held.empty()) {
      p.held_frame_of_reference = HeldFrameOfReference(held);
    }
    if (spool_ != nullptr) spool_->Add(p.bytes);
    Pending& kept = pending_[key] = p;
    if (was_open) {
      // An association was storing into it when the server stopped: what
      // it would have sent next never arrived.
      MarkIncomplete(key, kept,
                     "the server stopped while it was being received");
      ++interrupted;
    }
    FsyncPath(entry.path().string(), true);
    ++recovered;
  }
  int64_t unmatched_bytes =
      TreeSize((fs::path(options_.root) / "unmatched").string());
  if (spool_ != nullptr) spool_->Add(unmatched_bytes);
  if (recovered > 0) {
    spdlog::info(
        "dicom: {} series received before the restart wait for "
        "completion again ({} of them interrupted mid-association, now "
        "incomplete)",
        recovered, interrupted);
  }
  return absl::OkStatus();
}

void SeriesAssembler::Start() {
  std::lock_guard<std::mutex> lock(mu_);
  if (thread_.joinable()) return;
  stopping_ = false;
  thread_ = std::thread([this] { Loop(); });
}

void SeriesAssembler::Stop() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

int SeriesAssembler::pending_series() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(pending_.size());
}

std::string SeriesAssembler::StagingPath() {
  std::lock_guard<std::mutex> lock(mu_);
  return (fs::path(options_.root) / "incoming" /
          absl::StrCat(::getpid(), "-", next_staging_++, ".part"))
      .string();
}

uint64_t SeriesAssembler::BeginTransfer(Door door,
                                        const std::string& calling_ae,
                                        const std::string& called_ae) {
  std::lock_guard<std::mutex> lock(mu_);
  const uint64_t id = ++next_association_;
  Association& a = associations_[id];
  a.door = door;
  a.calling_ae = calling_ae;
  a.called_ae = called_ae;
  return id;
}

void SeriesAssembler::MarkIncomplete(const std::string& key, Pending& p,
                                     const std::string& reason) {
  // Only an association that begins after this moment can complete it.
  p.incomplete_after = next_association_;
  p.release_requested = false;
  if (p.incomplete.has_value()) return;
  p.incomplete = reason;
  p.incomplete_since_unix_ms = options_.clock->UnixMillis();
  nlohmann::json j = {{"reason", reason},
                      {"since_unix_ms", p.incomplete_since_unix_ms}};
  if (absl::Status s = WriteFileAtomically(
          (fs::path(SeriesDir(key)) / kIncompleteFile).string(),
          j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace));
      !s.ok()) {
    // Kept in memory all the same; after a restart the open-<n> files of
    // an interrupted association mark it again.
    spdlog::error("dicom: cannot record that a series is incomplete: {}",
                  LogSafe(s.message()));
  }
  if (metrics_ != nullptr) metrics_->DicomEvent("series_incomplete");
  spdlog::warn(
      "dicom: a series from {} -> {} ({} instance(s)) is incomplete: {}; it "
      "makes no job until a sender completes it, and is dropped if nothing "
      "of it arrives for {} s",
      LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances, reason,
      options_.unmatched_retention_seconds);
}

std::string SeriesAssembler::NewestHeld(const std::string& key) const {
  std::error_code ec;
  std::string held;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string name = entry.path().filename().string();
    // <key>-<ms>: names sort by time within a key while the times have as
    // many digits, which holds for centuries.
    if (absl::StartsWith(name, key + "-") && entry.path().string() > held) {
      held = entry.path().string();
    }
  }
  return held;
}

// Hard-links (or copies) the instances of `from` that `dir` lacks into it.
// Returns the instances and bytes added.
absl::Status SeriesAssembler::StartSeries(const std::string& key, Pending& p,
                                          const Association& a,
                                          const std::string& held) {
  std::error_code ec;
  const std::string dir = SeriesDir(key);
  fs::create_directories(dir, ec);
  if (ec) return absl::ResourceExhaustedError("cannot create a series folder");
  nlohmann::json origin = {{"called_ae", a.called_ae},
                           {"calling_ae", a.calling_ae}};
  if (absl::Status s = WriteFileAtomically(
          (fs::path(dir) / "origin.json").string(),
          origin.dump(-1, ' ', false,
                      nlohmann::json::error_handler_t::replace));
      !s.ok()) {
    fs::remove_all(dir, ec);
    return absl::ResourceExhaustedError(s.message());
  }
  p.called_ae = a.called_ae;
  p.first_arrival_unix_ms = options_.clock->UnixMillis();
  p.calling_ae = a.calling_ae;
  // The series was complete before (its job made, or no rule matched) and
  // is held: the next job takes those instances too.
  if (!held.empty()) {
    const bool had_job = fs::exists(fs::path(held) / "job", ec);
    const auto [n, bytes] = CarryInstances(held, dir);
    p.instances += n;
    p.bytes += bytes;
    p.carried = n;
    // Hard links share the held copy's blocks; counted again all the same,
    // as a job's hard-linked upload is.
    if (spool_ != nullptr) spool_->Add(bytes);
    spdlog::info(
        "dicom: a series from {} -> {} that {} received more instances; "
        "it waits for completion again with its {} earlier instance(s)",
        LogSafe(a.calling_ae), LogSafe(a.called_ae),
        had_job ? "already made its job" : "was held without a job", n);
  }
  FsyncPath((fs::path(options_.root) / "series").string(), true);
  return absl::OkStatus();
}

absl::Status SeriesAssembler::MarkTransferOpen(const std::string& key,
                                               Pending& p, uint64_t transfer,
                                               Association& a) {
  // While the transfer stores into the series, a file says so: a restart
  // then knows the transfer was interrupted.
  if (p.open.count(transfer) > 0) return absl::OkStatus();
  const std::string marker =
      (fs::path(SeriesDir(key)) / absl::StrCat(kOpenPrefix, transfer)).string();
  const int fd = ::open(marker.c_str(), O_CREAT | O_WRONLY | O_CLOEXEC, 0600);
  if (fd < 0) {
    return absl::ResourceExhaustedError(
        "the disk is full: cannot record a transfer in progress");
  }
  ::close(fd);
  p.open.insert(transfer);
  a.series.insert(key);
  return absl::OkStatus();
}

absl::StatusOr<std::string> SeriesAssembler::AddInstance(
    uint64_t association, const std::string& staged, int64_t received_bytes) {
  std::error_code ec;
  struct Cleanup {
    const std::string& path;
    bool keep = false;
    ~Cleanup() {
      if (!keep) ::unlink(path.c_str());
    }
  } cleanup{staged};
  // Refused before its series is known: every series of the association
  // misses an instance.
  auto refuse_unknown = [&](absl::Status status) -> absl::Status {
    InstanceRefused(association);
    return status;
  };
  absl::StatusOr<ReceivedInstance> received =
      ReadReceivedInstance(staged, received_bytes, options_.scan_limits);
  if (!received.ok()) return refuse_unknown(received.status());
  const int64_t size = received->size;
  const InstanceIds& ids = received->ids;
  std::string called_ae;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto a = associations_.find(association);
    if (a == associations_.end()) {
      return absl::InternalError("an instance outside an association");
    }
    called_ae = a->second.called_ae;
  }
  const std::string key = Key(called_ae, ids.study_uid, ids.series_uid);
  const std::string dir = SeriesDir(key);
  const std::string name = InstanceName(ids.sop_instance_uid);
  const std::string target = (fs::path(dir) / name).string();
  absl::Status synced = FsyncFile(staged);
  // A re-sent instance: is its content what the series holds already? Read
  // here, outside the lock every transfer needs (issue 39: only new content
  // can complete an incomplete series).
  bool same_as_held = false;
  if (fs::exists(target, ec)) {
    absl::StatusOr<std::string> held_hash = DatasetSha256(target);
    absl::StatusOr<std::string> new_hash = DatasetSha256(staged);
    same_as_held = held_hash.ok() && new_hash.ok() && *held_hash == *new_hash;
  }

  std::lock_guard<std::mutex> lock(mu_);
  Association& a = associations_[association];
  auto it = pending_.find(key);
  // A refusal of an instance whose series is known: the series misses it.
  auto refuse = [&](absl::Status status) -> absl::Status {
    a.refused.insert(key);
    auto p = pending_.find(key);
    if (p != pending_.end()) {
      MarkIncomplete(
          key, p->second,
          absl::StrCat("an instance was refused (", status.message(), ")"));
    }
    return status;
  };
  if (!synced.ok()) return refuse(synced);
  // The same SOP classes at every door (intake.h): the DIMSE listener
  // negotiates only these; a STOW-RS part may be anything. Its series (if
  // the node has one of that key) misses it; other series of the transfer
  // do not.
  if (!StorableSopClass(ids.sop_class_uid)) {
    return refuse(absl::UnimplementedError(
        "the node does not store instances of this SOP class (it takes CT "
        "and MR images, SEG and RTSTRUCT)"));
  }
  const bool fresh = it == pending_.end();
  // A late instance of a held series (see "Another frame of reference").
  const std::string held = fresh ? NewestHeld(key) : "";
  const std::string held_frame =
      fresh ? (held.empty() ? "" : HeldFrameOfReference(held))
            : it->second.held_frame_of_reference;
  if (!held_frame.empty() && !ids.frame_of_reference_uid.empty() &&
      ids.frame_of_reference_uid != held_frame) {
    if (metrics_ != nullptr) {
      metrics_->DicomEvent("instances_other_frame_of_reference");
    }
    spdlog::warn(
        "dicom: an instance from {} -> {} of a series held from before has "
        "another frame of reference than the held instances: refused, never "
        "merged into another geometry (send it as a series of its own)",
        LogSafe(a.calling_ae), LogSafe(a.called_ae));
    return refuse(absl::InvalidArgumentError(
        "the instance's frame of reference differs from that of the "
        "instances of its series held from before: refused, not merged into "
        "another geometry"));
  }
  Pending candidate;
  Pending& p = fresh ? candidate : it->second;
  const bool replaces = !fresh && fs::exists(target, ec);
  if (!replaces && p.instances + 1 > options_.max_instances_per_series) {
    return refuse(absl::ResourceExhaustedError(absl::StrCat(
        "the series already holds ", p.instances, " instances, the limit")));
  }
  if (p.bytes + size > options_.max_bytes_per_series) {
    return refuse(absl::ResourceExhaustedError(
        "the series would exceed the byte limit per series"));
  }
  if (spool_ != nullptr && !spool_->TryReserve(size)) {
    return refuse(absl::ResourceExhaustedError("the spool quota is reached"));
  }
  Pending* series = &p;
  if (fresh) {
    candidate.held_frame_of_reference = held_frame;
    if (absl::Status s = StartSeries(key, candidate, a, held); !s.ok()) {
      if (spool_ != nullptr) spool_->Release(size);
      return refuse(s);
    }
    series = &(pending_[key] = candidate);
  }
  if (absl::Status s = MarkTransferOpen(key, *series, association, a);
      !s.ok()) {
    if (spool_ != nullptr) spool_->Release(size);
    return refuse(s);
  }
  int64_t replaced_bytes = 0;
  const bool replaced = fs::exists(target, ec);
  if (replaced) {
    replaced_bytes = static_cast<int64_t>(fs::file_size(target, ec));
  }
  if (::rename(staged.c_str(), target.c_str()) != 0) {
    if (spool_ != nullptr) spool_->Release(size);
    return refuse(absl::ResourceExhaustedError(
        "the disk is full: cannot keep a received instance"));
  }
  cleanup.keep = true;
  FsyncPath(dir, true);
  if (replaced && spool_ != nullptr) spool_->Release(replaced_bytes);
  if (!replaced) ++series->instances;
  Contribution& contribution = a.contributed[key];
  contribution.instances.insert(name);
  if (!replaced || !same_as_held) contribution.brought_new = true;
  series->bytes += size - replaced_bytes;
  series->last_arrival = options_.clock->Now();
  series->release_requested = false;
  return key;
}

void SeriesAssembler::InstanceRefused(uint64_t association) {
  std::lock_guard<std::mutex> lock(mu_);
  auto a = associations_.find(association);
  if (a == associations_.end()) return;
  a->second.tainted = true;
  for (const std::string& key : a->second.series) {
    auto p = pending_.find(key);
    if (p != pending_.end()) {
      MarkIncomplete(key, p->second,
                     "its association had an instance refused that could not "
                     "be read");
    }
  }
}

void SeriesAssembler::EndTransfer(uint64_t association, bool released) {
  bool any = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = associations_.find(association);
    if (it == associations_.end()) return;
    const Association a = std::move(it->second);
    associations_.erase(it);
    std::set<std::string> keys = a.series;
    keys.insert(a.refused.begin(), a.refused.end());
    for (const std::string& key : keys) {
      auto pit = pending_.find(key);
      if (pit == pending_.end()) continue;
      Pending& p = pit->second;
      const std::string dir = SeriesDir(key);
      if (p.open.erase(association) > 0) {
        std::error_code ec;
        fs::remove(fs::path(dir) / absl::StrCat(kOpenPrefix, association), ec);
      }
      const bool clean = released && !a.tainted && a.refused.count(key) == 0;
      if (!clean) {
        MarkIncomplete(
            key, p,
            released ? "an instance of it was refused"
            : a.door == Door::kAssociation
                ? "its association ended without a normal release (aborted, "
                  "cut off or lost)"
                : "a STOW-RS request into it did not arrive whole (a body "
                  "short of its Content-Length, cut off, malformed or too "
                  "large)");
      } else if (p.incomplete.has_value() && association > p.incomplete_after) {
        const auto contributed = a.contributed.find(key);
        ResumeIfCompleted(key, p,
                          contributed != a.contributed.end()
                              ? contributed->second
                              : Contribution{});
      }
      if (clean && p.open.empty() && !p.incomplete.has_value()) {
        p.release_requested = true;
        p.released_through = a.door;
        any = true;
      }
      FsyncPath(dir, true);
    }
  }
  if (any) cv_.notify_all();
}

void SeriesAssembler::ResumeIfCompleted(const std::string& key, Pending& p,
                                        const Contribution& contribution) {
  // A transfer that began after the series became incomplete stored into
  // it and ended whole. It completed the series if it brought what the
  // series lacked, or re-sent all of it; re-sending some of what is held
  // proves nothing (see "Completeness" in series_assembler.h).
  const bool whole_series =
      static_cast<int64_t>(contribution.instances.size()) >= p.instances;
  if (!contribution.brought_new && !whole_series) {
    if (metrics_ != nullptr)
      metrics_->DicomEvent("series_resend_not_completing");
    spdlog::warn(
        "dicom: a series from {} -> {} ({} instance(s)) stays incomplete: a "
        "later transfer re-sent {} instance(s) it already held, unchanged, "
        "and nothing it lacked",
        LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances,
        contribution.instances.size());
    return;
  }
  std::error_code ec;
  fs::remove(fs::path(SeriesDir(key)) / kIncompleteFile, ec);
  spdlog::info(
      "dicom: a series from {} -> {} ({} instance(s)) is complete again "
      "after a later transfer of it ({})",
      LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances,
      contribution.brought_new ? "it brought what the series lacked"
                               : "it re-sent every instance");
  p.incomplete.reset();
}

int SeriesAssembler::CompleteStableSeries() {
  const std::shared_ptr<const RuleSet> rules = this->rules();
  const auto now = options_.clock->Now();
  const auto stable =
      std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(rules->stable_seconds));
  std::vector<std::pair<std::string, Pending>> ready;
  std::vector<std::string> dirs;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto it = pending_.begin(); it != pending_.end();) {
      Pending& p = it->second;
      // Never while a transfer into it is open, never when incomplete.
      if (!p.open.empty() || p.incomplete.has_value()) {
        ++it;
        continue;
      }
      const bool stable_over = now - p.last_arrival >= stable;
      if (!stable_over && !p.release_requested) {
        ++it;
        continue;
      }
      if (!stable_over) {
        // Its last transfer ended whole before the stable wait ended: only
        // a rule that says that transfer held the whole series cuts the
        // wait short: complete_on_release for an association,
        // complete_on_request for a STOW-RS request (a request is only part
        // of an upload unless the rule says otherwise; issue 39). The files
        // are all there (and passed the bounded scan), so their headers
        // are read now.
        SeriesFacts facts = ReadSeriesFacts(SeriesDir(it->first));
        facts.calling_ae = p.calling_ae;
        facts.called_ae = p.called_ae;
        const Rule* rule = rules->FirstMatch(facts);
        p.release_requested = false;
        const bool transfer_held_series =
            rule != nullptr && (p.released_through == Door::kAssociation
                                    ? rule->complete_on_release
                                    : rule->complete_on_request);
        if (!transfer_held_series) {
          ++it;
          continue;
        }
      }
      // Out of series/, so that a new instance of the series starts a new
      // folder instead of joining this one while its job is made.
      const std::string dir = (fs::path(options_.root) / "completing" /
                               absl::StrCat(it->first, "-", ++next_completion_))
                                  .string();
      if (::rename(SeriesDir(it->first).c_str(), dir.c_str()) != 0) {
        spdlog::error(
            "dicom: cannot move a complete series out of the way; "
            "it stays pending");
        ++it;
        continue;
      }
      ready.emplace_back(it->first, it->second);
      dirs.push_back(dir);
      it = pending_.erase(it);
    }
  }
  for (size_t i = 0; i < ready.size(); ++i) {
    Complete(ready[i].first, ready[i].second, dirs[i]);
  }
  return static_cast<int>(ready.size());
}

void SeriesAssembler::DropStaleIncomplete() {
  const auto now = options_.clock->Now();
  const auto wait =
      std::chrono::duration<double>(options_.unmatched_retention_seconds);
  std::vector<std::pair<std::string, Pending>> dropped;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto it = pending_.begin(); it != pending_.end();) {
      const Pending& p = it->second;
      if (!p.incomplete.has_value() || !p.open.empty() ||
          now - p.last_arrival < wait) {
        ++it;
        continue;
      }
      std::error_code ec;
      fs::remove_all(SeriesDir(it->first), ec);
      if (spool_ != nullptr) spool_->Release(p.bytes);
      dropped.emplace_back(it->first, p);
      KeptSeries gone;
      gone.state = "dropped";
      gone.id = it->first;
      gone.calling_ae = p.calling_ae;
      gone.called_ae = p.called_ae;
      gone.instances = p.instances;
      gone.kept_since_unix_ms = options_.clock->UnixMillis();
      gone.why = absl::StrCat(
          "dropped as incomplete (", p.incomplete.value_or(""),
          ") after receiving nothing for ",
          options_.unmatched_retention_seconds, " s; no job was made of it");
      recently_dropped_.push_back(std::move(gone));
      while (recently_dropped_.size() > kRecentlyDroppedKept) {
        recently_dropped_.pop_front();
      }
      it = pending_.erase(it);
    }
  }
  for (const auto& [key, p] : dropped) {
    if (metrics_ != nullptr) metrics_->DicomEvent("series_incomplete_dropped");
    spdlog::warn(
        "dicom: an incomplete series from {} -> {} ({} instance(s); {}) "
        "received nothing for {} s and was dropped; no job was made of it",
        LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances,
        p.incomplete.value_or(""), options_.unmatched_retention_seconds);
  }
}

void SeriesAssembler::Loop() {
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    cv_.wait_for(lock, options_.poll_interval);
    if (stopping_) break;
    lock.unlock();
    CompleteStableSeries();
    const auto now = options_.clock->Now();
    if (now - last_sweep_ > std::chrono::seconds(1)) {
      last_sweep_ = now;
      SweepUnmatched();
      DropStaleIncomplete();
    }
    lock.lock();
  }
}

}  // namespace interslice::server::node
