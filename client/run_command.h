// `interslice run`: the whole pipeline in-process, no server needed.
#ifndef INTERSLICE_CLIENT_RUN_COMMAND_H_
#define INTERSLICE_CLIENT_RUN_COMMAND_H_

#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/pipeline/pipeline.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

// Raw option values as typed by the user, before validation.
struct RunArguments {
  std::vector<std::string> inputs;
  std::string series_uid;
  std::optional<double> threshold;
  std::optional<double> upper;
  std::string roi;  // "x0,y0,z0,x1,y1,z1"
  std::string method = "cg";
  std::optional<int> iterations;
  std::optional<double> tolerance;
  std::string energy_units = "voxel";
  std::optional<int> factor;
  std::optional<double> spacing;
  bool strict_spacing = false;
  bool slab_deconvolution = false;
  std::string output_series;  // "mask,distance,intensity"
  bool seg = false;
  std::string dicom_compression = "none";
  std::string uid_root;
  bool random_uids = false;
  std::optional<int64_t> series_number_base;
  std::string multiframe_volume;
  std::optional<double> band;
  double adaptivity = 0;
  std::string out;
  std::string mesh = "stl";
  std::string volume = "nii";
  std::string report;
  int threads = 0;
  bool quiet = false;
  // Remote jobs only (interpolate, submit): DICOM peers of the server to
  // store the DICOM results on (JobSpec.send_to), and a series on a peer to
  // read instead of local files (JobSpec.pacs_source).
  std::vector<std::string> send_to;
  std::string pacs_peer, pacs_study, pacs_series;
};

// Adds the `run` subcommand's options to `app`, bound to `args`.
void AddRunOptions(CLI::App& app, RunArguments& args);

// Turns the raw arguments into a job spec; INVALID_ARGUMENT naming the
// option for anything malformed.
absl::StatusOr<JobSpec> BuildJobSpec(const RunArguments& args);

// Runs the job, shows progress on a terminal, writes the report, prints a
// summary. Returns the process exit code.
int ExecuteRun(const RunArguments& args);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_RUN_COMMAND_H_
