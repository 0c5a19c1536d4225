#include "server/engine/job_manager.h"

#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/strip.h"
#include "core/common/sha256.h"
#include "job/job.h"
#include "job/wire.h"
#include "nlohmann/json.hpp"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/base/redact.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

constexpr int kMaxFiles = 100000;
constexpr size_t kMaxLabelBytes = 200;

std::string NewJobId() {
  static std::mutex mu;
  static std::mt19937_64 rng{std::random_device{}()};
  std::lock_guard<std::mutex> lock(mu);
  char buffer[17];
  std::snprintf(buffer, sizeof(buffer), "%016llx",
                static_cast<unsigned long long>(rng()));
  return buffer;
}

using job::IsTerminalState;

// One audit record about `job` (its owner, and its origin when the DICOM
// node made it); nothing without an audit trail.
void AuditJob(AuditLog* audit, const std::shared_ptr<Job>& job,
              const char* event, AuditOutcome outcome,
              const std::string& detail) {
  if (audit == nullptr) return;
  AuditEvent e;
  e.event = event;
  e.outcome = outcome;
  e.identity = job->owner();
  e.source = job->Snapshot(false).origin();
  e.job = job->id();
  e.detail = detail;
  audit->Record(std::move(e));
}

// A delivery of the job's results to a DICOM peer is still to be made: the
// results must stay.
bool HasPendingDelivery(const JobRecord& record) {
  for (const v1::Delivery& d : record.status().deliveries()) {
    if (d.state() == v1::Delivery::PENDING) return true;
  }
  return false;
}

std::chrono::steady_clock::time_point SteadyFromUnixMillis(int64_t ms) {
  const int64_t delta = ms - UnixMillisNow();
  return std::chrono::steady_clock::now() + std::chrono::milliseconds(delta);
}

const char* OutcomeName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_SUCCEEDED:
      return "succeeded";
    case v1::JOB_STATE_CANCELLED:
      return "cancelled";
    default:
      return "failed";
  }
}

// Every file of every artifact, in report order (a derived DICOM series is a
// folder: each of its files becomes an artifact named "<folder>/<file>", one
// level, the only nesting), with its size and SHA-256 hashed on `threads`
// threads; `total_bytes` their sum.
absl::StatusOr<std::vector<v1::ArtifactInfo>> DescribeArtifacts(
    const std::vector<Artifact>& produced, int threads, int64_t* total_bytes) {
  struct ArtifactFile {
    std::string name, kind;
    fs::path path;
  };
  std::vector<ArtifactFile> files;
  for (const Artifact& a : produced) {
    const fs::path top(a.path);
    std::vector<ArtifactFile> entries;
    std::error_code ec;
    if (fs::is_directory(top, ec)) {
      for (const auto& entry : fs::directory_iterator(top, ec)) {
        if (!entry.is_regular_file(ec)) continue;
        entries.push_back(
            {top.filename().string() + "/" + entry.path().filename().string(),
             a.kind, entry.path()});
      }
      std::sort(entries.begin(), entries.end(),
                [](const ArtifactFile& x, const ArtifactFile& y) {
                  return x.name < y.name;
                });
    } else {
      entries.push_back({top.filename().string(), a.kind, top});
    }
    files.insert(files.end(), entries.begin(), entries.end());
  }
  std::vector<std::string> paths;
  for (const ArtifactFile& f : files) paths.push_back(f.path.string());
  // Hashing re-reads every output (~0.25 s per 400 MB in one thread): as
  // many threads as the job had, so it scales like the job's writing.
  const std::vector<absl::StatusOr<std::string>> shas =
      Sha256OfFiles(paths, threads);
  std::vector<v1::ArtifactInfo> artifacts;
  *total_bytes = 0;
  for (size_t n = 0; n < files.size(); ++n) {
    if (!shas[n].ok()) return shas[n].status();
    std::error_code ec;
    const int64_t size = static_cast<int64_t>(fs::file_size(files[n].path, ec));
    v1::ArtifactInfo info;
    info.set_name(files[n].name);
    info.set_kind(files[n].kind);
    info.set_media_type(job::MediaTypeForArtifact(files[n].name));
    info.set_size_bytes(size);
    info.set_sha256(*shas[n]);
    artifacts.push_back(info);
    *total_bytes += size;
  }
  return artifacts;
}

// The files of a job's DICOM artifacts (media type application/dicom),
// in artifact order, below its output folder: what its deliveries send.
template <typename Artifacts>
std::vector<std::string> DicomArtifactFiles(const Artifacts& artifacts,
                                            const std::string& output_dir) {
  std::vector<std::string> files;
  for (const v1::ArtifactInfo& a : artifacts) {
    if (a.media_type() == "application/dicom") {
      files.push_back((fs::path(output_dir) / a.name()).string());
    }
  }
  return files;
}

// The structured origin of a job the DICOM listener made, whose origin text
// is "dicom:<calling AE>-><called AE> rule <name>" (JobStatus.origin). AE
// titles may hold "->" or " rule ": the titles the listener wrote beside
// the series' files (origin.json) take precedence when the text starts with
// them; else the first "->" and the first " rule " after it split the text.
v1::JobOrigin DicomOrigin(const std::string& text,
                          const std::string& files_dir) {
  v1::JobOrigin origin;
  origin.set_door(v1::JobOrigin::DICOM);
  absl::string_view rest(text);
  if (!absl::ConsumePrefix(&rest, "dicom:")) return origin;
  std::ifstream file(fs::path(files_dir) / "origin.json");
  const nlohmann::json written = nlohmann::json::parse(file, nullptr, false);
  if (written.is_object()) {
    const std::string calling = written.value("calling_ae", "");
    const std::string called = written.value("called_ae", "");
    absl::string_view after = rest;
    if (absl::ConsumePrefix(&after,
                            absl::StrCat(calling, "->", called, " rule "))) {
      origin.set_calling_ae(calling);
      origin.set_called_ae(called);
      origin.set_rule(std::string(after));
      return origin;
    }
  }
  const size_t arrow = rest.find("->");
  const size_t rule =
      arrow == absl::string_view::npos ? arrow : rest.find(" rule ", arrow + 2);
  if (rule == absl::string_view::npos) return origin;
  origin.set_calling_ae(std::string(rest.substr(0, arrow)));
  origin.set_called_ae(std::string(rest.substr(arrow + 2, rule - arrow - 2)));
  origin.set_rule(std::string(rest.substr(rule + 6)));
  return origin;
}

}  // namespace

int64_t UnixMillisNow() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

void JobManager::RecordSource(Job& job, const job::SourceSeries& source) {
  job.Update([&source](JobRecord& r) {
    v1::JobStatus* s = r.mutable_status();
    s->set_modality(source.modality);
    s->set_instance_count(static_cast<int32_t>(
        std::min<int64_t>(source.instance_count, INT32_MAX)));
    s->set_study_instance_uid(source.study_instance_uid);
    s->set_series_instance_uid(source.series_instance_uid);
  });
}

v1::JobStatus Job::Snapshot(bool with_report) const {
  std::lock_guard<std::mutex> lock(mu_);
  v1::JobStatus status = record_.status();
  if (!with_report) status.clear_report_json();
  return status;
}

void Job::Subscribe(std::shared_ptr<Subscription> subscription) {
  std::lock_guard<std::mutex> lock(mu_);
  subscriptions_.erase(
      std::remove_if(subscriptions_.begin(), subscriptions_.end(),
                     [](const auto& s) { return s->closed(); }),
      subscriptions_.end());
  subscriptions_.push_back(std::move(subscription));
}

void Job::Update(const std::function<void(JobRecord&)>& change) {
  std::vector<std::shared_ptr<Subscription>> subscriptions;
  {
    std::lock_guard<std::mutex> lock(mu_);
    change(record_);
    record_.mutable_status()->set_sequence(record_.status().sequence() + 1);
    subscriptions = subscriptions_;
  }
  for (const auto& s : subscriptions) s->Fire();
}

JobManager::JobManager(const ManagerOptions& options, Spool* spool,
                       Metrics* metrics)
    : options_(options), spool_(spool), metrics_(metrics) {}

JobManager::~JobManager() { Shutdown(std::chrono::milliseconds(0)); }

absl::Status JobManager::Recover() {
  absl::StatusOr<std::vector<JobRecord>> records = spool_->LoadRecords();
  if (!records.ok()) return records.status();
  std::sort(records->begin(), records->end(),
            [](const JobRecord& a, const JobRecord& b) {
              return a.status().created_unix_ms() <
                     b.status().created_unix_ms();
            });
  int requeued = 0, aborted = 0, kept = 0;
  for (JobRecord& record : *records) {
    const std::string id = record.status().job_id();
    if (record.ephemeral()) {
      spool_->RemoveJob(id);
      continue;
    }
    std::shared_ptr<Job> job(new Job(id, false, record.owner()));
    // The kind once, from the record (one written by an older version may
    // not make one: the job then fails when it runs, saying why).
    if (absl::StatusOr<std::unique_ptr<job::JobKind>> kind =
            job::MakeJobFromWire(record.spec());
        kind.ok()) {
      job->kind_ = *std::move(kind);
    } else {
      job->kind_error_ = kind.status();
    }
    const v1::JobState state = record.status().state();
    const bool interrupted = state == v1::JOB_STATE_RUNNING;
    if (interrupted && record.attempts() < options_.max_attempts) {
      // Killed mid-job (kill -9, power cut, OOM killer): the upload is
      // still in the spool, so run it again; the attempts already counted
      // bound how often.
      v1::JobStatus* s = record.mutable_status();
      s->set_state(v1::JOB_STATE_QUEUED);
      s->set_started_unix_ms(0);
      s->mutable_progress()->set_stage("queued");
      s->set_sequence(s->sequence() + 1);
      spool_->RemoveOutputs(id);
      job->record_ = record;
      if (absl::Status st = spool_->WriteRecord(record); !st.ok()) {
        spdlog::error("job={} cannot persist recovery: {}", id,
                      RedactPhi(st.message()));
      }
      spdlog::warn(
          "job={} was running when the server stopped; running it again "
          "(start {} of at most {})",
          id, record.attempts() + 1, options_.max_attempts);
      ++kept;
    } else if (interrupted || state == v1::JOB_STATE_UPLOADING) {
      v1::JobStatus* s = record.mutable_status();
      s->set_state(v1::JOB_STATE_FAILED);
      s->set_error_code(static_cast<int>(absl::StatusCode::kAborted));
      s->set_error_message(
          interrupted
              ? absl::StrFormat(
                    "the server stopped while the job was running, %d "
                    "time(s); it is not run again (it may be what stops the "
                    "server)",
                    record.attempts())
              : "the server stopped while the job was being uploaded; "
                "submit it again");
      s->set_finished_unix_ms(UnixMillisNow());
      s->set_expires_unix_ms(UnixMillisNow() +
                             options_.retention_seconds * 1000);
      s->set_sequence(s->sequence() + 1);
      spool_->RemoveUploads(id);
      spool_->RemoveOutputs(id);
      job->record_ = record;
      if (absl::Status st = spool_->WriteRecord(record); !st.ok()) {
        spdlog::error("job={} cannot persist recovery: {}", id,
                      RedactPhi(st.message()));
      }
      ++aborted;
    } else {
      job->record_ = record;
      ++kept;
    }
    if (record.deadline_unix_ms() > 0) {
      job->token_.SetDeadline(SteadyFromUnixMillis(record.deadline_unix_ms()));
    }
    if (outbox_ != nullptr && HasPendingDelivery(job->record_)) {
      // Results not yet on every destination: the outbox carries on where
      // it stopped (attempts and next try kept).
      const std::vector<std::string> files = DicomArtifactFiles(
          job->record_.status().artifacts(), spool_->OutputDir(id));
      for (const v1::Delivery& d : job->record_.status().deliveries()) {
        outbox_->Add(id, d, files, job->record_.status().finished_unix_ms());
      }
    }
    std::lock_guard<std::mutex> lock(mu_);
    jobs_[id] = job;
    if (job->record_.status().state() == v1::JOB_STATE_QUEUED) {
      queue_.push_back(job);
      ++requeued;
      --kept;
    }
  }
  spdlog::info(
      "spool recovered: {} queued job(s) requeued, {} interrupted "
      "job(s) marked failed, {} finished job(s) kept",
      requeued, aborted, kept);
  return absl::OkStatus();
}

void JobManager::Start() {
  std::lock_guard<std::mutex> lock(mu_);
  for (int i = 0; i < options_.workers; ++i) {
    workers_.emplace_back([this] { WorkerLoop(); });
  }
  ticker_ = std::thread([this] { TickerLoop(); });
  PublishGauges();
}

absl::StatusOr<std::shared_ptr<Job>> JobManager::Admit(
    const v1::UploadHeader& header, bool ephemeral,
    std::optional<std::chrono::steady_clock::time_point> deadline,
    const std::string& owner) {
  auto reject = [this](absl::Status status) {
    metrics_->JobFinished("rejected");
    return status;
  };
  if (draining()) {
    return reject(absl::UnavailableError(
        "the server is shutting down and accepts no new jobs; retry on "
        "another replica"));
  }
  const bool pacs = header.spec().has_pacs_source();
  if (pacs && header.file_count() != 0) {
    return reject(absl::InvalidArgumentError(
        "spec.pacs_source reads the series from a DICOM peer: the upload "
        "must carry no files (file_count 0)"));
  }
  if (!pacs && (header.file_count() < 1 || header.file_count() > kMaxFiles)) {
    return reject(absl::InvalidArgumentError(
        absl::StrCat("header.file_count must be between 1 and ", kMaxFiles)));
  }
  if (pacs) {
    const v1::PacsSeriesSource& source = header.spec().pacs_source();
    if (series_source_ == nullptr) {
      return reject(absl::InvalidArgumentError(
          "spec.pacs_source names a DICOM peer, but the server has none "
          "configured (--dicom-peers)"));
    }
    if (absl::Status s = series_source_->CheckPeer(source.peer()); !s.ok()) {
      return reject(s);
    }
    if (source.study_instance_uid().empty() ||
        source.series_instance_uid().empty()) {
      return reject(absl::InvalidArgumentError(
          "spec.pacs_source needs study_instance_uid and "
          "series_instance_uid"));
    }
  }
  if (header.total_bytes() < 0) {
    return reject(
        absl::InvalidArgumentError("header.total_bytes must be >= 0"));
  }
  if (header.total_bytes() > options_.max_upload_bytes) {
    return reject(absl::ResourceExhaustedError(
        absl::StrCat("the upload (", header.total_bytes(),
                     " bytes) exceeds the server's limit of ",
                     options_.max_upload_bytes, " bytes per job")));
  }
  if (header.options().label().size() > kMaxLabelBytes) {
    return reject(
        absl::InvalidArgumentError("options.label is longer than 200 bytes"));
  }
  if (!(header.options().deadline_seconds() >= 0)) {
    return reject(
        absl::InvalidArgumentError("options.deadline_seconds must be >= 0"));
  }
  if (header.total_bytes() > spool_->quota_bytes()) {
    // Not "full": this upload can never fit, so retrying is pointless.
    return reject(absl::ResourceExhaustedError(
        absl::StrCat("the upload (", header.total_bytes(),
                     " bytes) exceeds the server's spool quota of ",
                     spool_->quota_bytes(), " bytes")));
  }
  // The job's kind and options, checked as every door checks them.
  absl::StatusOr<std::unique_ptr<job::JobKind>> kind =
      job::MakeJobFromWire(header.spec());
  if (!kind.ok()) return reject(kind.status());
  if (!pacs && header.file_count() < (*kind)->min_upload_files()) {
    // A fill job uploads its segmentation and its reference series' files.
    return reject(absl::InvalidArgumentError(absl::StrCat(
        "a ", (*kind)->name(), " job uploads at least ",
        (*kind)->min_upload_files(), " files: file_count must be >= ",
        (*kind)->min_upload_files(), " (got ", header.file_count(), ")")));
  }
  if (!header.spec().send_to().empty()) {
    if (outbox_ == nullptr) {
      return reject(absl::InvalidArgumentError(
          "spec.send_to names DICOM peers, but the server has none "
          "configured (--dicom-peers)"));
    }
    const std::vector<std::string> names(header.spec().send_to().begin(),
                                         header.spec().send_to().end());
    if (absl::Status s = outbox_->CheckPeers(names); !s.ok()) {
      return reject(s);
    }
    if (!(*kind)->writes_dicom()) {
      return reject(absl::InvalidArgumentError(
          "spec.send_to needs DICOM results: ask for derived series "
          "(output_series) or a segmentation"));
    }
  }

  std::string id_suffix;
  {
    std::lock_guard<std::mutex> lock(mu_);
    // The slot itself is taken by Enqueue, once the upload is complete.
    const int waiting = static_cast<int>(queue_.size()) + reserved_;
    if (waiting >= options_.max_queued_jobs) {
      metrics_->JobFinished("rejected");
      return absl::ResourceExhaustedError(
          absl::StrCat("the server's job queue is full (", waiting,
                       " job(s) waiting); retry later"));
    }
    ++uploading_;
    PublishGauges();
    id_suffix = job_id_suffix_;
  }
  auto unreserve = [this] {
    std::lock_guard<std::mutex> lock(mu_);
    --uploading_;
    PublishGauges();
  };
  if (!spool_->TryReserve(header.total_bytes())) {
    unreserve();
    return reject(absl::ResourceExhaustedError(
        "the server's spool is full; retry later"));
  }
  const std::string id = NewJobId() + id_suffix;
  if (absl::Status s = spool_->CreateJob(id); !s.ok()) {
    spool_->Release(header.total_bytes());
    unreserve();
    return s;
  }
  std::shared_ptr<Job> job(new Job(id, ephemeral, owner));
  job->kind_ = *std::move(kind);
  JobRecord& r = job->record_;
  r.set_owner(owner);
  r.mutable_status()->set_job_id(id);
  r.mutable_status()->set_state(v1::JOB_STATE_UPLOADING);
  r.mutable_status()->set_sequence(1);
  r.mutable_status()->set_created_unix_ms(UnixMillisNow());
  r.mutable_status()->set_label(header.options().label());
  v1::JobOrigin* source = r.mutable_status()->mutable_source();
  source->set_door(v1::JobOrigin::GRPC);
  source->set_client(owner);
  source->set_pacs_peer(header.spec().pacs_source().peer());
  *r.mutable_spec() = header.spec();
  *r.mutable_options() = header.options();
  r.set_ephemeral(ephemeral);
  r.set_upload_bytes(header.total_bytes());
  if (deadline.has_value()) {
    job->token_.SetDeadline(*deadline);
  } else if (header.options().deadline_seconds() > 0) {
    const auto ms =
        static_cast<int64_t>(header.options().deadline_seconds() * 1000);
    r.set_deadline_unix_ms(UnixMillisNow() + ms);
    job->token_.SetDeadline(std::chrono::steady_clock::now() +
                            std::chrono::milliseconds(ms));
  }
  spdlog::info("job={} admitted: {} file(s), {} bytes{}{}", id,
               header.file_count(), header.total_bytes(),
               ephemeral ? " (one call)" : "",
               owner.empty() ? "" : absl::StrCat(", owner ", LogSafe(owner)));
  return job;
}

absl::Status JobManager::Enqueue(const std::shared_ptr<Job>& job) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (draining_ && job->ephemeral()) {
      return absl::UnavailableError(
          "the server is shutting down and accepts no new jobs; retry on "
          "another replica");
    }
    const int waiting = static_cast<int>(queue_.size()) + reserved_;
    if (waiting >= options_.max_queued_jobs) {
      metrics_->JobFinished("rejected");
      return absl::ResourceExhaustedError(
          absl::StrCat("the server's job queue is full (", waiting,
                       " job(s) waiting); retry later"));
    }
    ++reserved_;
  }
  job->Update([](JobRecord& r) {
    r.mutable_status()->set_state(v1::JOB_STATE_QUEUED);
    r.mutable_status()->mutable_progress()->set_stage("queued");
    r.mutable_status()->mutable_progress()->set_iteration(-1);
    r.mutable_status()->mutable_progress()->set_relative_residual(-1);
    r.mutable_status()->mutable_progress()->set_energy(-1);
  });
  // Only detached jobs get a record: an Interpolate job without one is
  // deleted at start-up, since its caller is gone.
  if (!job->ephemeral()) {
    JobRecord record;
    {
      std::lock_guard<std::mutex> lock(job->mu_);
      record = job->record_;
    }
    if (absl::Status s = spool_->WriteRecord(record); !s.ok()) {
      std::lock_guard<std::mutex> lock(mu_);
      --reserved_;
      return s;  // the caller abandons the job
    }
  }
  {
    std::lock_guard<std::mutex> lock(mu_);
    --reserved_;
    --uploading_;
    jobs_[job->id()] = job;
    queue_.push_back(job);
    PublishGauges();
  }
  cv_.notify_all();  // the ticker waits on cv_ too
  spdlog::info("job={} queued", job->id());
  AuditJob(options_.audit, job, "job.submitted", AuditOutcome::kSuccess, "");
  return absl::OkStatus();
}

absl::StatusOr<std::string> JobManager::SubmitLocalFiles(
    const v1::JobSpec& spec, const std::string& files_dir,
    const std::string& owner, const std::string& origin,
    const std::map<std::string, std::string>& named_files) {
  // The series' files and the named files' bytes, for the admission.
  std::vector<fs::path> files;
  int64_t bytes = 0;
  std::error_code ec;
  for (const auto& [name, local] : named_files) {
    bytes += static_cast<int64_t>(fs::file_size(local, ec));
    if (ec) return absl::InternalError("cannot read a received file");
  }
  for (const auto& entry : fs::directory_iterator(files_dir, ec)) {
    if (entry.path().extension() != ".dcm" || !entry.is_regular_file(ec)) {
      continue;
    }
    files.push_back(entry.path());
    bytes += static_cast<int64_t>(entry.file_size(ec));
  }
  if (ec) {
    return absl::InternalError("cannot list the received files of a series");
  }
  v1::UploadHeader header;
  *header.mutable_spec() = spec;
  header.set_file_count(
      static_cast<int32_t>(files.size() + named_files.size()));
  header.set_total_bytes(bytes);
  absl::StatusOr<std::shared_ptr<Job>> job =
      Admit(header, /*ephemeral=*/false, std::nullopt, owner);
  if (!job.ok()) return job.status();
  // Exactly the files the kind takes by name, each where it keeps them.
  std::vector<std::pair<std::string, fs::path>> placed;  // local -> target
  for (const job::NamedUpload& upload : (*job)->kind()->named_uploads()) {
    const auto it = named_files.find(upload.client_name);
    if (it == named_files.end()) {
      Abandon(*job);
      return absl::InvalidArgumentError(
          absl::StrCat("a job on received files needs the file that ",
                       upload.field, " names"));
    }
    placed.emplace_back(it->second, upload.path);
  }
  if (placed.size() != named_files.size()) {
    Abandon(*job);
    return absl::InvalidArgumentError(
        "a job on received files was given a file its kind does not take");
  }
  const std::string upload = spool_->UploadDir((*job)->id());
  for (size_t i = 0; i < files.size(); ++i) {
    const fs::path target =
        fs::path(upload) / absl::StrFormat("%06d.dcm", static_cast<int>(i));
    // Same file system (both in the spool): a link, not a copy.
    fs::create_hard_link(files[i], target, ec);
    if (ec) fs::copy_file(files[i], target, ec);
    if (ec) {
      Abandon(*job);
      return absl::ResourceExhaustedError(
          "cannot place a received series into a job's upload folder");
    }
  }
  for (const auto& [local, relative] : placed) {
    const fs::path target = fs::path(upload) / relative;
    fs::create_directories(target.parent_path(), ec);
    if (!ec) fs::create_hard_link(local, target, ec);
    if (ec) fs::copy_file(local, target, ec);
    if (ec) {
      Abandon(*job);
      return absl::ResourceExhaustedError(
          "cannot place a received file into a job's upload folder");
    }
  }
  const v1::JobOrigin source = DicomOrigin(origin, files_dir);
  (*job)->Update([&origin, &source](JobRecord& r) {
    r.mutable_status()->set_origin(origin);
    *r.mutable_status()->mutable_source() = source;
  });
  if (absl::Status s = Enqueue(*job); !s.ok()) {
    Abandon(*job);
    return s;
  }
  return (*job)->id();
}

void JobManager::Abandon(const std::shared_ptr<Job>& job) {
  spool_->RemoveJob(job->id());
  spool_->Release(job->record_.upload_bytes());
  std::lock_guard<std::mutex> lock(mu_);
  --uploading_;
  PublishGauges();
  spdlog::info("job={} upload abandoned; its files were deleted", job->id());
}

void JobManager::Discard(const std::shared_ptr<Job>& job) {
  bool remove_now = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    std::lock_guard<std::mutex> job_lock(job->mu_);
    if (job->discard_) return;
    job->discard_ = true;
    job->token_.Cancel();
    auto it = std::find(queue_.begin(), queue_.end(), job);
    if (it != queue_.end()) queue_.erase(it);
    if (!job->running_ && !HasPendingDelivery(job->record_)) {
      remove_now = true;
      jobs_.erase(job->id());
    }
    PublishGauges();
  }
  if (remove_now) RemoveFinished(job);
}

void JobManager::RemoveFinished(const std::shared_ptr<Job>& job) {
  int64_t bytes = 0;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    const v1::JobState s = job->record_.status().state();
    bytes = IsTerminalState(s) ? job->record_.result_bytes()
                               : job->record_.upload_bytes();
  }
  if (outbox_ != nullptr) outbox_->Forget(job->id());
  spool_->RemoveJob(job->id());
  spool_->Release(bytes);
}

void JobManager::UpdateDelivery(const std::string& job_id,
                                const v1::Delivery& delivery) {
  std::shared_ptr<Job> job = Find(job_id);
  if (job == nullptr) return;  // deleted meanwhile
  bool ended = false;          // this update ends the delivery (audited once)
  job->Update([&](JobRecord& r) {
    for (v1::Delivery& d : *r.mutable_status()->mutable_deliveries()) {
      if (d.peer() != delivery.peer()) continue;
      ended = d.state() != delivery.state() &&
              (delivery.state() == v1::Delivery::DELIVERED ||
               delivery.state() == v1::Delivery::FAILED);
      d = delivery;
    }
  });
  if (ended && options_.audit != nullptr) {
    const bool delivered = delivery.state() == v1::Delivery::DELIVERED;
    AuditEvent e;
    e.event = delivered ? "delivery.delivered" : "delivery.failed";
    e.outcome =
        delivered ? AuditOutcome::kSuccess : AuditOutcome::kSeriousFailure;
    e.identity = job->owner();
    e.job = job_id;
    e.peer = delivery.peer();
    e.count = delivery.instances_sent();
    e.detail = delivered ? absl::StrCat(delivery.instances_sent(), " of ",
                                        delivery.instances_total(),
                                        " instance(s) accepted")
                         : delivery.last_error();
    options_.audit->Record(std::move(e));
  }
  Persist(job);
  bool remove = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    std::lock_guard<std::mutex> job_lock(job->mu_);
    // An Interpolate job whose call has ended waited only for this.
    if (job->discard_ && !job->running_ && !HasPendingDelivery(job->record_) &&
        jobs_.erase(job_id) > 0) {
      remove = true;
    }
  }
  if (remove) RemoveFinished(job);
}

void JobManager::SetJobIdSuffix(std::string suffix) {
  std::lock_guard<std::mutex> lock(mu_);
  job_id_suffix_ = std::move(suffix);
}

std::shared_ptr<Job> JobManager::Find(const std::string& id) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = jobs_.find(id);
  return it == jobs_.end() ? nullptr : it->second;
}

absl::StatusOr<v1::JobStatus> JobManager::Cancel(const std::string& id) {
  std::shared_ptr<Job> job;
  bool was_queued = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return absl::NotFoundError("no such job");
    job = it->second;
    auto q = std::find(queue_.begin(), queue_.end(), job);
    if (q != queue_.end()) {
      queue_.erase(q);
      was_queued = true;
      PublishGauges();
    }
  }
  job->token_.Cancel();
  if (was_queued) {
    job->Update([this](JobRecord& r) {
      v1::JobStatus* s = r.mutable_status();
      s->set_state(v1::JOB_STATE_CANCELLED);
      s->set_error_code(static_cast<int>(absl::StatusCode::kCancelled));
      s->set_error_message("cancelled by request");
      s->set_finished_unix_ms(UnixMillisNow());
      s->set_expires_unix_ms(UnixMillisNow() +
                             options_.retention_seconds * 1000);
      s->mutable_progress()->set_stage("done");
    });
    spool_->RemoveUploads(id);
    spool_->Release(job->record_.upload_bytes());
    Persist(job);
    metrics_->JobFinished("cancelled");
    spdlog::info("job={} cancelled while queued", id);
    AuditJob(options_.audit, job, "job.cancelled", AuditOutcome::kMinorFailure,
             "cancelled while queued");
  } else if (!IsTerminalState(job->Snapshot(false).state())) {
    job->Update(
        [](JobRecord& r) { r.mutable_status()->set_cancel_requested(true); });
    spdlog::info("job={} cancellation requested", id);
  }
  return job->Snapshot(true);
}

std::vector<v1::JobStatus> JobManager::List(bool include_finished,
                                            const std::string* owner) {
  std::vector<std::shared_ptr<Job>> jobs;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const auto& [id, job] : jobs_) {
      if (job->ephemeral()) continue;
      if (owner != nullptr && job->owner() != *owner) continue;
      jobs.push_back(job);
    }
  }
  std::vector<v1::JobStatus> out;
  for (const auto& job : jobs) {
    v1::JobStatus s = job->Snapshot(false);
    if (!include_finished && IsTerminalState(s.state())) continue;
    out.push_back(std::move(s));
  }
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) {
    return a.created_unix_ms() > b.created_unix_ms();
  });
  return out;
}

void JobManager::BeginDrain() {
  std::vector<std::shared_ptr<Subscription>> to_fire;
  std::vector<std::string> ended;
  int64_t upload_bytes = 0;
  {
    std::lock_guard<std::mutex> lock(mu_);
    draining_ = true;
    // Queued Interpolate jobs would only be cancelled at the end of the
    // grace period, their callers told nothing useful: end them now, so
    // that the callers can retry on another replica at once. The state
    // changes under mu_, so that a concurrent Discard sees a terminal job
    // and does not release its upload bytes a second time.
    const int64_t now = UnixMillisNow();
    for (auto it = queue_.begin(); it != queue_.end();) {
      const std::shared_ptr<Job> job = *it;
      if (!job->ephemeral()) {
        ++it;
        continue;
      }
      std::lock_guard<std::mutex> job_lock(job->mu_);
      v1::JobStatus* s = job->record_.mutable_status();
      s->set_state(v1::JOB_STATE_FAILED);
      s->set_error_code(static_cast<int>(absl::StatusCode::kUnavailable));
      s->set_error_message(
          "the server is shutting down and did not start the job; retry on "
          "another replica");
      s->set_finished_unix_ms(now);
      s->set_expires_unix_ms(now + options_.retention_seconds * 1000);
      s->mutable_progress()->set_stage("done");
      s->set_sequence(s->sequence() + 1);
      upload_bytes += job->record_.upload_bytes();
      to_fire.insert(to_fire.end(), job->subscriptions_.begin(),
                     job->subscriptions_.end());
      ended.push_back(job->id());
      it = queue_.erase(it);
    }
    PublishGauges();
  }
  spool_->Release(upload_bytes);
  for (const auto& subscription : to_fire) subscription->Fire();
  for (const std::string& id : ended) {
    metrics_->JobFinished("failed");
    spdlog::info("job={} not started: the server is shutting down", id);
  }
}

bool JobManager::draining() {
  std::lock_guard<std::mutex> lock(mu_);
  return draining_;
}

int JobManager::queued() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(queue_.size());
}

int JobManager::running() {
  std::lock_guard<std::mutex> lock(mu_);
  return running_;
}

void JobManager::Shutdown(std::chrono::milliseconds grace) {
  std::unique_lock<std::mutex> lock(mu_);
  if (stopping_) return;
  draining_ = true;
  if (running_ > 0) {
    spdlog::info("draining: waiting up to {} ms for {} running job(s)",
                 grace.count(), running_);
  }
  cv_.wait_for(lock, grace, [this] { return running_ == 0; });
  stopping_ = true;
  for (const auto& [id, job] : jobs_) {
    std::lock_guard<std::mutex> job_lock(job->mu_);
    if (job->running_) {
      job->shutdown_cancelled_ = true;
      job->token_.Cancel();
      spdlog::info(
          "job={} cancelled by shutdown; it will run again after a "
          "restart",
          id);
    }
  }
  lock.unlock();
  cv_.notify_all();
  for (std::thread& t : workers_) t.join();
  workers_.clear();
  if (ticker_.joinable()) ticker_.join();
}

void JobManager::PublishGauges() {
  metrics_->SetQueueDepth(uploading_ + static_cast<double>(queue_.size()));
  metrics_->SetRunning(running_);
}

void JobManager::Persist(const std::shared_ptr<Job>& job) {
  if (job->ephemeral()) return;
  JobRecord record;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    record = job->record_;
  }
  if (absl::Status s = spool_->WriteRecord(record); !s.ok()) {
    spdlog::error("job={} cannot persist its record: {}", job->id(),
                  RedactPhi(s.message()));
  }
}

void JobManager::WorkerLoop() {
  for (;;) {
    std::shared_ptr<Job> job;
    {
      std::unique_lock<std::mutex> lock(mu_);
      cv_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
      if (stopping_) return;
      job = queue_.front();
      queue_.pop_front();
      std::lock_guard<std::mutex> job_lock(job->mu_);
      job->running_ = true;
      ++running_;
      PublishGauges();
    }
    RunOne(job);
    bool remove = false;
    {
      std::lock_guard<std::mutex> lock(mu_);
      std::lock_guard<std::mutex> job_lock(job->mu_);
      job->running_ = false;
      --running_;
      if (job->discard_ && !HasPendingDelivery(job->record_)) {
        remove = true;
        jobs_.erase(job->id());
      }
      if (job->shutdown_cancelled_) jobs_.erase(job->id());
      PublishGauges();
    }
    if (remove) RemoveFinished(job);
    cv_.notify_all();  // Shutdown waits for running_ == 0
  }
}

void JobManager::RunOne(const std::shared_ptr<Job>& job) {
  const std::string& id = job->id();
  v1::JobSpec wire;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    wire = job->record_.spec();
    job->started_ = std::chrono::steady_clock::now();
  }
  job->Update([](JobRecord& r) {
    // Counted (and persisted below) before the job starts: if it takes the
    // server down, the restart sees this start.
    r.set_attempts(r.attempts() + 1);
    v1::JobStatus* s = r.mutable_status();
    s->set_state(v1::JOB_STATE_RUNNING);
    s->set_started_unix_ms(UnixMillisNow());
    s->mutable_progress()->set_stage("read");
    s->mutable_progress()->set_stage_percent(0);
    s->mutable_progress()->set_queue_position(-1);
  });
  Persist(job);
  spdlog::info("job={} started", id);

  absl::StatusOr<job::JobResult> result = Execute(job, wire);

  bool shutdown_cancelled;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    shutdown_cancelled = job->shutdown_cancelled_;
  }
  if (!result.ok() && shutdown_cancelled && !job->ephemeral()) {
    // Stopped by a drain, not by its owner: keep the upload and run it
    // after the restart.
    spool_->RemoveOutputs(id);
    job->Update([](JobRecord& r) {
      // A drain is not a crash: this start does not count.
      r.set_attempts(std::max(0, r.attempts() - 1));
      r.mutable_status()->set_state(v1::JOB_STATE_QUEUED);
      r.mutable_status()->set_started_unix_ms(0);
      r.mutable_status()->mutable_progress()->set_stage("queued");
    });
    Persist(job);
    return;
  }

  const int64_t upload_bytes = job->record_.upload_bytes();
  spool_->RemoveUploads(id);
  spool_->Release(upload_bytes);
  if (result.ok()) {
    // Before publishing: the status, the quota and the deliveries see only
    // what is kept (server/engine/spool.h).
    JobRecord record;
    {
      std::lock_guard<std::mutex> lock(job->mu_);
      record = job->record_;
    }
    if (const int64_t bytes = RemoveArtifactsNotAskedFor(record, &*result);
        bytes > 0) {
      spdlog::info("job={} kept only what it was asked for: {} bytes not kept",
                   id, bytes);
    }
  }
  const int64_t now = UnixMillisNow();
  const int64_t expires = now + options_.retention_seconds * 1000;
  absl::Status published =
      result.ok() ? Publish(job, *result, now, expires) : result.status();
  if (!published.ok()) FailJob(job, published, now, expires);
}

absl::StatusOr<job::JobResult> JobManager::Execute(
    const std::shared_ptr<Job>& job, const v1::JobSpec& wire) {
  const std::string& id = job->id();
  // The job's kind, made once (Admit, Recover); then pointed at its folders.
  absl::Status ready =
      job->kind() != nullptr ? absl::OkStatus() : job->kind_error();
  // A series named on a DICOM peer is retrieved into the upload folder
  // first; then the job runs as if it had been uploaded.
  if (ready.ok() && wire.has_pacs_source() &&
      !wire.pacs_source().peer().empty()) {
    job->Update([](JobRecord& r) {
      r.mutable_status()->mutable_progress()->set_stage("retrieve");
    });
    ready = RetrieveFromPeer(job, wire.pacs_source());
  }
  if (!ready.ok()) return ready;
  job::JobKind& work = *job->kind();
  bool omit_files_dicom_objects_carry;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    omit_files_dicom_objects_carry = DeliversOnlyDicomToPeers(job->record_);
  }
  const std::string upload_dir = spool_->UploadDir(id);
  const std::string output_dir = spool_->OutputDir(id);
  ComputeContext context;
  context.threads = options_.threads_per_job;
  context.cancel = &job->token_;
  const auto started = std::chrono::steady_clock::now();
  const bool in_process = !options_.isolate_jobs;
  const float threshold = wire.threshold();
  context.progress = [job, started, in_process,
                      threshold](const ProgressEvent& e) {
    const std::chrono::duration<double> elapsed =
        std::chrono::steady_clock::now() - started;
    job->Update([&](JobRecord& r) {
      v1::Progress* p = r.mutable_status()->mutable_progress();
      p->set_stage(e.stage);
      p->set_stage_percent(100.0 * e.fraction);
      p->set_iteration(e.iteration);
      p->set_relative_residual(e.relative_residual);
      p->set_energy(e.energy);
      p->set_elapsed_seconds(elapsed.count());
    });
    if (in_process) InjectTestFault(e.stage, threshold);
  };
  // A deadline that passed while queued fails fast, without reading.
  if (absl::Status early = job->token_.Check(); !early.ok()) return early;
  if (options_.isolate_jobs) {
    spool::v1::WorkerRequest request;
    *request.mutable_spec() = wire;
    {
      std::lock_guard<std::mutex> lock(job->mu_);
      request.set_deadline_unix_ms(job->record_.deadline_unix_ms());
    }
    request.set_input_dir(upload_dir);
    request.set_output_dir(output_dir);
    request.set_max_output_voxels(options_.max_output_voxels);
    request.set_threads(options_.threads_per_job);
    request.set_server_pid(::getpid());
    request.set_omit_files_dicom_objects_carry(omit_files_dicom_objects_carry);
    WorkerOutcome outcome;
    absl::StatusOr<job::JobResult> result = RunInWorkerProcess(
        request, context, options_.worker, &outcome,
        [job](const job::SourceSeries& source) { RecordSource(*job, source); });
    if (outcome.crashed) {
      spdlog::error(
          "job={} worker process crashed (signal {}) during stage {}; the "
          "job failed, the server carries on",
          id, outcome.signal,
          outcome.last_stage.empty() ? "start" : outcome.last_stage);
    }
    return result;
  }
  if (absl::Status s =
          work.UseSpool(upload_dir, output_dir, options_.max_output_voxels);
      !s.ok()) {
    return s;
  }
  if (omit_files_dicom_objects_carry) work.OmitFilesDicomObjectsCarry();
  // As the worker process does (job_worker.cc): which series, for the
  // status; the job's own read reports a folder without one.
  if (absl::StatusOr<job::SourceSeries> source = job::DescribeSourceSeries(
          upload_dir, wire.series_instance_uid(),
          ComputeContext{.threads = context.threads, .cancel = context.cancel});
      source.ok()) {
    RecordSource(*job, *source);
  }
  return work.Run(context);
}

absl::Status JobManager::Publish(const std::shared_ptr<Job>& job,
                                 const job::JobResult& result, int64_t now,
                                 int64_t expires) {
  const std::string& id = job->id();
  for (const StageTiming& s : result.stages) {
    metrics_->StageSeconds(s.stage, s.seconds);
  }
  int64_t result_bytes = 0;
  absl::StatusOr<std::vector<v1::ArtifactInfo>> artifacts = DescribeArtifacts(
      result.artifacts, options_.threads_per_job, &result_bytes);
  if (!artifacts.ok()) return artifacts.status();
  spool_->Add(result_bytes);
  const std::string& json = result.report_json;
  // One delivery per destination, of every DICOM file the job wrote.
  std::vector<std::string> dicom_files;
  std::vector<v1::Delivery> deliveries;
  std::vector<std::string> send_to;
  {
    std::lock_guard<std::mutex> lock(job->mu_);
    send_to.assign(job->record_.spec().send_to().begin(),
                   job->record_.spec().send_to().end());
  }
  if (outbox_ != nullptr && !send_to.empty()) {
    dicom_files = DicomArtifactFiles(*artifacts, spool_->OutputDir(id));
    for (const std::string& peer : send_to) {
      v1::Delivery d;
      d.set_peer(peer);
      d.set_state(v1::Delivery::PENDING);
      d.set_instances_total(static_cast<int32_t>(dicom_files.size()));
      deliveries.push_back(d);
    }
  }
  job->Update([&](JobRecord& r) {
    for (const v1::Delivery& d : deliveries) {
      *r.mutable_status()->add_deliveries() = d;
    }
    v1::JobStatus* s = r.mutable_status();
    s->set_state(v1::JOB_STATE_SUCCEEDED);
    s->set_finished_unix_ms(now);
    s->set_expires_unix_ms(expires);
    s->mutable_progress()->set_stage("done");
    s->mutable_progress()->set_stage_percent(100);
    for (const auto& a : *artifacts) *s->add_artifacts() = a;
    s->set_report_json(json);
    r.set_result_bytes(result_bytes);
  });
  Persist(job);
  for (const v1::Delivery& d : deliveries) {
    outbox_->Add(id, d, dicom_files, now);
  }
  metrics_->JobFinished("succeeded");
  spdlog::info("job={} succeeded: {} artifact(s), {} bytes", id,
               artifacts->size(), result_bytes);
  AuditJob(options_.audit, job, "job.succeeded", AuditOutcome::kSuccess,
           absl::StrCat(artifacts->size(), " artifact(s), ", result_bytes,
                        " bytes"));
  return absl::OkStatus();
}

void JobManager::FailJob(const std::shared_ptr<Job>& job,
                         const absl::Status& cause, int64_t now,
                         int64_t expires) {
  const std::string& id = job->id();
  // A write that failed for want of space: RESOURCE_EXHAUSTED "disk full"
  // rather than INTERNAL with a server path (asked before the outputs go).
  const absl::Status error =
      DiskFullAsResourceExhausted(cause, spool_->FileSystemFull());
  spool_->RemoveOutputs(id);
  const bool cancelled = error.code() == absl::StatusCode::kCancelled;
  const std::string message = RedactPhi(error.message());
  job->Update([&](JobRecord& r) {
    v1::JobStatus* s = r.mutable_status();
    s->set_state(cancelled ? v1::JOB_STATE_CANCELLED : v1::JOB_STATE_FAILED);
    s->set_error_code(static_cast<int>(error.code()));
    s->set_error_message(message);
    s->set_finished_unix_ms(now);
    s->set_expires_unix_ms(expires);
    s->mutable_progress()->set_stage("done");
    r.set_result_bytes(0);
  });
  Persist(job);
  metrics_->JobFinished(OutcomeName(job->Snapshot(false).state()));
  spdlog::info("job={} {}: {} ({})", id, cancelled ? "cancelled" : "failed",
               absl::StatusCodeToString(error.code()), message);
  AuditJob(
      options_.audit, job, cancelled ? "job.cancelled" : "job.failed",
      cancelled ? AuditOutcome::kMinorFailure : AuditOutcome::kSeriousFailure,
      absl::StrCat(absl::StatusCodeToString(error.code()), ": ", message));
}

absl::Status JobManager::RetrieveFromPeer(const std::shared_ptr<Job>& job,
                                          const v1::PacsSeriesSource& source) {
  const std::string& id = job->id();
  if (series_source_ == nullptr) {
    return absl::FailedPreconditionError("the server has no DICOM peers");
  }
  // A rerun after a restart starts from an empty folder.
  spool_->RemoveUploads(id);
  std::error_code ec;
  fs::create_directories(spool_->UploadDir(id), ec);
  const auto started = std::chrono::steady_clock::now();
  absl::StatusOr<RetrievedSeries> result = series_source_->Retrieve(
      source, spool_->UploadDir(id),
      std::min(options_.max_upload_bytes, spool_->quota_bytes()), &job->token_);
  if (!result.ok()) {
    spool_->RemoveUploads(id);
    spdlog::info("job={} retrieval from peer {} failed: {}", id,
                 LogSafe(source.peer()), RedactPhi(result.status().message()));
    return result.status();
  }
  // Accounted like an upload (released when the job ends).
  spool_->Add(result->bytes);
  job->Update([&](JobRecord& r) { r.set_upload_bytes(result->bytes); });
  spdlog::info(
      "job={} retrieved {} instance(s), {} bytes from peer {} in "
      "{:.2f} s",
      id, result->instances, result->bytes, LogSafe(source.peer()),
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started)
          .count());
  return absl::OkStatus();
}

void JobManager::TickerLoop() {
  int ticks = 0;
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    cv_.wait_for(lock, std::chrono::seconds(1));
    if (stopping_) break;
    // Heartbeat: queue positions and elapsed time, so that watchers hear
    // from a job at least once a second.
    std::vector<std::pair<std::shared_ptr<Job>, int>> active;
    int position = 0;
    for (const auto& job : queue_) active.emplace_back(job, position++);
    for (const auto& [id, job] : jobs_) {
      std::lock_guard<std::mutex> job_lock(job->mu_);
      if (job->running_) active.emplace_back(job, -1);
    }
    std::vector<std::shared_ptr<Job>> expired;
    if (++ticks % 10 == 0) {
      const int64_t now = UnixMillisNow();
      for (auto it = jobs_.begin(); it != jobs_.end();) {
        std::shared_ptr<Job> job = it->second;
        std::lock_guard<std::mutex> job_lock(job->mu_);
        const v1::JobStatus& s = job->record_.status();
        // Results still owed to a DICOM peer outlive retention until the
        // delivery ends (delivered, or failed after give_up_after).
        if (!job->ephemeral() && !job->running_ && IsTerminalState(s.state()) &&
            s.expires_unix_ms() > 0 && s.expires_unix_ms() < now &&
            !HasPendingDelivery(job->record_)) {
          expired.push_back(job);
          it = jobs_.erase(it);
        } else {
          ++it;
        }
      }
    }
    lock.unlock();
    for (const auto& [job, pos] : active) {
      Job* j = job.get();
      const int position = pos;
      job->Update([j, position](JobRecord& r) {  // runs under j->mu_
        v1::Progress* p = r.mutable_status()->mutable_progress();
        p->set_queue_position(position);
        if (position < 0) {
          p->set_elapsed_seconds(
              std::chrono::duration<double>(std::chrono::steady_clock::now() -
                                            j->started_)
                  .count());
        }
      });
    }
    for (const auto& job : expired) {
      spdlog::info("job={} expired; its files were deleted", job->id());
      RemoveFinished(job);
    }
    lock.lock();
  }
}

}  // namespace interslice::server
