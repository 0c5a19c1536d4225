// `interslice fill`: a segmentation (label map, DICOM SEG or RTSTRUCT) drawn
// on some slices of a reference DICOM series, filled between its key slices
// for every label, in-process (core/labels/fill_job.h).
#ifndef INTERSLICE_CLIENT_FILL_COMMAND_H_
#define INTERSLICE_CLIENT_FILL_COMMAND_H_

#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/labels/fill_job.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

// Raw option values as typed by the user, before validation.
struct FillArguments {
  std::string segmentation;
  std::vector<std::string> reference;
  std::string series_uid;
  std::string labels;      // "1,3,7"
  std::string key_slices;  // "0,5,10" or ranges "0-40:5"
  std::string method = "auto";
  std::optional<int> iterations;
  std::optional<int> factor;
  std::optional<double> spacing;
  std::optional<double> band;
  double adaptivity = 0;
  std::string out;
  std::string mesh = "stl";
  std::string volume = "nii";
  std::string report;
  bool seg = false;
  bool rtstruct = false, no_rtstruct = false;
  std::string uid_root;
  bool random_uids = false;
  int threads = 0;
  bool quiet = false;
};

void AddFillOptions(CLI::App& app, FillArguments& args);

// Parses a slice list: comma-separated indices and ranges "a-b" (inclusive)
// or "a-b:step". INVALID_ARGUMENT naming the bad item.
absl::StatusOr<std::vector<int64_t>> ParseSliceList(const std::string& text);

// INVALID_ARGUMENT naming the option for anything malformed.
absl::StatusOr<FillJobSpec> BuildFillJobSpec(const FillArguments& args);

// Runs the job, prints warnings and a summary. Returns the exit code.
int ExecuteFill(const FillArguments& args);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_FILL_COMMAND_H_
