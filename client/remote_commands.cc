#include "client/remote_commands.h"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string_view>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/fill_command.h"
#include "client/progress_display.h"
#include "core/common/sha256.h"
#include "core/dicom/series_reader.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "interslice/v1/interslice.grpc.pb.h"
#include "job/errors.h"
#include "job/job.h"
#include "job/wire.h"
#include "nlohmann/json.hpp"

namespace interslice::client {
namespace fs = std::filesystem;
namespace {

constexpr size_t kChunkBytes = 64 * 1024;
constexpr int kWatchRetries = 30;  // reconnects, 1 s apart

int Fail(const std::string& message) {
  std::fprintf(stderr, "interslice: error: %s\n", message.c_str());
  return 1;
}

// SHA-256 of a file, raw bytes; empty when it cannot be read (the upload
// of that file then fails on its own).
std::string HashFile(const std::string& path) {
  absl::StatusOr<std::string> sha = Sha256OfFile(path);
  return sha.ok() ? *sha : std::string();
}

struct LocalFile {
  std::string path;
  std::string name;
  int64_t size = 0;
};

// Every regular file under the inputs, found as `interslice run` finds them
// (core/dicom CollectInputFiles: recursive, de-duplicated, sorted; the
// server skips what is not DICOM), so that a remote job reads the same
// files as the local one. Uploaded under their own file names (the server
// stores them by index).
absl::StatusOr<std::vector<LocalFile>> CollectFiles(
    const std::vector<std::string>& inputs) {
  absl::StatusOr<std::vector<std::string>> paths = CollectInputFiles(inputs);
  if (!paths.ok()) return paths.status();
  std::vector<LocalFile> files;
  for (const std::string& path : *paths) {
    std::error_code ec;
    const auto size = fs::file_size(path, ec);
    if (ec) return absl::NotFoundError("cannot read an input file's size");
    files.push_back(
        {path, fs::path(path).filename().string(), static_cast<int64_t>(size)});
  }
  if (files.empty()) return absl::NotFoundError("no input files found");
  return files;
}

// Sends the header and every file; false as soon as the stream breaks (the
// caller then reads the status from Finish()).
template <typename Writer>
bool Upload(Writer& writer, const v1::UploadHeader& header,
            const std::vector<LocalFile>& files) {
  v1::UploadRequest request;
  *request.mutable_header() = header;
  if (!writer.Write(request)) return false;
  std::vector<char> buffer(kChunkBytes);
  for (size_t i = 0; i < files.size(); ++i) {
    std::ifstream in(files[i].path, std::ios::binary);
    const std::string sha = HashFile(files[i].path);
    int64_t offset = 0;
    bool first = true;
    while (first || offset < files[i].size) {
      const int64_t n = std::min<int64_t>(kChunkBytes, files[i].size - offset);
      in.read(buffer.data(), n);
      request.Clear();
      v1::FileChunk* chunk = request.mutable_chunk();
      chunk->set_file_index(static_cast<int>(i));
      if (first) {
        chunk->set_file_name(files[i].name);
        chunk->set_file_size(files[i].size);
        chunk->set_sha256(sha);
      }
      chunk->set_offset(offset);
      chunk->set_data(buffer.data(), static_cast<size_t>(in.gcount()));
      if (!writer.Write(request)) return false;
      offset += in.gcount();
      first = false;
      if (in.gcount() == 0) break;
    }
  }
  return true;
}

ProgressEvent ToEvent(const v1::Progress& p) {
  ProgressEvent e;
  e.stage = p.stage();
  e.fraction = p.stage_percent() / 100.0;
  e.iteration = p.iteration();
  e.relative_residual = p.relative_residual();
  e.energy = p.energy();
  return e;
}

}  // namespace

// Artifact names come from the server and become local paths: a file name,
// or "<folder>/<file>" (derived DICOM series), of plain characters only, so
// no name can climb out of the output folder or be absolute.
bool IsSafeArtifactName(const std::string& name) {
  const size_t slash = name.find('/');
  if (slash != std::string::npos &&
      name.find('/', slash + 1) != std::string::npos) {
    return false;
  }
  auto safe_component = [](std::string_view c) {
    if (c.empty() || c == "." || c == "..") return false;
    for (char ch : c) {
      if (!(std::isalnum(static_cast<unsigned char>(ch)) || ch == '.' ||
            ch == '_' || ch == '-')) {
        return false;
      }
    }
    return true;
  };
  const std::string_view view(name);
  if (slash == std::string::npos) return safe_component(view);
  return safe_component(view.substr(0, slash)) &&
         safe_component(view.substr(slash + 1));
}

namespace {

// Writes one artifact to <dir>/<name>.part, then checks its size and
// SHA-256 and renames it to <dir>/<name>.
class ArtifactFile {
 public:
  absl::Status Begin(const std::string& dir, const v1::ArtifactInfo& info,
                     int64_t offset) {
    info_ = info;
    if (!IsSafeArtifactName(info.name())) {
      return absl::DataLossError("the server sent a bad artifact name");
    }
    final_ = (fs::path(dir) / info.name()).string();
    part_ = final_ + ".part";
    std::error_code ec;
    fs::create_directories(fs::path(final_).parent_path(), ec);
    if (ec) return absl::PermissionDeniedError("cannot create " + final_);
    // The digest is computed from the bytes as they arrive (no second read
    // of the file); a resumed fetch first hashes the part already on disk.
    hash_ = std::make_unique<Sha256>();
    if (offset > 0) {
      std::ifstream in(part_, std::ios::binary);
      std::vector<char> buffer(1 << 16);
      int64_t left = offset;
      while (in && left > 0) {
        in.read(buffer.data(), static_cast<std::streamsize>(
                                   std::min<int64_t>(left, buffer.size())));
        hash_->Update(std::string_view(buffer.data(), in.gcount()));
        left -= in.gcount();
      }
      if (left != 0) return absl::DataLossError("cannot read " + part_);
    }
    bytes_ = offset;
    out_.open(part_, offset > 0 ? std::ios::binary | std::ios::app
                                : std::ios::binary | std::ios::trunc);
    if (!out_) return absl::PermissionDeniedError("cannot write " + part_);
    return absl::OkStatus();
  }
  absl::Status Append(const std::string& data) {
    out_.write(data.data(), static_cast<std::streamsize>(data.size()));
    if (!out_) return absl::ResourceExhaustedError("cannot write " + part_);
    hash_->Update(data);
    bytes_ += static_cast<int64_t>(data.size());
    return absl::OkStatus();
  }
  absl::Status Commit() {
    out_.close();
    std::error_code ec;
    const auto size = fs::file_size(part_, ec);
    if (!out_ || ec || static_cast<int64_t>(size) != info_.size_bytes() ||
        bytes_ != info_.size_bytes() || hash_->Finish() != info_.sha256()) {
      return absl::DataLossError(absl::StrCat(
          info_.name(), ": size or SHA-256 does not match the server's"));
    }
    fs::rename(part_, final_, ec);
    if (ec) return absl::PermissionDeniedError("cannot rename " + part_);
    return absl::OkStatus();
  }
  bool open() const { return out_.is_open(); }
  const std::string& part_path() const { return part_; }

 private:
  v1::ArtifactInfo info_;
  std::string final_, part_;
  std::ofstream out_;
  std::unique_ptr<Sha256> hash_;
  int64_t bytes_ = 0;
};

// Whether `path` already holds the artifact: a regular file of its size and
// SHA-256.
bool IsCompleteArtifact(const std::string& path, const v1::ArtifactInfo& info) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) return false;
  const auto size = fs::file_size(path, ec);
  return !ec && static_cast<int64_t>(size) == info.size_bytes() &&
         HashFile(path) == info.sha256();
}

// The server's report with artifact paths turned into local ones.
// The region of interest an interpolation job used, as the in-process
// summary says it (a fill's report has none: nothing is printed).
void PrintRegion(const std::string& report_json) {
  if (report_json.empty()) return;
  absl::StatusOr<JobReport> report = JobReportFromJson(report_json);
  if (!report.ok()) return;
  if (std::optional<std::string> line = job::RegionSummaryLine(*report)) {
    std::printf("%s\n", line->c_str());
  }
}

absl::Status WriteReport(const std::string& report_json,
                         const std::string& out_dir, const std::string& path) {
  nlohmann::ordered_json j =
      nlohmann::ordered_json::parse(report_json, nullptr, false);
  if (j.is_discarded()) return absl::DataLossError("the report is not JSON");
  if (j.contains("artifacts")) {
    for (auto& a : j["artifacts"]) {
      a["path"] = (fs::path(out_dir) / a["path"].get<std::string>()).string();
    }
  }
  std::ofstream file(path);
  file << j.dump(2) << "\n";
  file.close();
  if (!file) return absl::PermissionDeniedError("cannot write report " + path);
  return absl::OkStatus();
}

const char* StateName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_UPLOADING:
      return "uploading";
    case v1::JOB_STATE_QUEUED:
      return "queued";
    case v1::JOB_STATE_RUNNING:
      return "running";
    case v1::JOB_STATE_SUCCEEDED:
      return "succeeded";
    case v1::JOB_STATE_FAILED:
      return "failed";
    case v1::JOB_STATE_CANCELLED:
      return "cancelled";
    default:
      return "unknown";
  }
}

void SetTimeout(grpc::ClientContext& context, double seconds) {
  context.set_deadline(
      std::chrono::system_clock::now() +
      std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000)));
}

absl::StatusOr<v1::UploadHeader> PrepareUpload(const RunArguments& args,
                                               double deadline_seconds,
                                               const std::string& label,
                                               std::vector<LocalFile>* files) {
  const bool pacs = !args.pacs_peer.empty();
  if (pacs && (args.pacs_study.empty() || args.pacs_series.empty())) {
    return absl::InvalidArgumentError(
        "--pacs needs --study and --series (the series' Study and Series "
        "Instance UIDs)");
  }
  if (!pacs && (!args.pacs_study.empty() || !args.pacs_series.empty())) {
    return absl::InvalidArgumentError("--study and --series need --pacs PEER");
  }
  if (pacs && !args.inputs.empty()) {
    return absl::InvalidArgumentError(
        "give either DICOM_DIR... or --pacs PEER, not both");
  }
  if (!pacs && args.inputs.empty()) {
    return absl::InvalidArgumentError(
        "no input: give DICOM_DIR... or --pacs PEER --study UID --series UID");
  }
  RunArguments checked = args;
  // BuildJobSpec checks the job options; the series comes from the peer.
  if (pacs) checked.inputs = {"."};
  absl::StatusOr<JobSpec> spec = job::BuildJobSpec(checked);
  if (!spec.ok()) {
    return job::ForDoor(spec.status(), job::ErrorDoor::kCommandLine);
  }
  if (!pacs) {
    absl::StatusOr<std::vector<LocalFile>> found = CollectFiles(spec->inputs);
    if (!found.ok()) return found.status();
    *files = std::move(*found);
  }
  v1::UploadHeader header;
  *header.mutable_spec() = job::ToWire(*spec);
  for (const std::string& peer : args.send_to) {
    header.mutable_spec()->add_send_to(peer);
  }
  if (pacs) {
    v1::PacsSeriesSource* source = header.mutable_spec()->mutable_pacs_source();
    source->set_peer(args.pacs_peer);
    source->set_study_instance_uid(args.pacs_study);
    source->set_series_instance_uid(args.pacs_series);
  }
  header.mutable_options()->set_deadline_seconds(deadline_seconds);
  header.mutable_options()->set_label(label);
  header.set_file_count(static_cast<int>(files->size()));
  int64_t total = 0;
  for (const LocalFile& f : *files) total += f.size;
  header.set_total_bytes(total);
  return header;
}

// One Interpolate call: uploads `files` after `header`, writes the artifacts
// to `out` and the report to `report` (if not empty).
int InterpolateCall(const Connection& connection,
                    const v1::UploadHeader& header,
                    const std::vector<LocalFile>& files, const std::string& out,
                    const std::string& report, bool quiet,
                    double deadline_seconds) {
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) return Fail("cannot create output folder " + out);

  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  if (deadline_seconds > 0) SetTimeout(context, deadline_seconds);
  auto stream = stub->Interpolate(&context);
  if (Upload(*stream, header, files)) stream->WritesDone();

  ProgressDisplay display(stderr, !quiet);
  v1::InterpolateResponse response;
  ArtifactFile artifact;
  absl::Status local = absl::OkStatus();
  std::string job_id;
  v1::JobSummary summary;
  bool have_summary = false;
  while (stream->Read(&response)) {
    if (response.has_accepted()) {
      job_id = response.accepted().job_id();
    } else if (response.has_progress()) {
      display.Update(ToEvent(response.progress()));
    } else if (response.has_artifact() && local.ok()) {
      const v1::ArtifactChunk& chunk = response.artifact();
      if (chunk.has_info()) {
        if (artifact.open()) local = artifact.Commit();
        if (local.ok()) local = artifact.Begin(out, chunk.info(), 0);
      }
      if (local.ok()) local = artifact.Append(chunk.data());
    } else if (response.has_summary()) {
      if (artifact.open() && local.ok()) local = artifact.Commit();
      summary = response.summary();
      have_summary = true;
    }
    if (!local.ok()) context.TryCancel();
  }
  const grpc::Status status = stream->Finish();
  display.Finish();
  if (!local.ok()) return Fail(std::string(local.message()));
  if (!status.ok()) {
    if (artifact.open()) fs::remove(artifact.part_path(), ec);
    return Fail(DescribeRpcError(status, connection.address()));
  }
  if (!have_summary) return Fail("the server ended the call without a summary");
  if (!report.empty()) {
    if (absl::Status s = WriteReport(summary.report_json(), out, report);
        !s.ok()) {
      return Fail(std::string(s.message()));
    }
  }
  if (!quiet) {
    std::printf("interslice: wrote %d file(s) to %s (job %s on %s)\n",
                summary.artifacts_size(), out.c_str(), job_id.c_str(),
                connection.address().c_str());
    for (const v1::ArtifactInfo& a : summary.artifacts()) {
      std::printf("  %-9s %s (%lld bytes)\n", a.kind().c_str(),
                  (fs::path(out) / a.name()).string().c_str(),
                  static_cast<long long>(a.size_bytes()));
    }
    PrintRegion(summary.report_json());
  }
  return 0;
}

int RunInterpolate(const Connection& connection, const RunArguments& args,
                   double deadline_seconds) {
  std::vector<LocalFile> files;
  absl::StatusOr<v1::UploadHeader> header = PrepareUpload(args, 0, "", &files);
  if (!header.ok()) return Fail(std::string(header.status().message()));
  return InterpolateCall(connection, *header, files, args.out,
                         args.local.report, args.local.quiet, deadline_seconds);
}

// `interslice fill --server`: the segmentation (uploaded under its own file
// name, which spec.fill.segmentation_file names), its label names if given
// (under "label-names/<file name>", spec.fill.label_names_file) and the
// reference series' files (under "series/<file name>"), so that no name of
// one can equal another's. The header and the files in upload order.
absl::StatusOr<v1::UploadHeader> PrepareFillUpload(
    const FillArguments& args, double deadline_seconds,
    const std::string& label, std::vector<LocalFile>* files) {
  FillArguments checked = args;
  // The output folder belongs to the client (or to `fetch`, for a detached
  // job); BuildFillJobSpec wants one.
  if (checked.out.empty()) checked.out = ".";
  absl::StatusOr<FillJobSpec> spec = job::BuildFillJobSpec(checked);
  if (!spec.ok()) {
    return job::ForDoor(spec.status(), job::ErrorDoor::kCommandLine);
  }
  std::error_code ec;
  if (!fs::is_regular_file(spec->segmentation, ec)) {
    return absl::NotFoundError("no such segmentation file: " +
                               spec->segmentation);
  }
  if (!spec->label_names.empty() &&
      !fs::is_regular_file(spec->label_names, ec)) {
    return absl::NotFoundError("--label-names: no such file: " +
                               spec->label_names);
  }
  absl::StatusOr<std::vector<LocalFile>> reference =
      CollectFiles(spec->reference);
  if (!reference.ok()) return reference.status();
  // A segmentation or label names kept in the series' folder are not part
  // of the series.
  std::vector<fs::path> named = {fs::weakly_canonical(spec->segmentation, ec)};
  files->clear();
  files->push_back(
      {spec->segmentation, fs::path(spec->segmentation).filename().string(),
       static_cast<int64_t>(fs::file_size(spec->segmentation, ec))});
  std::string label_names_file;
  if (!spec->label_names.empty()) {
    named.push_back(fs::weakly_canonical(spec->label_names, ec));
    label_names_file =
        "label-names/" + fs::path(spec->label_names).filename().string();
    files->push_back(
        {spec->label_names, label_names_file,
         static_cast<int64_t>(fs::file_size(spec->label_names, ec))});
  }
  for (LocalFile& f : *reference) {
    const fs::path canonical = fs::weakly_canonical(f.path, ec);
    if (std::find(named.begin(), named.end(), canonical) != named.end()) {
      continue;
    }
    f.name = "series/" + f.name;
    files->push_back(std::move(f));
  }
  v1::UploadHeader header;
  *header.mutable_spec() =
      job::ToWire(*spec, files->front().name, label_names_file);
  for (const std::string& peer : args.send_to) {
    header.mutable_spec()->add_send_to(peer);
  }
  header.mutable_options()->set_deadline_seconds(deadline_seconds);
  header.mutable_options()->set_label(label);
  header.set_file_count(static_cast<int>(files->size()));
  int64_t total = 0;
  for (const LocalFile& f : *files) total += f.size;
  header.set_total_bytes(total);
  return header;
}

int RunFillRemote(const Connection& connection, const FillArguments& args,
                  double deadline_seconds) {
  std::vector<LocalFile> files;
  absl::StatusOr<v1::UploadHeader> header =
      PrepareFillUpload(args, 0, "", &files);
  if (!header.ok()) return Fail(std::string(header.status().message()));
  return InterpolateCall(connection, *header, files, args.out,
                         args.local.report, args.local.quiet, deadline_seconds);
}

// A detached job: uploads `files` after `header` by Submit and prints the
// job's id (the one line on stdout, for scripts).
int SubmitCall(const Connection& connection, const v1::UploadHeader& header,
               const std::vector<LocalFile>& files) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  v1::SubmitResponse response;
  auto writer = stub->Submit(&context, &response);
  if (Upload(*writer, header, files)) writer->WritesDone();
  const grpc::Status status = writer->Finish();
  if (!status.ok()) return Fail(DescribeRpcError(status, connection.address()));
  std::printf("%s\n", response.job_id().c_str());
  return 0;
}

int RunSubmit(const Connection& connection, const RunArguments& args,
              double deadline_seconds, const std::string& label) {
  std::vector<LocalFile> files;
  // The output folder belongs to `fetch`; BuildJobSpec wants one.
  RunArguments with_out = args;
  if (with_out.out.empty()) with_out.out = ".";
  absl::StatusOr<v1::UploadHeader> header =
      PrepareUpload(with_out, deadline_seconds, label, &files);
  if (!header.ok()) return Fail(std::string(header.status().message()));
  return SubmitCall(connection, *header, files);
}

// `interslice fill --server ADDR --submit`: the same upload as a detached
// job (then watch, fetch, list, cancel as for any job).
int RunFillSubmit(const Connection& connection, const FillArguments& args,
                  double deadline_seconds, const std::string& label) {
  std::vector<LocalFile> files;
  absl::StatusOr<v1::UploadHeader> header =
      PrepareFillUpload(args, deadline_seconds, label, &files);
  if (!header.ok()) return Fail(std::string(header.status().message()));
  return SubmitCall(connection, *header, files);
}

// Watches until the job ends, reconnecting after transient failures. Fills
// `final` with the terminal status.
int WatchJob(const Connection& connection, const std::string& job_id,
             bool quiet, v1::JobStatus* final) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  ProgressDisplay display(stderr, !quiet);
  int64_t sequence = 0;
  int retries = 0;
  for (;;) {
    grpc::ClientContext context;
    connection.Authorize(context);
    v1::WatchRequest request;
    request.set_job_id(job_id);
    request.set_after_sequence(sequence);
    auto reader = stub->Watch(&context, request);
    v1::JobStatus status;
    while (reader->Read(&status)) {
      retries = 0;
      sequence = std::max(sequence, status.sequence());
      if (status.state() == v1::JOB_STATE_RUNNING ||
          status.state() == v1::JOB_STATE_QUEUED) {
        display.Update(ToEvent(status.progress()));
      }
      if (job::IsTerminalState(status.state())) *final = status;
    }
    const grpc::Status s = reader->Finish();
    if (s.ok() && job::IsTerminalState(final->state())) break;
    if (s.error_code() == grpc::UNAVAILABLE && ++retries <= kWatchRetries) {
      std::this_thread::sleep_for(std::chrono::seconds(1));
      continue;  // resume after `sequence`
    }
    display.Finish();
    return Fail(DescribeRpcError(s, connection.address()));
  }
  display.Finish();
  return 0;
}

const char* DeliveryStateName(v1::Delivery::State s) {
  switch (s) {
    case v1::Delivery::PENDING:
      return "pending";
    case v1::Delivery::DELIVERED:
      return "delivered";
    case v1::Delivery::FAILED:
      return "FAILED";
    default:
      return "unknown";
  }
}

bool HasPendingDelivery(const v1::JobStatus& status) {
  for (const v1::Delivery& d : status.deliveries()) {
    if (d.state() == v1::Delivery::PENDING) return true;
  }
  return false;
}

// Free text from the server (labels, AE titles, rule names, errors): no
// control characters reach the terminal, one line stays one line.
std::string Printable(std::string text) {
  for (char& c : text) {
    if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) c = '?';
  }
  return text;
}

// "2026-11-26 03:50:01Z" (UTC) for Unix ms; "-" for 0 (not yet).
std::string UtcTime(int64_t unix_ms) {
  if (unix_ms <= 0) return "-";
  const std::time_t seconds = static_cast<std::time_t>(unix_ms / 1000);
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  char text[32];
  std::strftime(text, sizeof(text), "%Y-%m-%d %H:%M:%SZ", &utc);
  return text;
}

// Where the job came from, what it reads and when it ran: the lines
// `list` and `watch` show under a job (UIDs included: only the job's owner
// and admins receive its status).
std::vector<std::string> DescribeJob(const v1::JobStatus& j) {
  std::vector<std::string> lines;
  const v1::JobOrigin& o = j.source();
  std::string from;
  if (o.door() == v1::JobOrigin::DICOM) {
    from =
        absl::StrCat("DICOM from ", Printable(o.calling_ae()), " to ",
                     Printable(o.called_ae()), ", rule ", Printable(o.rule()));
  } else if (o.door() == v1::JobOrigin::GRPC) {
    from = o.client().empty() ? "client"
                              : absl::StrCat("client ", Printable(o.client()));
    if (!o.pacs_peer().empty()) {
      absl::StrAppend(&from, ", series pulled from peer ",
                      Printable(o.pacs_peer()));
    }
  } else if (!j.origin().empty()) {
    from = Printable(j.origin());  // a record of an older server
  }
  if (!from.empty()) lines.push_back(absl::StrCat("  origin    ", from));
  if (j.instance_count() > 0) {
    lines.push_back(absl::StrFormat(
        "  input     %s, %d instance(s)",
        j.modality().empty() ? "modality unknown" : Printable(j.modality()),
        j.instance_count()));
  }
  if (!j.study_instance_uid().empty() || !j.series_instance_uid().empty()) {
    lines.push_back(
        absl::StrCat("  study     ", Printable(j.study_instance_uid())));
    lines.push_back(
        absl::StrCat("  series    ", Printable(j.series_instance_uid())));
  }
  lines.push_back(absl::StrCat("  times     created ",
                               UtcTime(j.created_unix_ms()), ", started ",
                               UtcTime(j.started_unix_ms()), ", finished ",
                               UtcTime(j.finished_unix_ms())));
  return lines;
}

void PrintDeliveries(const v1::JobStatus& status) {
  for (const v1::Delivery& d : status.deliveries()) {
    std::printf("  to %s: %s, %d of %d instance(s) stored, %d attempt(s)%s%s\n",
                Printable(d.peer()).c_str(), DeliveryStateName(d.state()),
                d.instances_sent(), d.instances_total(), d.attempts(),
                d.last_error().empty() ? "" : "; last error: ",
                Printable(d.last_error()).c_str());
  }
}

// The job's status now (the first message of a Watch).
absl::StatusOr<v1::JobStatus> CurrentStatus(const Connection& connection,
                                            const std::string& job_id) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 60);
  v1::WatchRequest request;
  request.set_job_id(job_id);
  auto reader = stub->Watch(&context, request);
  v1::JobStatus status;
  const bool got = reader->Read(&status);
  if (got) context.TryCancel();
  const grpc::Status s = reader->Finish();
  if (!got) {
    return absl::UnavailableError(DescribeRpcError(s, connection.address()));
  }
  return status;
}

int RunWatch(const Connection& connection, const std::string& job_id,
             bool quiet, bool wait_deliveries) {
  v1::JobStatus final;
  if (int rc = WatchJob(connection, job_id, quiet, &final); rc != 0) return rc;
  if (final.state() != v1::JOB_STATE_SUCCEEDED) {
    return Fail(absl::StrCat("job ", job_id, " ", StateName(final.state()),
                             ": ", final.error_message()));
  }
  // Deliveries to DICOM peers go on after the job: poll until they end.
  while (wait_deliveries && HasPendingDelivery(final)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    absl::StatusOr<v1::JobStatus> now = CurrentStatus(connection, job_id);
    if (!now.ok()) return Fail(std::string(now.status().message()));
    final = *now;
  }
  if (!quiet) {
    std::printf(
        "job %s succeeded: %d artifact(s); get them with "
        "`interslice fetch %s --out DIR`\n",
        job_id.c_str(), final.artifacts_size(), job_id.c_str());
    for (const std::string& line : DescribeJob(final)) {
      std::printf("%s\n", line.c_str());
    }
    PrintDeliveries(final);
  }
  for (const v1::Delivery& d : final.deliveries()) {
    if (wait_deliveries && d.state() == v1::Delivery::FAILED) {
      return Fail(absl::StrCat("job ", job_id, ": delivery to ", d.peer(),
                               " failed: ", d.last_error()));
    }
  }
  return 0;
}

int RunFetch(const Connection& connection, const std::string& job_id,
             const std::string& out, const std::string& report, bool quiet) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  // The job's status: the first message of a Watch.
  v1::JobStatus status;
  {
    grpc::ClientContext context;
    connection.Authorize(context);
    SetTimeout(context, 60);
    v1::WatchRequest request;
    request.set_job_id(job_id);
    auto reader = stub->Watch(&context, request);
    const bool got = reader->Read(&status);
    // Only a stream still open needs cancelling; cancelling one that ended
    // would replace its status (NOT_FOUND, ...) with CANCELLED.
    if (got) context.TryCancel();
    const grpc::Status s = reader->Finish();
    if (!got) return Fail(DescribeRpcError(s, connection.address()));
  }
  if (status.state() != v1::JOB_STATE_SUCCEEDED) {
    return Fail(absl::StrCat("job ", job_id, " is ", StateName(status.state()),
                             status.error_message().empty()
                                 ? ""
                                 : absl::StrCat(": ", status.error_message())));
  }
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) return Fail("cannot create output folder " + out);
  int skipped = 0;
  for (const v1::ArtifactInfo& info : status.artifacts()) {
    // A complete file from an earlier fetch: keep it.
    if (IsSafeArtifactName(info.name()) &&
        IsCompleteArtifact((fs::path(out) / info.name()).string(), info)) {
      ++skipped;
      continue;
    }
    int attempts = 0;
    for (;;) {
      // Resume from what an earlier, interrupted fetch left behind.
      const std::string part = (fs::path(out) / info.name()).string() + ".part";
      int64_t offset = fs::exists(part, ec)
                           ? static_cast<int64_t>(fs::file_size(part, ec))
                           : 0;
      if (offset > info.size_bytes()) offset = 0;
      ArtifactFile file;
      if (absl::Status s = file.Begin(out, info, offset); !s.ok()) {
        return Fail(std::string(s.message()));
      }
      grpc::ClientContext context;
      connection.Authorize(context);
      v1::FetchRequest request;
      request.set_job_id(job_id);
      request.set_artifact_name(info.name());
      request.set_offset(offset);
      auto reader = stub->Fetch(&context, request);
      v1::ArtifactChunk chunk;
      absl::Status local = absl::OkStatus();
      while (local.ok() && reader->Read(&chunk))
        local = file.Append(chunk.data());
      if (!local.ok()) context.TryCancel();
      const grpc::Status s = reader->Finish();
      if (!local.ok()) return Fail(std::string(local.message()));
      if (s.ok()) {
        if (absl::Status c = file.Commit(); !c.ok()) {
          fs::remove(part, ec);
          return Fail(std::string(c.message()));
        }
        break;
      }
      if (s.error_code() == grpc::UNAVAILABLE && ++attempts <= kWatchRetries) {
        std::this_thread::sleep_for(std::chrono::seconds(1));
        continue;
      }
      return Fail(DescribeRpcError(s, connection.address()));
    }
  }
  if (!report.empty()) {
    if (absl::Status s = WriteReport(status.report_json(), out, report);
        !s.ok()) {
      return Fail(std::string(s.message()));
    }
  }
  if (!quiet) {
    const std::string kept =
        skipped > 0 ? absl::StrCat(" (", skipped, " already complete, kept)")
                    : "";
    std::printf("interslice: fetched %d file(s) of job %s to %s%s\n",
                status.artifacts_size() - skipped, job_id.c_str(), out.c_str(),
                kept.c_str());
    PrintRegion(status.report_json());
  }
  return 0;
}

int RunCancel(const Connection& connection, const std::string& job_id) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 30);
  v1::CancelRequest request;
  request.set_job_id(job_id);
  v1::JobStatus status;
  const grpc::Status s = stub->Cancel(&context, request, &status);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  std::printf("job %s: %s%s\n", job_id.c_str(), StateName(status.state()),
              status.cancel_requested() && !job::IsTerminalState(status.state())
                  ? " (cancellation requested)"
                  : "");
  return 0;
}

int RunList(const Connection& connection, bool all) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 30);
  v1::ListRequest request;
  request.set_include_finished(all);
  v1::ListResponse response;
  const grpc::Status s = stub->List(&context, request, &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  // Labels are free text from whoever submitted (an admin lists everyone's):
  // Printable.
  for (const v1::JobStatus& j : response.jobs()) {
    std::printf("%s  %-9s  %-8s %5.1f%%  %s\n", j.job_id().c_str(),
                StateName(j.state()), j.progress().stage().c_str(),
                j.progress().stage_percent(), Printable(j.label()).c_str());
    for (const std::string& line : DescribeJob(j)) {
      std::printf("%s\n", line.c_str());
    }
    PrintDeliveries(j);
  }
  return 0;
}

// Studies, then their series, one per line with their UIDs (for
// `submit --pacs PEER --study UID --series UID`). Text from the PACS reaches
// the terminal without control characters.
int RunFind(const Connection& connection, const v1::FindRequest& request) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  // Two queries per study on the server's side, each within the peer's
  // timeout: a generous bound.
  SetTimeout(context, 600);
  v1::FindResponse response;
  const grpc::Status s = stub->Find(&context, request, &response);
  // The peer's failure (named in the message: "cannot associate with peer
  // NAME (...)"), not the server's: said as it is.
  if (s.error_code() == grpc::UNAVAILABLE &&
      s.error_message().find("peer " + request.peer() + " (") !=
          std::string::npos) {
    return Fail(s.error_message());
  }
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  auto printable = [](std::string text) {
    for (char& c : text) {
      if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) c = '?';
    }
    return text;
  };
  for (const v1::FoundStudy& study : response.studies()) {
    std::printf("study %s  date %s  patient %s  accession %s  %s  \"%s\"\n",
                printable(study.study_instance_uid()).c_str(),
                printable(study.study_date()).c_str(),
                printable(study.patient_id()).c_str(),
                printable(study.accession_number()).c_str(),
                printable(study.modalities_in_study()).c_str(),
                printable(study.study_description()).c_str());
    for (const v1::FoundSeries& series : study.series()) {
      const std::string instances =
          series.instances() >= 0
              ? absl::StrCat(series.instances(), " instance(s)")
              : std::string("? instance(s)");
      std::printf("  series %s  %s  #%s  %s  \"%s\"\n",
                  printable(series.series_instance_uid()).c_str(),
                  printable(series.modality()).c_str(),
                  printable(series.series_number()).c_str(), instances.c_str(),
                  printable(series.series_description()).c_str());
    }
  }
  if (response.studies().empty()) {
    std::fprintf(stderr, "no study on peer %s matches\n",
                 request.peer().c_str());
  }
  if (response.truncated()) {
    std::fprintf(stderr,
                 "more matched than the caps (%d studies, %d series): the "
                 "first are listed; narrow the keys (or --max-studies)\n",
                 response.max_studies(), response.max_series());
  }
  return 0;
}

// One line per kept series: id, since when, from whom, what, why (UIDs
// included: only admins are answered).
int RunKeptList(const Connection& connection) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 120);
  v1::ListKeptResponse response;
  const grpc::Status s =
      stub->ListKept(&context, v1::ListKeptRequest(), &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  for (const v1::ListKeptResponse::Series& k : response.series()) {
    std::printf(
        "%s  kept %s  %s -> %s  %s  %lld instance(s)  study %s  series %s  "
        "%s\n",
        Printable(k.id()).c_str(), UtcTime(k.kept_since_unix_ms()).c_str(),
        Printable(k.calling_ae()).c_str(), Printable(k.called_ae()).c_str(),
        k.modality().empty() ? "?" : Printable(k.modality()).c_str(),
        static_cast<long long>(k.instance_count()),
        Printable(k.study_instance_uid()).c_str(),
        Printable(k.series_instance_uid()).c_str(), Printable(k.why()).c_str());
  }
  if (response.series().empty()) std::fprintf(stderr, "no series is kept\n");
  return 0;
}

// One line per series run again: "job ID" for each job made, "not matched
// ID: why" for each series no rule takes (not an error).
int RunKeptRerun(const Connection& connection, const std::string& id,
                 bool all_unmatched) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 600);
  v1::RerunKeptRequest request;
  request.set_id(id);
  request.set_all_unmatched(all_unmatched);
  v1::RerunKeptResponse response;
  const grpc::Status s = stub->RerunKept(&context, request, &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  for (const std::string& job : response.job_ids()) {
    std::printf("job %s\n", Printable(job).c_str());
  }
  for (const std::string& why : response.not_matched()) {
    std::printf("not matched %s\n", Printable(why).c_str());
  }
  if (all_unmatched && response.job_ids().empty() &&
      response.not_matched().empty()) {
    std::fprintf(stderr, "no kept series without a job\n");
  }
  return 0;
}

int RunInfo(const Connection& connection) {
  auto stub = v1::InterSlice::NewStub(connection.channel());
  grpc::ClientContext context;
  connection.Authorize(context);
  SetTimeout(context, 30);
  v1::ServerInfo info;
  const grpc::Status s =
      stub->GetServerInfo(&context, v1::ServerInfoRequest(), &info);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  const v1::Limits& l = info.limits();
  std::printf("interslice-server %s (%s)%s\n", info.version().c_str(),
              info.api().c_str(), info.draining() ? ", draining" : "");
  std::printf(
      "  workers %d x %d threads, queue %d, upload <= %lld bytes, "
      "output <= %lld voxels, chunk <= %d bytes\n",
      l.workers(), l.threads_per_job(), l.max_queued_jobs(),
      static_cast<long long>(l.max_upload_bytes()),
      static_cast<long long>(l.max_output_voxels()), l.max_chunk_bytes());
  std::printf(
      "  uploads <= %d at once (%d per client), idle timeout %g s, time "
      "limit %g s\n",
      l.max_concurrent_uploads(), l.max_uploads_per_client(),
      l.upload_idle_timeout_seconds(), l.upload_timeout_seconds());
  std::printf("  results kept %lld s, spool quota %lld bytes, auth %s\n",
              static_cast<long long>(l.result_retention_seconds()),
              static_cast<long long>(l.spool_quota_bytes()),
              info.auth_required() ? "required" : "off");
  std::string list;
  for (const auto& m : info.methods()) list += " " + m;
  std::printf("  methods:%s\n", list.c_str());
  list.clear();
  for (const auto& m : info.volume_formats()) list += " " + m;
  for (const auto& m : info.mesh_formats()) list += " " + m;
  std::printf("  outputs:%s\n", list.c_str());
  list.clear();
  for (const auto& m : info.rpcs()) list += " " + m;
  std::printf("  rpcs:%s\n", list.c_str());
  std::printf("  transfer syntaxes:\n");
  for (const auto& t : info.transfer_syntaxes()) {
    std::printf("    %s  %s\n", t.uid().c_str(), t.name().c_str());
  }
  return 0;
}

int RunHealth(const Connection& connection) {
  auto stub = grpc::health::v1::Health::NewStub(connection.channel());
  grpc::ClientContext context;
  SetTimeout(context, 10);
  grpc::health::v1::HealthCheckRequest request;
  grpc::health::v1::HealthCheckResponse response;
  const grpc::Status s = stub->Check(&context, request, &response);
  if (!s.ok()) return Fail(DescribeRpcError(s, connection.address()));
  const bool serving =
      response.status() == grpc::health::v1::HealthCheckResponse::SERVING;
  std::printf("%s\n", grpc::health::v1::HealthCheckResponse::ServingStatus_Name(
                          response.status())
                          .c_str());
  return serving ? 0 : 1;
}

}  // namespace

void RemoteCommands::Register(CLI::App& app) {
  interpolate_ = app.add_subcommand(
      "interpolate",
      "Run a job on a server in one call: upload, progress, artifacts");
  AddRunOptions(*interpolate_, run_args_);
  AddConnectionOptions(*interpolate_, connection_);
  interpolate_->add_option("--deadline", deadline_seconds_,
                           "Give up (and cancel the job) after this many "
                           "seconds");

  submit_ = app.add_subcommand(
      "submit", "Upload a detached job; prints its id (then: watch, fetch)");
  // The same job options as `run`; --out is accepted but only `fetch`
  // writes files.
  AddRunOptions(*submit_, run_args_);
  AddConnectionOptions(*submit_, connection_);
  submit_->add_option("--deadline", deadline_seconds_,
                      "Server-side limit on the job, seconds from acceptance");
  submit_->add_option("--label", label_, "Free text shown by `list` (no PHI)");
  for (CLI::App* remote : {interpolate_, submit_}) {
    remote
        ->add_option("--send-to", run_args_.send_to,
                     "Store the DICOM results on these DICOM peers of the "
                     "server (names from its --dicom-peers file)")
        ->delimiter(',');
    remote->add_option("--pacs", run_args_.pacs_peer,
                       "Read the series from this DICOM peer of the server "
                       "(C-GET) instead of DICOM_DIR");
    remote->add_option("--study", run_args_.pacs_study,
                       "With --pacs: the series' StudyInstanceUID");
    remote->add_option("--series", run_args_.pacs_series,
                       "With --pacs: the SeriesInstanceUID");
    // DICOM_DIR is not needed with --pacs (PrepareUpload checks one of them).
    for (CLI::Option* o : remote->get_options()) {
      if (o->check_name("inputs")) o->required(false);
    }
  }
  // --out is required by AddRunOptions; a detached job needs none.
  for (CLI::Option* o : submit_->get_options()) {
    if (o->check_name("--out")) o->required(false);
  }

  watch_ = app.add_subcommand("watch",
                              "Follow a detached job until it ends "
                              "(reconnects after network failures)");
  watch_->add_option("job", job_id_, "Job id")->required();
  watch_->add_flag("--quiet", quiet_, "No progress display");
  watch_->add_flag("--wait-deliveries", wait_deliveries_,
                   "After the job, wait until its DICOM deliveries (send_to) "
                   "are delivered or failed; exit 1 if one failed");
  AddConnectionOptions(*watch_, connection_);

  fetch_ = app.add_subcommand(
      "fetch", "Download a finished job's artifacts (resumes partial files)");
  fetch_->add_option("job", job_id_, "Job id")->required();
  fetch_->add_option("--out", out_, "Output folder")->required();
  fetch_->add_option("--report", report_, "Write the JSON report here");
  fetch_->add_flag("--quiet", quiet_, "No summary");
  AddConnectionOptions(*fetch_, connection_);

  cancel_ = app.add_subcommand("cancel", "Cancel a detached job");
  cancel_->add_option("job", job_id_, "Job id")->required();
  AddConnectionOptions(*cancel_, connection_);

  list_ = app.add_subcommand("list", "List the server's detached jobs");
  list_->add_flag("--all", all_, "Include finished jobs");
  AddConnectionOptions(*list_, connection_);

  info_ = app.add_subcommand("info", "Show the server's version and limits");
  AddConnectionOptions(*info_, connection_);

  health_ = app.add_subcommand(
      "health", "Check the server's health (exit 0 only when SERVING)");
  AddConnectionOptions(*health_, connection_);

  find_ = app.add_subcommand(
      "find",
      "List the studies and series (with their UIDs) on a DICOM peer of the "
      "server (C-FIND), for `submit --pacs PEER --study UID --series UID`");
  find_
      ->add_option("--pacs", find_peer_,
                   "The peer (a name from the server's --dicom-peers file)")
      ->required();
  find_->add_option("--patient-id", find_patient_id_,
                    "Patient ID (wildcards * and ? allowed)");
  find_->add_option("--study-date", find_study_date_,
                    "YYYYMMDD, or a range YYYYMMDD-YYYYMMDD (either end may "
                    "be left out)");
  find_->add_option("--modality", find_modality_,
                    "CT, MR, ...: studies that have it, and only those series");
  find_->add_option("--accession", find_accession_,
                    "Accession number (wildcards * and ? allowed)");
  find_->add_option("--max-studies", find_max_studies_,
                    "At most this many studies (default: the server's, 100)");
  AddConnectionOptions(*find_, connection_);

  kept_ = app.add_subcommand(
      "kept",
      "The series the server's DICOM listener holds (no rule matched, or "
      "their job was made), and running them again (admins only)");
  kept_->require_subcommand(1);
  kept_list_ = kept_->add_subcommand(
      "list",
      "One line per kept series: id, since, AE titles, modality, instances, "
      "UIDs, why it is kept");
  AddConnectionOptions(*kept_list_, connection_);
  kept_rerun_ = kept_->add_subcommand(
      "rerun",
      "Match a kept series (or every one without a job) against the "
      "server's rules now and make its job; prints each job id");
  kept_rerun_->add_option("id", kept_id_, "A kept series' id (kept list)");
  kept_rerun_->add_flag("--all-unmatched", kept_all_unmatched_,
                        "Every kept series no rule matched");
  AddConnectionOptions(*kept_rerun_, connection_);
}

void RemoteCommands::RegisterFill(CLI::App& fill, FillArguments& args) {
  fill_ = &fill;
  fill_args_ = &args;
  AddConnectionOptions(fill, connection_);
  fill.add_option("--deadline", deadline_seconds_,
                  "With --server: give up (and cancel the job) after this "
                  "many seconds; with --submit: the server's limit on the "
                  "job, seconds from acceptance");
  fill.add_flag("--submit", fill_submit_,
                "With --server: upload as a detached job and print its id "
                "(then: watch, fetch, list, cancel); not with --out");
  fill.add_option("--label", label_,
                  "With --submit: free text shown by `list` (no PHI)");
  fill.add_option("--send-to", args.send_to,
                  "With --server: store the DICOM results (seg.dcm, "
                  "rtstruct.dcm) on these DICOM peers of the server (names "
                  "from its --dicom-peers file)")
      ->delimiter(',');
  // --out is where the in-process fill and the one-call form write; a
  // detached job's files are written by `fetch` (checked in ExecuteFill and
  // by the in-process fill's own check).
  fill.get_option("--out")->required(false);
}

int RemoteCommands::ExecuteFill() {
  if (fill_ == nullptr || !fill_->parsed()) return -1;
  const bool remote = fill_->get_option("--server")->count() > 0;
  if (!remote) {
    for (const char* option : {"--submit", "--label", "--send-to"}) {
      if (fill_->get_option(option)->count() > 0) {
        return Fail(
            absl::StrCat(option, " needs --server ADDR (a job on a server)"));
      }
    }
    return -1;  // in-process
  }
  if (deadline_seconds_ < 0) return Fail("--deadline must be >= 0");
  if (fill_submit_ && !fill_args_->local.report.empty()) {
    return Fail(
        "--report: a detached job's report is written by `interslice fetch "
        "JOB --report FILE`");
  }
  if (fill_submit_ && !fill_args_->out.empty()) {
    return Fail(
        "--out: a detached job's files are written by `interslice fetch JOB "
        "--out DIR`");
  }
  if (!fill_submit_ && fill_->get_option("--label")->count() > 0) {
    return Fail("--label needs --submit (it names a detached job)");
  }
  if (!fill_submit_ && fill_args_->out.empty()) {
    return Fail("--out is required (or --submit for a detached job)");
  }
  absl::StatusOr<Connection> connection = Connection::Open(connection_);
  if (!connection.ok()) return Fail(std::string(connection.status().message()));
  if (fill_submit_) {
    return RunFillSubmit(*connection, *fill_args_, deadline_seconds_, label_);
  }
  return RunFillRemote(*connection, *fill_args_, deadline_seconds_);
}

int RemoteCommands::Execute() {
  CLI::App* commands[] = {interpolate_, submit_,    watch_,     fetch_,
                          cancel_,      list_,      info_,      health_,
                          find_,        kept_list_, kept_rerun_};
  bool any = false;
  for (CLI::App* c : commands) any = any || (c != nullptr && c->parsed());
  if (!any) return -1;
  if (deadline_seconds_ < 0) return Fail("--deadline must be >= 0");
  if (kept_rerun_->parsed() && kept_all_unmatched_ == !kept_id_.empty()) {
    return Fail("kept rerun: give a kept series' id or --all-unmatched");
  }
  absl::StatusOr<Connection> connection = Connection::Open(connection_);
  if (!connection.ok()) return Fail(std::string(connection.status().message()));
  if (kept_list_->parsed()) return RunKeptList(*connection);
  if (kept_rerun_->parsed()) {
    return RunKeptRerun(*connection, kept_id_, kept_all_unmatched_);
  }
  if (interpolate_->parsed()) {
    return RunInterpolate(*connection, run_args_, deadline_seconds_);
  }
  if (submit_->parsed()) {
    return RunSubmit(*connection, run_args_, deadline_seconds_, label_);
  }
  if (watch_->parsed()) {
    return RunWatch(*connection, job_id_, quiet_, wait_deliveries_);
  }
  if (fetch_->parsed()) {
    return RunFetch(*connection, job_id_, out_, report_, quiet_);
  }
  if (cancel_->parsed()) return RunCancel(*connection, job_id_);
  if (list_->parsed()) return RunList(*connection, all_);
  if (info_->parsed()) return RunInfo(*connection);
  if (find_->parsed()) {
    if (find_max_studies_ < 0) return Fail("--max-studies must be >= 0");
    v1::FindRequest request;
    request.set_peer(find_peer_);
    request.set_patient_id(find_patient_id_);
    request.set_study_date(find_study_date_);
    request.set_modality(find_modality_);
    request.set_accession_number(find_accession_);
    request.set_max_studies(find_max_studies_);
    return RunFind(*connection, request);
  }
  return RunHealth(*connection);
}

}  // namespace interslice::client
