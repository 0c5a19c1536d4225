#include "core/pipeline/pipeline.h"

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <future>
#include <limits>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/preview_series.h"
#include "core/pipeline/pipeline_internal.h"
#include "nlohmann/json.hpp"

namespace interslice {
namespace {

using pipeline_internal::Contains;
using pipeline_internal::ContourStage;
using pipeline_internal::MeshStage;
using pipeline_internal::PendingDicomMesh;
using pipeline_internal::PendingIntensity;
using pipeline_internal::PreviewStage;
using pipeline_internal::ReadSourceStage;
using pipeline_internal::SolveStage;
using pipeline_internal::SourceSlices;
using pipeline_internal::StackStage;
using pipeline_internal::StartDicomMesh;
using pipeline_internal::StartIntensityMorph;
using pipeline_internal::WantedOutputs;
using pipeline_internal::WriteStage;

WantedOutputs OutputsOfSpec(const JobSpec& spec) {
  WantedOutputs wants;
  // A SEG and a distance map reference the intensity series on their grid,
  // so either one brings it along (see JobSpec::output_series).
  wants.seg = spec.write_seg || Contains(spec.output_series, "mask");
  wants.distance_map = Contains(spec.output_series, "distance");
  wants.intensity = Contains(spec.output_series, "intensity") || wants.seg ||
                    wants.distance_map;
  wants.previews = !spec.preview_formats.empty();
  // The Encapsulated STL's mesh (JobSpec::dicom_mesh_adaptivity) and how far
  // it lies from the unsimplified surface.
  wants.dicom_mesh = wants.intensity && Contains(spec.mesh_formats, "stl");
  return wants;
}

// Said right after the read, not after the whole computation
// (PlanEnhancedIntensity says it again at the write).
absl::Status CheckEnhancedLayoutModality(const JobSpec& spec,
                                         const WantedOutputs& wants,
                                         const DicomSeries& source) {
  if (wants.intensity && spec.dicom_layout == "enhanced" &&
      source.modality != "CT" && source.modality != "MR") {
    return absl::FailedPreconditionError(absl::StrCat(
        "--dicom-layout enhanced writes Enhanced CT and Enhanced MR only; "
        "this series' modality is '",
        source.modality, "' (use the classic layout)"));
  }
  return absl::OkStatus();
}

}  // namespace

int64_t MaxEncapsulatedStlTriangles(double max_mb, int64_t source_instances) {
  if (!(max_mb > 0)) return 0;
  const double bytes =
      max_mb * 1e6 - static_cast<double>(kEncapsulatedStlHeaderReserveBytes) -
      static_cast<double>(kEncapsulatedStlBytesPerSourceInstance) *
          static_cast<double>(std::max<int64_t>(0, source_instances)) -
      84;
  return std::max<int64_t>(1, static_cast<int64_t>(std::floor(bytes / 50)));
}

absl::Status ValidateJobSpec(const JobSpec& spec) {
  if (spec.inputs.empty()) {
    return absl::InvalidArgumentError("no input DICOM files or folders given");
  }
  if (spec.output_dir.empty()) {
    return absl::InvalidArgumentError("no output folder given");
  }
  if (!std::isfinite(spec.lower_threshold)) {
    return absl::InvalidArgumentError("threshold must be a finite number");
  }
  if (spec.upper_threshold.has_value() &&
      (!std::isfinite(*spec.upper_threshold) ||
       *spec.upper_threshold < spec.lower_threshold)) {
    return absl::InvalidArgumentError(
        "upper threshold must be finite and not below the threshold");
  }
  if (spec.roi.has_value() && spec.roi_mm.has_value()) {
    return absl::InvalidArgumentError(
        "region of interest given twice: roi (voxels) and roi_mm (patient "
        "mm) exclude each other; give one");
  }
  if (spec.roi_mm.has_value()) {
    for (int a = 0; a < 3; ++a) {
      if (!std::isfinite(spec.roi_mm->min[a]) ||
          !std::isfinite(spec.roi_mm->max[a]) ||
          spec.roi_mm->min[a] > spec.roi_mm->max[a]) {
        return absl::InvalidArgumentError(
            "roi_mm must be finite with min <= max on every axis");
      }
    }
  }
  if (!spec.segment_label.empty()) {
    if (absl::Status s = ValidateSegmentLabel(spec.segment_label); !s.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("segment_label: ", s.message()));
    }
  }
  if (!spec.segment_code.empty()) {
    if (absl::Status s = ParseCodedConcept(spec.segment_code).status();
        !s.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("segment_code: ", s.message()));
    }
  }
  if (!(spec.dicom_mesh_adaptivity >= 0 && spec.dicom_mesh_adaptivity <= 1)) {
    return absl::InvalidArgumentError(
        "DICOM mesh adaptivity must be in [0, 1]");
  }
  if (!(spec.dicom_mesh_max_mb == 0 ||
        (spec.dicom_mesh_max_mb >= kMinDicomMeshMaxMb &&
         spec.dicom_mesh_max_mb <= kMaxDicomMeshMaxMb))) {
    return absl::InvalidArgumentError(
        absl::StrFormat("DICOM mesh size cap must be 0 (none) or between %g "
                        "and %g MB",
                        kMinDicomMeshMaxMb, kMaxDicomMeshMaxMb));
  }
  if (!(spec.mesh_adaptivity >= 0 && spec.mesh_adaptivity <= 1)) {
    return absl::InvalidArgumentError("mesh adaptivity must be in [0, 1]");
  }
  for (const std::string& f : spec.volume_formats) {
    if (f != "nii" && f != "nrrd" && f != "nii-uncompressed") {
      return absl::InvalidArgumentError(
          absl::StrCat("unknown volume format '", f,
                       "' (choose from nii, nrrd, nii-uncompressed)"));
    }
  }
  if (spec.dicom_compression != "none" && spec.dicom_compression != "rle") {
    return absl::InvalidArgumentError(
        absl::StrCat("unknown DICOM compression '", spec.dicom_compression,
                     "' (choose from none, rle)"));
  }
  if (spec.dicom_layout != "classic" && spec.dicom_layout != "enhanced") {
    return absl::InvalidArgumentError(
        absl::StrCat("unknown DICOM layout '", spec.dicom_layout,
                     "' (choose from classic, enhanced)"));
  }
  if (spec.intensity_method != "linear" && spec.intensity_method != "morph") {
    return absl::InvalidArgumentError(
        absl::StrCat("unknown intensity method '", spec.intensity_method,
                     "' (choose from linear, morph)"));
  }
  for (const std::string& f : spec.output_series) {
    if (f != "mask" && f != "distance" && f != "intensity") {
      return absl::InvalidArgumentError(
          absl::StrCat("unknown output series '", f,
                       "' (choose from mask, distance, intensity)"));
    }
  }
  for (const std::string& f : spec.mesh_formats) {
    if (f != "stl" && f != "ply" && f != "obj") {
      return absl::InvalidArgumentError(absl::StrCat(
          "unknown mesh format '", f, "' (choose from stl, ply, obj)"));
    }
  }
  if (spec.solver.max_iterations < 0) {
    return absl::InvalidArgumentError("iterations must be >= 0");
  }
  if (!(spec.solver.tolerance >= 0) || !std::isfinite(spec.solver.tolerance)) {
    return absl::InvalidArgumentError("tolerance must be >= 0");
  }
  if (spec.max_output_voxels <= 0 || spec.max_input_voxels <= 0) {
    return absl::InvalidArgumentError("voxel limits must be positive");
  }
  // The derived objects are numbered base + 1 ... base + 6, each a DICOM IS
  // (signed 32-bit): refused now rather than after the whole job ran.
  if (spec.series_number_base >
      std::numeric_limits<int>::max() - kPreviewSeriesNumberOffset) {
    return absl::InvalidArgumentError(absl::StrCat(
        "series number base must be at most ",
        std::numeric_limits<int>::max() - kPreviewSeriesNumberOffset));
  }
  for (const std::string& f : spec.preview_formats) {
    if (f != "png" && f != "dicom") {
      return absl::InvalidArgumentError(absl::StrCat(
          "unknown preview format '", f, "' (choose from png, dicom)"));
    }
  }
  // Likewise a malformed UID root.
  if (!spec.uid_root.empty()) {
    if (absl::Status s = DeriveDicomUid(spec.uid_root, "check").status();
        !s.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("uid root: ", s.message()));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<JobReport> RunJob(const JobSpec& spec,
                                 const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateJobSpec(spec));
  JobReport report;
  report.energy_units = spec.solver.units;
  const WantedOutputs wants = OutputsOfSpec(spec);

  INTERSLICE_ASSIGN_OR_RETURN(SourceSlices input,
                              ReadSourceStage(spec, report, context));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhancedLayoutModality(spec, wants, input.source));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // contour: 2D signed distance maps of the original slices
  INTERSLICE_ASSIGN_OR_RETURN(
      Volume<float> slice_maps,
      ContourStage(spec, wants, input, report, context));
  INTERSLICE_ASSIGN_OR_RETURN(
      StackedField stacked, StackStage(spec, input.positions,
                                       std::move(slice_maps), report, context));

  // The intensity morph runs from here on beside the solve, mesh and
  // preview stages (StartIntensityMorph). `intensity` is declared after
  // everything its thread reads, so an early return waits for it before
  // they go.
  PendingIntensity intensity;
  if (wants.intensity) {
    INTERSLICE_ASSIGN_OR_RETURN(intensity.padding,
                                SourcePixelPadding(input.source));
    if (spec.intensity_method == "morph") {
      intensity.morphing =
          StartIntensityMorph(input.image, input.positions, stacked.field.grid,
                              intensity.padding, context);
    }
  }

  INTERSLICE_RETURN_IF_ERROR(SolveStage(spec, stacked, report, context));
  const Volume<float>& field = stacked.field;

  Mesh mesh;
  if (!spec.mesh_formats.empty()) {
    INTERSLICE_ASSIGN_OR_RETURN(mesh, MeshStage(spec, field, report, context));
  }
  // The Encapsulated STL's mesh, beside the preview and write stages
  // (StartDicomMesh); declared after what its thread reads.
  PendingDicomMesh dicom_mesh;
  dicom_mesh.mesh = &mesh;
  if (wants.dicom_mesh) {
    StartDicomMesh(spec, input.source, mesh, field, report, dicom_mesh,
                   context);
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // preview: rendered now, written with the other outputs; a failure is a
  // note, never the job's failure (JobSpec::preview_formats).
  std::optional<PreviewSet> previews;
  if (wants.previews) {
    INTERSLICE_ASSIGN_OR_RETURN(
        previews, PreviewStage(spec, wants, input, field, report, context));
  }

  INTERSLICE_RETURN_IF_ERROR(WriteStage(spec, wants, input, field, mesh,
                                        previews, intensity, dicom_mesh, report,
                                        context));
  return report;
}

std::string JobReportToJson(const JobReport& report) {
  using nlohmann::ordered_json;
  ordered_json j;
  ordered_json stages = ordered_json::object();
  for (const StageTiming& s : report.stages) stages[s.stage] = s.seconds;
  j["stages"] = stages;
  j["solver"] = {{"method", SolverMethodName(report.solver.method)},
                 {"iterations", report.solver.iterations},
                 {"relative_residual", report.solver.relative_residual},
                 {"initial_residual", report.solver.initial_residual},
                 {"energy", report.solver.energy},
                 {"initial_energy", report.solver.initial_energy},
                 {"energy_units", EnergyUnitsName(report.energy_units)},
                 {"converged", report.solver.converged}};
  auto grid_json = [](const Grid& g) {
    return ordered_json{{"size", g.size},
                        {"spacing", g.spacing},
                        {"origin", g.origin},
                        {"direction", g.direction}};
  };
  j["grid"] = grid_json(report.output_grid);
  j["grid"]["insertion_factor"] = report.insertion_factor;
  j["grid"]["max_snap_mm"] = report.max_snap_mm;
  j["input"] = grid_json(report.input_grid);
  j["input"]["slices_used"] = report.input_slices;
  j["input"]["skipped_files"] = report.skipped_files;
  j["input"]["gantry_tilt_degrees"] = report.gantry_tilt_degrees;
  j["input"]["min_gap_mm"] = report.min_gap_mm;
  j["input"]["max_gap_mm"] = report.max_gap_mm;
  j["input"]["notes"] = report.input_notes;
  if (report.roi.has_value()) {
    j["input"]["roi"] = {{"begin", report.roi->begin},
                         {"end", report.roi->end}};
  }
  if (report.roi_mm.has_value()) {
    j["input"]["roi_mm"] = {{"min", report.roi_mm->min},
                            {"max", report.roi_mm->max}};
  }
  if (report.slab_thickness_mm > 0) {
    j["input"]["slab_deconvolution"] = {
        {"slab_thickness_mm", report.slab_thickness_mm},
        {"iterations", report.slab_iterations},
        {"residual_before", report.slab_residual_before},
        {"residual_after", report.slab_residual_after}};
  }
  if (!report.intensity_method.empty()) {
    j["intensity"] = {
        {"method", report.intensity_method},
        {"gaps", report.intensity_gaps},
        {"gaps_not_registered", report.intensity_gaps_not_registered},
        {"fallback_fraction", report.intensity_fallback_fraction},
        {"mean_displacement_mm", report.intensity_mean_displacement_mm},
        {"max_displacement_mm", report.intensity_max_displacement_mm}};
  }
  j["mesh"] = {{"vertices", report.mesh_vertices},
               {"triangles", report.mesh_triangles}};
  if (report.dicom_mesh_adaptivity >= 0) {
    j["dicom_mesh"] = {
        {"adaptivity", report.dicom_mesh_adaptivity},
        {"vertices", report.dicom_mesh_vertices},
        {"triangles", report.dicom_mesh_triangles},
        {"max_deviation_mm", report.dicom_mesh_max_deviation_mm},
        {"mean_deviation_mm", report.dicom_mesh_mean_deviation_mm},
        {"deviation_resolution_mm", report.dicom_mesh_resolution_mm},
        {"samples_beyond_band", report.dicom_mesh_samples_beyond_band},
        {"max_mb", report.dicom_mesh_max_mb},
        {"triangles_before_cap", report.dicom_mesh_triangles_before_cap},
        {"simplify_error_mm", report.dicom_mesh_simplify_error_mm},
        {"stl_bytes", report.dicom_mesh_stl_bytes},
        {"over_cap", report.dicom_mesh_over_cap}};
  }
  bool previews = !report.preview_notes.empty();
  for (const StageTiming& s : report.stages) previews |= s.stage == "preview";
  if (previews) j["previews"] = {{"notes", report.preview_notes}};
  ordered_json artifacts = ordered_json::array();
  for (const Artifact& a : report.artifacts) {
    artifacts.push_back(
        {{"kind", a.kind}, {"path", a.path}, {"size_bytes", a.size_bytes}});
  }
  j["artifacts"] = artifacts;
  j["peak_rss_bytes"] = report.peak_rss_bytes;
  return j.dump(2);
}

absl::StatusOr<JobReport> JobReportFromJson(const std::string& text) {
  using nlohmann::json;
  const json j = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return absl::InvalidArgumentError("job report: not a JSON object");
  }
  JobReport report;
  try {
    for (const auto& [stage, seconds] : j.at("stages").items()) {
      report.stages.push_back({stage, seconds.get<double>()});
    }
    const json& solver = j.at("solver");
    const std::string method = solver.at("method").get<std::string>();
    bool known_method = false;
    for (SolverMethod m :
         {SolverMethod::kLinear, SolverMethod::kConjugateGradient,
          SolverMethod::kDirect, SolverMethod::kMorph}) {
      if (SolverMethodName(m) == method) {
        report.solver.method = m;
        known_method = true;
      }
    }
    if (!known_method) {
      return absl::InvalidArgumentError(
          absl::StrCat("job report: unknown solver method ", method));
    }
    report.solver.iterations = solver.at("iterations").get<int>();
    report.solver.relative_residual =
        solver.at("relative_residual").get<double>();
    report.solver.initial_residual =
        solver.at("initial_residual").get<double>();
    report.solver.energy = solver.at("energy").get<double>();
    report.solver.initial_energy = solver.at("initial_energy").get<double>();
    report.solver.converged = solver.at("converged").get<bool>();
    report.energy_units = solver.at("energy_units").get<std::string>() ==
                                  EnergyUnitsName(EnergyUnits::kMillimetre)
                              ? EnergyUnits::kMillimetre
                              : EnergyUnits::kVoxel;
    auto read_grid = [](const json& g, Grid& grid) {
      grid.size = g.at("size").get<Index3>();
      grid.spacing = g.at("spacing").get<Vec3>();
      grid.origin = g.at("origin").get<Vec3>();
      grid.direction = g.at("direction").get<Mat3>();
    };
    const json& grid = j.at("grid");
    read_grid(grid, report.output_grid);
    report.insertion_factor = grid.at("insertion_factor").get<int>();
    report.max_snap_mm = grid.at("max_snap_mm").get<double>();
    const json& input = j.at("input");
    read_grid(input, report.input_grid);
    report.input_slices = input.at("slices_used").get<int64_t>();
    report.skipped_files = input.at("skipped_files").get<int64_t>();
    report.gantry_tilt_degrees = input.at("gantry_tilt_degrees").get<double>();
    report.min_gap_mm = input.at("min_gap_mm").get<double>();
    report.max_gap_mm = input.at("max_gap_mm").get<double>();
    // Absent in reports written before the reader had notes.
    if (input.contains("notes")) {
      report.input_notes = input.at("notes").get<std::vector<std::string>>();
    }
    if (input.contains("roi")) {
      report.roi = VoxelBox{input.at("roi").at("begin").get<Index3>(),
                            input.at("roi").at("end").get<Index3>()};
    }
    if (input.contains("roi_mm")) {
      report.roi_mm = PhysicalBox{input.at("roi_mm").at("min").get<Vec3>(),
                                  input.at("roi_mm").at("max").get<Vec3>()};
    }
    if (input.contains("slab_deconvolution")) {
      const json& slab = input.at("slab_deconvolution");
      report.slab_thickness_mm = slab.at("slab_thickness_mm").get<double>();
      report.slab_iterations = slab.at("iterations").get<int>();
      report.slab_residual_before = slab.at("residual_before").get<double>();
      report.slab_residual_after = slab.at("residual_after").get<double>();
    }
    // Absent in reports without an intensity series (and in older ones).
    if (j.contains("intensity")) {
      const json& intensity = j.at("intensity");
      report.intensity_method = intensity.at("method").get<std::string>();
      report.intensity_gaps = intensity.at("gaps").get<int>();
      report.intensity_gaps_not_registered =
          intensity.at("gaps_not_registered").get<int>();
      report.intensity_fallback_fraction =
          intensity.at("fallback_fraction").get<double>();
      report.intensity_mean_displacement_mm =
          intensity.at("mean_displacement_mm").get<double>();
      report.intensity_max_displacement_mm =
          intensity.at("max_displacement_mm").get<double>();
    }
    report.mesh_vertices = j.at("mesh").at("vertices").get<int64_t>();
    report.mesh_triangles = j.at("mesh").at("triangles").get<int64_t>();
    if (j.contains("dicom_mesh")) {
      const json& d = j.at("dicom_mesh");
      report.dicom_mesh_adaptivity = d.at("adaptivity").get<double>();
      report.dicom_mesh_vertices = d.at("vertices").get<int64_t>();
      report.dicom_mesh_triangles = d.at("triangles").get<int64_t>();
      report.dicom_mesh_max_deviation_mm =
          d.at("max_deviation_mm").get<double>();
      report.dicom_mesh_mean_deviation_mm =
          d.at("mean_deviation_mm").get<double>();
      report.dicom_mesh_resolution_mm =
          d.at("deviation_resolution_mm").get<double>();
      report.dicom_mesh_samples_beyond_band =
          d.at("samples_beyond_band").get<int64_t>();
      // The size cap's fields: absent in reports from before it.
      if (d.contains("max_mb")) {
        report.dicom_mesh_max_mb = d.at("max_mb").get<double>();
        report.dicom_mesh_triangles_before_cap =
            d.at("triangles_before_cap").get<int64_t>();
        report.dicom_mesh_simplify_error_mm =
            d.at("simplify_error_mm").get<double>();
        report.dicom_mesh_stl_bytes = d.at("stl_bytes").get<int64_t>();
        report.dicom_mesh_over_cap = d.at("over_cap").get<bool>();
      }
    }
    if (j.contains("previews")) {
      report.preview_notes =
          j.at("previews").at("notes").get<std::vector<std::string>>();
    }
    for (const json& a : j.at("artifacts")) {
      report.artifacts.push_back({a.at("kind").get<std::string>(),
                                  a.at("path").get<std::string>(),
                                  a.at("size_bytes").get<int64_t>()});
    }
    report.peak_rss_bytes = j.at("peak_rss_bytes").get<int64_t>();
  } catch (const json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("job report: ", e.what()));
  }
  return report;
}

int64_t PeakRssBytes() {
  // The mm's own high-water mark, which starts afresh at execve (see the
  // header for why not getrusage).
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    int64_t kilobytes = 0;
    if (std::sscanf(line.c_str(), "VmHWM: %" SCNd64 " kB", &kilobytes) == 1) {
      return kilobytes * 1024;
    }
  }
  return -1;
}

}  // namespace interslice
