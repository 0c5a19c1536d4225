#include "client/remote/fill_remote_command.h"

#include <algorithm>
#include <filesystem>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "client/remote/remote_common.h"
#include "client/remote/upload.h"
#include "job/errors.h"
#include "job/wire.h"

namespace interslice::client::remote {
namespace fs = std::filesystem;
namespace {

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

}  // namespace

void RegisterFillRemoteOptions(CLI::App& fill, FillArguments& args,
                               FillRemoteArguments& remote,
                               ConnectionOptions& connection) {
  AddConnectionOptions(fill, connection);
  fill.add_option("--deadline", remote.deadline_seconds,
                  "With --server: give up (and cancel the job) after this "
                  "many seconds; with --submit: the server's limit on the "
                  "job, seconds from acceptance");
  fill.add_flag("--submit", remote.submit,
                "With --server: upload as a detached job and print its id "
                "(then: watch, fetch, list, cancel); not with --out");
  fill.add_option("--label", remote.label,
                  "With --submit: free text shown by `list` (no PHI)");
  fill.add_option("--send-to", args.send_to,
                  "With --server: store the DICOM results (seg.dcm, "
                  "rtstruct.dcm) on these DICOM peers of the server (names "
                  "from its --dicom-peers file)")
      ->delimiter(',');
  // --out is where the in-process fill and the one-call form write; a
  // detached job's files are written by `fetch` (checked in ExecuteFillRemote
  // and by the in-process fill's own check).
  fill.get_option("--out")->required(false);
}

int ExecuteFillRemote(const CLI::App& fill, const FillArguments& args,
                      const FillRemoteArguments& remote,
                      const ConnectionOptions& connection_options) {
  const bool on_server = fill.get_option("--server")->count() > 0;
  if (!on_server) {
    for (const char* option : {"--submit", "--label", "--send-to"}) {
      if (fill.get_option(option)->count() > 0) {
        return Fail(
            absl::StrCat(option, " needs --server ADDR (a job on a server)"));
      }
    }
    return -1;  // in-process
  }
  if (remote.deadline_seconds < 0) return Fail("--deadline must be >= 0");
  if (remote.submit && !args.local.report.empty()) {
    return Fail(
        "--report: a detached job's report is written by `interslice fetch "
        "JOB --report FILE`");
  }
  if (remote.submit && !args.out.empty()) {
    return Fail(
        "--out: a detached job's files are written by `interslice fetch JOB "
        "--out DIR`");
  }
  if (!remote.submit && fill.get_option("--label")->count() > 0) {
    return Fail("--label needs --submit (it names a detached job)");
  }
  if (!remote.submit && args.out.empty()) {
    return Fail("--out is required (or --submit for a detached job)");
  }
  absl::StatusOr<Connection> connection = Connection::Open(connection_options);
  if (!connection.ok()) return Fail(std::string(connection.status().message()));
  if (remote.submit) {
    return RunFillSubmit(*connection, args, remote.deadline_seconds,
                         remote.label);
  }
  return RunFillRemote(*connection, args, remote.deadline_seconds);
}

}  // namespace interslice::client::remote
