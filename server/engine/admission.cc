// JobManager (server/engine/job_manager.h): admission. The checks of an
// upload's header, a job's first record, queueing it once its files are in,
// jobs on files the DICOM node received, and abandoned uploads.
#include <filesystem>
#include <fstream>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/strip.h"
#include "job/job.h"
#include "nlohmann/json.hpp"
#include "server/base/audit.h"
#include "server/base/log_safe.h"
#include "server/engine/job_manager.h"
#include "server/engine/job_manager_internal.h"
#include "spdlog/spdlog.h"

namespace interslice::server {
namespace fs = std::filesystem;
namespace {

using job_manager_internal::AuditJob;

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

// header.file_count: none when the series comes from a DICOM peer
// (spec.pacs_source), else between 1 and kMaxFiles.
absl::Status CheckFileCount(const v1::UploadHeader& header) {
  const bool pacs = header.spec().has_pacs_source();
  if (pacs && header.file_count() != 0) {
    return absl::InvalidArgumentError(
        "spec.pacs_source reads the series from a DICOM peer: the upload "
        "must carry no files (file_count 0)");
  }
  if (!pacs && (header.file_count() < 1 || header.file_count() > kMaxFiles)) {
    return absl::InvalidArgumentError(
        absl::StrCat("header.file_count must be between 1 and ", kMaxFiles));
  }
  return absl::OkStatus();
}

// spec.pacs_source: a DICOM peer the server has, and the series' UIDs.
absl::Status CheckPacsSource(const v1::PacsSeriesSource& source,
                             const PeerSeriesSource* series_source) {
  if (series_source == nullptr) {
    return absl::InvalidArgumentError(
        "spec.pacs_source names a DICOM peer, but the server has none "
        "configured (--dicom-peers)");
  }
  if (absl::Status s = series_source->CheckPeer(source.peer()); !s.ok()) {
    return s;
  }
  if (source.study_instance_uid().empty() ||
      source.series_instance_uid().empty()) {
    return absl::InvalidArgumentError(
        "spec.pacs_source needs study_instance_uid and "
        "series_instance_uid");
  }
  return absl::OkStatus();
}

// The header's limits: the upload's size (the server's limit per job, then
// the spool's quota), the label and the deadline.
absl::Status CheckHeaderLimits(const v1::UploadHeader& header,
                               int64_t max_upload_bytes, const Spool& spool) {
  if (header.total_bytes() < 0) {
    return absl::InvalidArgumentError("header.total_bytes must be >= 0");
  }
  if (header.total_bytes() > max_upload_bytes) {
    return absl::ResourceExhaustedError(
        absl::StrCat("the upload (", header.total_bytes(),
                     " bytes) exceeds the server's limit of ", max_upload_bytes,
                     " bytes per job"));
  }
  if (header.options().label().size() > kMaxLabelBytes) {
    return absl::InvalidArgumentError("options.label is longer than 200 bytes");
  }
  if (!(header.options().deadline_seconds() >= 0)) {
    return absl::InvalidArgumentError("options.deadline_seconds must be >= 0");
  }
  if (header.total_bytes() > spool.quota_bytes()) {
    // Not "full": this upload can never fit, so retrying is pointless.
    return absl::ResourceExhaustedError(
        absl::StrCat("the upload (", header.total_bytes(),
                     " bytes) exceeds the server's spool quota of ",
                     spool.quota_bytes(), " bytes"));
  }
  return absl::OkStatus();
}

// header.file_count against the files the job's kind uploads at least.
absl::Status CheckUploadFilesOfKind(const v1::UploadHeader& header,
                                    const job::JobKind& kind) {
  if (!header.spec().has_pacs_source() &&
      header.file_count() < kind.min_upload_files()) {
    // A fill job uploads its segmentation and its reference series' files.
    return absl::InvalidArgumentError(absl::StrCat(
        "a ", kind.name(), " job uploads at least ", kind.min_upload_files(),
        " files: file_count must be >= ", kind.min_upload_files(), " (got ",
        header.file_count(), ")"));
  }
  return absl::OkStatus();
}

// spec.send_to: DICOM peers the server has, and a job that writes DICOM
// results to send them.
absl::Status CheckSendTo(const v1::JobSpec& spec, const job::JobKind& kind,
                         const ResultOutbox* outbox) {
  if (spec.send_to().empty()) return absl::OkStatus();
  if (outbox == nullptr) {
    return absl::InvalidArgumentError(
        "spec.send_to names DICOM peers, but the server has none "
        "configured (--dicom-peers)");
  }
  const std::vector<std::string> names(spec.send_to().begin(),
                                       spec.send_to().end());
  if (absl::Status s = outbox->CheckPeers(names); !s.ok()) {
    return s;
  }
  if (!kind.writes_dicom()) {
    return absl::InvalidArgumentError(
        "spec.send_to needs DICOM results: ask for derived series "
        "(output_series) or a segmentation");
  }
  return absl::OkStatus();
}

// Every check of JobManager::Admit but the queue's, in the order a client
// meets them: the file count, the pacs_source, the header's limits, the
// spec (the job's kind, and the files it uploads at least) and the send_to
// peers. The job's kind when all pass.
absl::StatusOr<std::unique_ptr<job::JobKind>> CheckUploadHeader(
    const v1::UploadHeader& header, int64_t max_upload_bytes,
    const Spool& spool, const PeerSeriesSource* series_source,
    const ResultOutbox* outbox) {
  if (absl::Status s = CheckFileCount(header); !s.ok()) return s;
  if (header.spec().has_pacs_source()) {
    if (absl::Status s =
            CheckPacsSource(header.spec().pacs_source(), series_source);
        !s.ok()) {
      return s;
    }
  }
  if (absl::Status s = CheckHeaderLimits(header, max_upload_bytes, spool);
      !s.ok()) {
    return s;
  }
  // The job's kind and options, checked as every door checks them.
  absl::StatusOr<std::unique_ptr<job::JobKind>> kind =
      job::MakeJobFromWire(header.spec());
  if (!kind.ok()) return kind.status();
  if (absl::Status s = CheckUploadFilesOfKind(header, **kind); !s.ok()) {
    return s;
  }
  if (absl::Status s = CheckSendTo(header.spec(), **kind, outbox); !s.ok()) {
    return s;
  }
  return kind;
}

// The first record of an admitted job: UPLOADING, made through the gRPC
// door by `owner`, with the header's spec and options (the deadline is
// Admit's to set).
JobRecord AdmittedRecord(const std::string& id, const v1::UploadHeader& header,
                         bool ephemeral, const std::string& owner) {
  JobRecord r;
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
  return r;
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
  absl::StatusOr<std::unique_ptr<job::JobKind>> kind = CheckUploadHeader(
      header, options_.max_upload_bytes, *spool_, series_source_, outbox_);
  if (!kind.ok()) return reject(kind.status());

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
  job->record_ = AdmittedRecord(id, header, ephemeral, owner);
  JobRecord& r = job->record_;
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

}  // namespace interslice::server
