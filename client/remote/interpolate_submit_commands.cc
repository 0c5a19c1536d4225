#include "client/remote/interpolate_submit_commands.h"

#include <vector>

#include "CLI/CLI.hpp"
#include "client/remote/remote_common.h"
#include "client/remote/upload.h"
#include "job/errors.h"
#include "job/wire.h"

namespace interslice::client::remote {
namespace {

// What both take besides the job options: where the DICOM results go and
// where the series comes from.
void AddSeriesSourceAndDestinationOptions(CLI::App& remote,
                                          RunArguments& args) {
  remote
      .add_option("--send-to", args.send_to,
                  "Store the DICOM results on these DICOM peers of the "
                  "server (names from its --dicom-peers file)")
      ->delimiter(',');
  remote.add_option("--pacs", args.pacs_peer,
                    "Read the series from this DICOM peer of the server "
                    "(C-GET) instead of DICOM_DIR");
  remote.add_option("--study", args.pacs_study,
                    "With --pacs: the series' StudyInstanceUID");
  remote.add_option("--series", args.pacs_series,
                    "With --pacs: the SeriesInstanceUID");
  // DICOM_DIR is not needed with --pacs (PrepareUpload checks one of them).
  for (CLI::Option* o : remote.get_options()) {
    if (o->check_name("inputs")) o->required(false);
  }
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

}  // namespace

CLI::App* RegisterInterpolate(CLI::App& app, RemoteJobArguments& args,
                              ConnectionOptions& connection) {
  CLI::App* interpolate = app.add_subcommand(
      "interpolate",
      "Run a job on a server in one call: upload, progress, artifacts");
  AddRunOptions(*interpolate, args.run);
  AddConnectionOptions(*interpolate, connection);
  interpolate->add_option("--deadline", args.deadline_seconds,
                          "Give up (and cancel the job) after this many "
                          "seconds");
  AddSeriesSourceAndDestinationOptions(*interpolate, args.run);
  return interpolate;
}

CLI::App* RegisterSubmit(CLI::App& app, RemoteJobArguments& args,
                         ConnectionOptions& connection) {
  CLI::App* submit = app.add_subcommand(
      "submit", "Upload a detached job; prints its id (then: watch, fetch)");
  // The same job options as `run`; --out is accepted but only `fetch`
  // writes files.
  AddRunOptions(*submit, args.run);
  AddConnectionOptions(*submit, connection);
  submit->add_option("--deadline", args.deadline_seconds,
                     "Server-side limit on the job, seconds from acceptance");
  submit->add_option("--label", args.label,
                     "Free text shown by `list` (no PHI)");
  AddSeriesSourceAndDestinationOptions(*submit, args.run);
  // --out is required by AddRunOptions; a detached job needs none.
  for (CLI::Option* o : submit->get_options()) {
    if (o->check_name("--out")) o->required(false);
  }
  return submit;
}

int RunInterpolate(const Connection& connection,
                   const RemoteJobArguments& args) {
  std::vector<LocalFile> files;
  absl::StatusOr<v1::UploadHeader> header =
      PrepareUpload(args.run, 0, "", &files);
  if (!header.ok()) return Fail(std::string(header.status().message()));
  return InterpolateCall(connection, *header, files, args.run.out,
                         args.run.local.report, args.run.local.quiet,
                         args.deadline_seconds);
}

int RunSubmit(const Connection& connection, const RemoteJobArguments& args) {
  std::vector<LocalFile> files;
  // The output folder belongs to `fetch`; BuildJobSpec wants one.
  RunArguments with_out = args.run;
  if (with_out.out.empty()) with_out.out = ".";
  absl::StatusOr<v1::UploadHeader> header =
      PrepareUpload(with_out, args.deadline_seconds, args.label, &files);
  if (!header.ok()) return Fail(std::string(header.status().message()));
  return SubmitCall(connection, *header, files);
}

}  // namespace interslice::client::remote
