#include "server/fill_spec.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <set>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "nlohmann/json.hpp"

namespace interslice::server {
namespace {

namespace fs = std::filesystem;

// The same cap as `interslice run` applies when only a tolerance is given.
constexpr int kToleranceIterationCap = 100000;
constexpr const char* kSegmentationFolder = "segmentation";

absl::Status NotForFill(const std::string& field) {
  return absl::InvalidArgumentError(absl::StrCat(
      "spec.", field, " is not used by fill jobs (spec.fill is set)"));
}

}  // namespace

absl::StatusOr<FillJobSpec> FillJobSpecFromProto(const v1::JobSpec& p) {
  // Fields of interpolation jobs that mean nothing for a fill: refused, so
  // that a client never believes they were applied.
  if (p.has_threshold()) return NotForFill("threshold");
  if (p.has_upper_threshold()) return NotForFill("upper_threshold");
  if (p.has_roi()) return NotForFill("roi");
  if (p.strict_spacing()) return NotForFill("strict_spacing");
  if (!p.multiframe_volume().empty()) return NotForFill("multiframe_volume");
  if (p.derived_series().ByteSizeLong() > 0) {
    return NotForFill("derived_series");
  }
  if (p.segmentation().ByteSizeLong() > 0) return NotForFill("segmentation");
  if (p.has_pacs_source()) return NotForFill("pacs_source");

  const v1::LabelFill& f = p.fill();
  FillJobSpec spec;
  if (f.segmentation_file().empty()) {
    return absl::InvalidArgumentError(
        "spec.fill.segmentation_file is required (the FileChunk.file_name of "
        "the uploaded segmentation)");
  }
  spec.series_instance_uid = p.series_instance_uid();
  std::set<int> labels;
  for (int label : f.labels()) {
    if (label < 1 || label > 65535) {
      return absl::InvalidArgumentError(absl::StrCat(
          "spec.fill.labels: ", label, " is not a label (1..65535)"));
    }
    if (!labels.insert(label).second) {
      return absl::InvalidArgumentError(
          absl::StrCat("spec.fill.labels: label ", label, " is repeated"));
    }
    spec.fill.labels.push_back(label);
  }
  if (f.key_slices_size() > 0) {
    std::set<int64_t> seen;
    std::vector<int64_t> keys;
    for (int64_t k : f.key_slices()) {
      if (k < 0) {
        return absl::InvalidArgumentError(absl::StrCat(
            "spec.fill.key_slices: ", k, " is not a slice index (>= 0)"));
      }
      if (!seen.insert(k).second) {
        return absl::InvalidArgumentError(
            absl::StrCat("spec.fill.key_slices: slice ", k, " is repeated"));
      }
      keys.push_back(k);
    }
    spec.fill.key_slices = std::move(keys);
  }
  switch (p.z_resolution_case()) {
    case v1::JobSpec::kInsertionFactor:
      if (p.insertion_factor() < 1) {
        return absl::InvalidArgumentError("spec.insertion_factor must be >= 1");
      }
      spec.fill.z_resolution.factor = p.insertion_factor();
      break;
    case v1::JobSpec::kSliceSpacingMm:
      if (!(p.slice_spacing_mm() > 0) || !std::isfinite(p.slice_spacing_mm())) {
        return absl::InvalidArgumentError(
            "spec.slice_spacing_mm must be positive");
      }
      spec.fill.z_resolution.spacing_mm = p.slice_spacing_mm();
      break;
    default:
      break;
  }
  spec.uid_root = p.uid_root();
  spec.random_uids = p.random_uids();
  spec.write_seg = f.seg();
  if (f.has_rtstruct()) spec.write_rtstruct = f.rtstruct();
  // Unset = the fill's own default (auto, per label); a method given applies
  // to every label.
  spec.fill.method = p.method() == v1::SOLVER_METHOD_UNSPECIFIED
                         ? FillMethod::kAuto
                         : FillMethod::kSolver;
  switch (p.method()) {
    case v1::SOLVER_METHOD_UNSPECIFIED:
      break;
    case v1::SOLVER_METHOD_CONJUGATE_GRADIENT:
      spec.fill.solver.method = SolverMethod::kConjugateGradient;
      break;
    case v1::SOLVER_METHOD_LINEAR:
      spec.fill.solver.method = SolverMethod::kLinear;
      break;
    case v1::SOLVER_METHOD_DIRECT:
      spec.fill.solver.method = SolverMethod::kDirect;
      break;
    case v1::SOLVER_METHOD_MORPH:
      return absl::InvalidArgumentError(
          "spec.method: MORPH is not available for fill jobs (choose LINEAR, "
          "CONJUGATE_GRADIENT or DIRECT)");
    default:
      return absl::InvalidArgumentError("spec.method: unknown method");
  }
  if (p.has_max_iterations()) {
    if (p.max_iterations() < 0) {
      return absl::InvalidArgumentError("spec.max_iterations must be >= 0");
    }
    spec.fill.solver.max_iterations = p.max_iterations();
  } else if (p.has_tolerance()) {
    spec.fill.solver.max_iterations = kToleranceIterationCap;
  }
  if (p.has_tolerance()) {
    if (!(p.tolerance() > 0) || !std::isfinite(p.tolerance())) {
      return absl::InvalidArgumentError("spec.tolerance must be positive");
    }
    spec.fill.solver.tolerance = p.tolerance();
  }
  switch (p.energy_units()) {
    case v1::ENERGY_UNITS_UNSPECIFIED:
    case v1::ENERGY_UNITS_VOXEL:
      spec.fill.solver.units = EnergyUnits::kVoxel;
      break;
    case v1::ENERGY_UNITS_MILLIMETRE:
      spec.fill.solver.units = EnergyUnits::kMillimetre;
      break;
    default:
      return absl::InvalidArgumentError("spec.energy_units: unknown units");
  }
  if (p.has_band_radius_mm()) {
    if (!(p.band_radius_mm() > 0) || !std::isfinite(p.band_radius_mm())) {
      return absl::InvalidArgumentError("spec.band_radius_mm must be positive");
    }
    spec.fill.band_radius_mm = p.band_radius_mm();
  }
  spec.mesh_adaptivity = p.mesh_adaptivity();
  if (p.has_outputs()) {
    spec.volume_formats.clear();
    spec.mesh_formats.clear();
    auto add = [](std::vector<std::string>& list, const std::string& v) {
      if (std::find(list.begin(), list.end(), v) == list.end()) {
        list.push_back(v);
      }
    };
    for (int f : p.outputs().volume_formats()) {
      if (f == v1::VOLUME_FORMAT_NIFTI) {
        add(spec.volume_formats, "nii");
      } else if (f == v1::VOLUME_FORMAT_NRRD) {
        add(spec.volume_formats, "nrrd");
      } else {
        return absl::InvalidArgumentError(
            "spec.outputs.volume_formats: unknown format for a fill job "
            "(NIFTI or NRRD)");
      }
    }
    for (int f : p.outputs().mesh_formats()) {
      if (f == v1::MESH_FORMAT_STL) {
        add(spec.mesh_formats, "stl");
      } else if (f == v1::MESH_FORMAT_PLY) {
        add(spec.mesh_formats, "ply");
      } else if (f == v1::MESH_FORMAT_OBJ) {
        add(spec.mesh_formats, "obj");
      } else {
        return absl::InvalidArgumentError(
            "spec.outputs.mesh_formats: unknown format");
      }
    }
  }
  // Validate everything but the files, which the server supplies.
  FillJobSpec probe = spec;
  probe.segmentation = "segmentation";
  probe.reference = {"upload"};
  probe.output_dir = "out";
  if (absl::Status s = ValidateFillJobSpec(probe); !s.ok()) {
    return absl::InvalidArgumentError(s.message());
  }
  return spec;
}

std::string SegmentationUploadPath(const std::string& client_file_name) {
  std::string lower = client_file_name;
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char c) { return std::tolower(c); });
  std::string extension = ".dcm";
  for (const char* e : {".nii.gz", ".nii", ".nrrd"}) {
    if (absl::EndsWith(lower, e)) {
      extension = e;
      break;
    }
  }
  return absl::StrCat(kSegmentationFolder, "/segmentation", extension);
}

absl::Status SetFillInputs(const std::string& upload_dir, FillJobSpec* spec) {
  std::error_code ec;
  spec->reference.clear();
  for (const auto& entry : fs::directory_iterator(upload_dir, ec)) {
    if (entry.is_regular_file(ec)) {
      spec->reference.push_back(entry.path().string());
    }
  }
  std::sort(spec->reference.begin(), spec->reference.end());
  spec->segmentation.clear();
  for (const auto& entry :
       fs::directory_iterator(fs::path(upload_dir) / kSegmentationFolder, ec)) {
    if (entry.is_regular_file(ec)) spec->segmentation = entry.path().string();
  }
  if (spec->segmentation.empty()) {
    return absl::FailedPreconditionError(
        "the fill job's segmentation file is missing from its upload");
  }
  if (spec->reference.empty()) {
    return absl::FailedPreconditionError(
        "the fill job's upload holds no reference series files");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> RunFillJobInSpool(const v1::JobSpec& proto,
                                              const std::string& upload_dir,
                                              const std::string& output_dir,
                                              int64_t max_output_voxels,
                                              const ComputeContext& context) {
  absl::StatusOr<FillJobSpec> spec = FillJobSpecFromProto(proto);
  if (!spec.ok()) return spec.status();
  if (absl::Status s = SetFillInputs(upload_dir, &*spec); !s.ok()) return s;
  spec->output_dir = output_dir;
  if (max_output_voxels > 0) spec->fill.max_output_voxels = max_output_voxels;
  absl::StatusOr<FillJobReport> report = RunFillJob(*spec, context);
  if (!report.ok()) return report.status();
  return FillJobReportToJson(*report);
}

absl::StatusOr<FillReportSummary> SummarizeFillReport(const std::string& json) {
  nlohmann::ordered_json j =
      nlohmann::ordered_json::parse(json, nullptr, false);
  const auto bad = [] {
    return absl::InternalError("a fill job's report is not what it should be");
  };
  if (!j.is_object() || !j.contains("stages") || !j["stages"].is_object() ||
      !j.contains("artifacts") || !j["artifacts"].is_array()) {
    return bad();
  }
  FillReportSummary summary;
  for (const auto& [stage, seconds] : j["stages"].items()) {
    if (!seconds.is_number()) return bad();
    summary.stages.push_back({stage, seconds.get<double>()});
  }
  for (auto& a : j["artifacts"]) {
    if (!a.is_object() || !a.contains("kind") || !a["kind"].is_string() ||
        !a.contains("path") || !a["path"].is_string()) {
      return bad();
    }
    Artifact artifact;
    artifact.kind = a["kind"].get<std::string>();
    artifact.path = a["path"].get<std::string>();
    artifact.size_bytes = a.value("size_bytes", int64_t{0});
    a["path"] = fs::path(artifact.path).filename().string();
    summary.artifacts.push_back(std::move(artifact));
  }
  summary.report_json = j.dump(2);
  return summary;
}

}  // namespace interslice::server
