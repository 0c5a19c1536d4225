// BuildJobSpec (declared in client/run_command.h): the `interslice run`
// option values -> the core job spec. Its own library (interslice_job_spec)
// so that the server's DICOM rules (server/dicom/config.cc), whose job keys
// are the same option names, map them exactly as the command line does.
#include <algorithm>
#include <cmath>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "client/run_command.h"

namespace interslice::client {
namespace {

// CG iteration cap when only --tolerance is given: far beyond what any
// reasonable problem needs, but it still bounds the run.
constexpr int kToleranceIterationCap = 100000;

absl::StatusOr<std::vector<std::string>> ParseList(
    const std::string& text, const std::vector<std::string>& allowed,
    const std::string& option) {
  std::vector<std::string> out;
  if (text.empty() || text == "none") return out;
  for (absl::string_view item : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    std::string value(item);
    if (std::find(allowed.begin(), allowed.end(), value) == allowed.end()) {
      return absl::InvalidArgumentError(
          absl::StrCat(option, ": unknown value '", value, "' (choose from ",
                       absl::StrJoin(allowed, ", "), ", or none)"));
    }
    if (std::find(out.begin(), out.end(), value) == out.end()) {
      out.push_back(value);
    }
  }
  return out;
}

absl::StatusOr<VoxelBox> ParseRoi(const std::string& text) {
  const std::vector<std::string> parts = absl::StrSplit(text, ',');
  if (parts.size() != 6) {
    return absl::InvalidArgumentError(
        "--roi: expected six integers x0,y0,z0,x1,y1,z1 (a half-open voxel "
        "box)");
  }
  int64_t v[6];
  for (int n = 0; n < 6; ++n) {
    if (!absl::SimpleAtoi(parts[n], &v[n])) {
      return absl::InvalidArgumentError(
          absl::StrCat("--roi: '", parts[n], "' is not an integer"));
    }
  }
  return VoxelBox{{v[0], v[1], v[2]}, {v[3], v[4], v[5]}};
}

}  // namespace

absl::StatusOr<JobSpec> BuildJobSpec(const RunArguments& args) {
  JobSpec spec;
  spec.inputs = args.inputs;
  spec.series_instance_uid = args.series_uid;
  spec.output_dir = args.out;
  if (!args.threshold.has_value()) {
    return absl::InvalidArgumentError("--threshold is required");
  }
  spec.lower_threshold = static_cast<float>(*args.threshold);
  if (args.upper.has_value()) {
    spec.upper_threshold = static_cast<float>(*args.upper);
  }
  if (!args.roi.empty()) {
    absl::StatusOr<VoxelBox> roi = ParseRoi(args.roi);
    if (!roi.ok()) return roi.status();
    spec.roi = *roi;
  }
  if (args.method == "direct") {
    spec.solver.method = SolverMethod::kDirect;
  } else if (args.method == "cg") {
    spec.solver.method = SolverMethod::kConjugateGradient;
  } else if (args.method == "linear") {
    spec.solver.method = SolverMethod::kLinear;
  } else if (args.method == "morph") {
    spec.solver.method = SolverMethod::kMorph;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("--method: unknown method '", args.method,
                     "' (choose from direct, cg, linear, morph)"));
  }
  if (args.iterations.has_value()) {
    if (*args.iterations < 0) {
      return absl::InvalidArgumentError("--iterations must be >= 0");
    }
    spec.solver.max_iterations = *args.iterations;
  } else if (args.tolerance.has_value()) {
    spec.solver.max_iterations = kToleranceIterationCap;
  }
  if (args.tolerance.has_value()) {
    if (!(*args.tolerance > 0) || !std::isfinite(*args.tolerance)) {
      return absl::InvalidArgumentError("--tolerance must be positive");
    }
    spec.solver.tolerance = *args.tolerance;
  }
  if (args.energy_units == "voxel") {
    spec.solver.units = EnergyUnits::kVoxel;
  } else if (args.energy_units == "mm") {
    spec.solver.units = EnergyUnits::kMillimetre;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("--energy-units: unknown units '", args.energy_units,
                     "' (choose from voxel, mm)"));
  }
  if (args.factor.has_value() && args.spacing.has_value()) {
    return absl::InvalidArgumentError(
        "--factor and --spacing are alternatives; give one");
  }
  spec.z_resolution.factor = args.factor;
  spec.z_resolution.spacing_mm = args.spacing;
  spec.strict_spacing = args.strict_spacing;
  spec.slab_deconvolution = args.slab_deconvolution;
  absl::StatusOr<std::vector<std::string>> series = ParseList(
      args.output_series, {"mask", "distance", "intensity"}, "--output-series");
  if (!series.ok()) return series.status();
  spec.output_series = *series;
  if (args.dicom_compression != "none" && args.dicom_compression != "rle") {
    return absl::InvalidArgumentError(
        absl::StrCat("--dicom-compression: unknown value '",
                     args.dicom_compression, "' (choose from none, rle)"));
  }
  spec.dicom_compression = args.dicom_compression;
  spec.write_seg = args.seg;
  spec.uid_root = args.uid_root;
  spec.random_uids = args.random_uids;
  if (args.series_number_base.has_value()) {
    if (*args.series_number_base < 1 || *args.series_number_base > 2147483644) {
      return absl::InvalidArgumentError(
          "--series-number-base must be between 1 and 2147483644");
    }
    spec.series_number_base = *args.series_number_base;
  }
  spec.multiframe_volume = args.multiframe_volume;
  if (args.band.has_value()) {
    if (!(*args.band > 0)) {
      return absl::InvalidArgumentError("--band must be positive (mm)");
    }
    spec.band_radius_mm = *args.band;
  }
  spec.mesh_adaptivity = args.adaptivity;
  absl::StatusOr<std::vector<std::string>> mesh =
      ParseList(args.mesh, {"stl", "ply", "obj"}, "--mesh");
  if (!mesh.ok()) return mesh.status();
  spec.mesh_formats = *mesh;
  absl::StatusOr<std::vector<std::string>> volume =
      ParseList(args.volume, {"nii", "nrrd", "nii-uncompressed"}, "--volume");
  if (!volume.ok()) return volume.status();
  spec.volume_formats = *volume;
  if (args.threads < 0) {
    return absl::InvalidArgumentError("--threads must be >= 0");
  }
  absl::Status valid = ValidateJobSpec(spec);
  if (!valid.ok()) return valid;
  return spec;
}

}  // namespace interslice::client
