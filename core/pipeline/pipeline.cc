#include "core/pipeline/pipeline.h"

#include <sys/resource.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <future>
#include <limits>
#include <optional>
#include <system_error>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status_macros.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/encapsulated_stl.h"
#include "core/dicom_out/enhanced_series.h"
#include "core/dicom_out/preview_series.h"
#include "core/morph/intensity_morph.h"
#include "core/morph/morph.h"
#include "core/preview/preview.h"
#include "core/sdf/signed_distance.h"
#include "core/slab/slab_deconvolution.h"
#include "core/surface/surface.h"
#include "core/volume_io/volume_io.h"
#include "nlohmann/json.hpp"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

class StageClock {
 public:
  StageClock(JobReport& report, const ComputeContext& context,
             std::string stage)
      : report_(report),
        stage_(std::move(stage)),
        start_(std::chrono::steady_clock::now()) {
    context.Report({.stage = stage_, .fraction = 0});
  }
  ~StageClock() {
    const std::chrono::duration<double> elapsed =
        std::chrono::steady_clock::now() - start_;
    report_.stages.push_back({stage_, elapsed.count()});
  }

 private:
  JobReport& report_;
  std::string stage_;
  std::chrono::steady_clock::time_point start_;
};

// Bytes of a file, or of all files in a folder (a derived series).
int64_t PathSize(const std::filesystem::path& path) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    int64_t total = 0;
    for (const auto& entry : std::filesystem::directory_iterator(path, ec)) {
      if (entry.is_regular_file(ec)) total += entry.file_size(ec);
    }
    return total;
  }
  const auto size = std::filesystem::file_size(path, ec);
  return ec ? -1 : static_cast<int64_t>(size);
}

absl::Status WriteTextFile(const std::string& path, const std::string& text) {
  const std::string temp = path + ".tmp";
  {
    std::ofstream out(temp, std::ios::binary | std::ios::trunc);
    out << text;
    out.close();
    if (!out) {
      std::error_code ec;
      std::filesystem::remove(temp, ec);
      return absl::InternalError(absl::StrCat("cannot write ", path));
    }
  }
  std::error_code ec;
  std::filesystem::rename(temp, path, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot write ", path));
  return absl::OkStatus();
}

bool Contains(const std::vector<std::string>& list, const std::string& item) {
  return std::find(list.begin(), list.end(), item) != list.end();
}

// What tells this job's DICOM results apart from those of other parameters
// in the study's series descriptions (dicom_writer.h, "Identity"): the
// solver method, the threshold(s) (modality units; HU for CT) and the output
// slice spacing, e.g. "cg >=300 HU, 0.5 mm" or "direct 300..1500 HU,
// 0.625 mm"; at most 38 characters for every finite threshold (%.6g).
std::string ParameterSummary(const JobSpec& spec, const std::string& modality,
                             const Grid& output_grid) {
  const std::string unit = modality == "CT" ? " HU" : "";
  const std::string thresholds =
      spec.upper_threshold.has_value()
          ? absl::StrFormat("%.6g..%.6g", spec.lower_threshold,
                            *spec.upper_threshold)
          : absl::StrFormat(">=%.6g", spec.lower_threshold);
  return absl::StrFormat("%s %s%s, %.3g mm",
                         SolverMethodName(spec.solver.method), thresholds, unit,
                         output_grid.spacing[2]);
}

// The job's parameters that shape its results, in a canonical text: with the
// source instances and the UID root, it names the derived DICOM objects (see
// DicomWriteOptions::derivation_key). Thread counts, output folders and file
// formats do not change a voxel, so they are not part of it.
std::string DerivationKey(const JobSpec& spec,
                          const std::optional<VoxelBox>& roi,
                          const Grid& output_grid) {
  std::string key = absl::StrFormat(
      "lower=%.9g upper=%s band=%.9g method=%s units=%s iterations=%d "
      "tolerance=%.9g strict=%d volume=%s",
      spec.lower_threshold,
      spec.upper_threshold.has_value()
          ? absl::StrFormat("%.9g", *spec.upper_threshold)
          : "none",
      spec.band_radius_mm, SolverMethodName(spec.solver.method),
      EnergyUnitsName(spec.solver.units), spec.solver.max_iterations,
      spec.solver.tolerance, spec.strict_spacing ? 1 : 0,
      spec.multiframe_volume);
  // Linear is what every job did before the option existed: its key (and
  // so its UIDs) stays as it was.
  if (spec.intensity_method != "linear") {
    absl::StrAppend(&key, " intensity=", spec.intensity_method);
  }
  // Absent for the default segment, so that the UIDs of jobs that name
  // none stay as they were.
  if (!spec.segment_label.empty()) {
    absl::StrAppend(&key, " segment-label=", spec.segment_label);
  }
  if (!spec.segment_code.empty()) {
    absl::StrAppend(&key, " segment-code=", spec.segment_code);
  }
  // The voxel box, however it was given (a box in mm that maps to the same
  // voxels makes the same objects).
  if (roi.has_value()) {
    absl::StrAppend(&key, " roi=", absl::StrJoin(roi->begin, ","), ",",
                    absl::StrJoin(roi->end, ","));
  }
  absl::StrAppend(&key, " grid=", absl::StrJoin(output_grid.size, ","));
  for (double v : output_grid.spacing) {
    absl::StrAppend(&key, absl::StrFormat(" %.9g", v));
  }
  for (double v : output_grid.origin) {
    absl::StrAppend(&key, absl::StrFormat(" %.9g", v));
  }
  return key;
}

// Writes the intensity series into `folder`, replacing an older one only
// once the new one is complete: slices go to a fresh sibling folder, which is
// then renamed into place (a series never mixes files of two runs).
absl::Status WriteIntensityFolder(const DicomSeries& source,
                                  const Volume<float>& intensity,
                                  const DerivedObjectIdentity& identity,
                                  const DicomWriteOptions& options,
                                  const std::filesystem::path& folder) {
  const std::filesystem::path temp =
      folder.parent_path() / ("." + folder.filename().string() + ".tmp");
  std::error_code ec;
  std::filesystem::remove_all(temp, ec);
  INTERSLICE_RETURN_IF_ERROR(
      WriteIntensitySeries(source, intensity, identity, options, temp.string())
          .status());
  std::filesystem::remove_all(folder, ec);
  std::filesystem::rename(temp, folder, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot move the derived series into ", folder.string(),
                     ": ", ec.message()));
  }
  return absl::OkStatus();
}

// WriteIntensityFolder for the enhanced layout: the one instance in a fresh
// sibling folder, renamed into place (so a classic series of an earlier run
// in `folder` is replaced, never mixed with it).
absl::Status WriteEnhancedIntensityFolder(const DicomSeries& source,
                                          const Volume<float>& intensity,
                                          const DerivedObjectIdentity& identity,
                                          const DicomWriteOptions& options,
                                          const std::filesystem::path& folder) {
  const std::filesystem::path temp =
      folder.parent_path() / ("." + folder.filename().string() + ".tmp");
  std::error_code ec;
  std::filesystem::remove_all(temp, ec);
  std::filesystem::create_directories(temp, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create ", temp.string(), ": ", ec.message()));
  }
  INTERSLICE_RETURN_IF_ERROR(
      WriteEnhancedIntensity(source, intensity, identity, options,
                             (temp / kEnhancedIntensityFileName).string()));
  std::filesystem::remove_all(folder, ec);
  std::filesystem::rename(temp, folder, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot move the derived series into ", folder.string(),
                     ": ", ec.message()));
  }
  return absl::OkStatus();
}

// JobSpec::slab_deconvolution: the slices' slab deconvolution on the factor
// of the job's own (uniform) plan, the slab being the series' SliceThickness.
absl::StatusOr<Volume<float>> DeconvolveSlabsForPlan(
    const Volume<float>& image, const std::vector<double>& positions,
    double slice_thickness_mm, const JobSpec& spec, JobReport& report,
    const ComputeContext& context) {
  if (!(slice_thickness_mm > 0))
    return absl::InvalidArgumentError(
        "slab deconvolution needs the series' SliceThickness (0018,0050), "
        "which it does not have");
  INTERSLICE_ASSIGN_OR_RETURN(
      const StackPlan plan,
      PlanStack(positions,
                std::min(image.grid.spacing[0], image.grid.spacing[1]),
                spec.z_resolution));
  if (!plan.uniform)
    return absl::InvalidArgumentError(absl::StrFormat(
        "slab deconvolution needs uniform slice spacing; gaps run from %.3f "
        "to %.3f mm",
        plan.min_gap_mm, plan.max_gap_mm));
  SlabDeconvolutionOptions options;
  options.slab_thickness_mm = slice_thickness_mm;
  options.factor = plan.factor;
  INTERSLICE_ASSIGN_OR_RETURN(SlabDeconvolution result,
                              DeconvolveSlabs(image, options, context));
  report.slab_thickness_mm = slice_thickness_mm;
  report.slab_iterations = result.iterations;
  report.slab_residual_before = result.initial_rms;
  report.slab_residual_after = result.final_rms;
  return std::move(result.slices);
}

// The outline's colour in the previews of an interpolation.
constexpr std::array<uint8_t, 3> kOutlineColour = {60, 230, 60};

std::string FormatMm(double v) { return absl::StrFormat("%.4g", v); }

// The previews of the job (JobSpec::preview_formats): the scene of the
// refined field on the output grid over the grey values as read, with the
// original slices' true positions marked.
absl::StatusOr<PreviewSet> RenderJobPreviews(
    const JobSpec& spec, const DicomSeries& source, const Volume<float>& image,
    const std::vector<double>& positions, const Volume<float>& field,
    const JobReport& report, const ComputeContext& context) {
  const Grid& grid = field.grid;
  INTERSLICE_ASSIGN_OR_RETURN(const std::optional<float> padding,
                              SourcePixelPadding(source));
  PreviewScene scene;
  scene.grid = grid;
  const CancellationToken* cancel = context.cancel;
  scene.intensity = [&image, &positions, &grid, padding,
                     cancel](const VoxelBox& box) {
    ComputeContext one_thread;
    one_thread.threads = 1;
    one_thread.cancel = cancel;
    return ResampleSourceSlicesInBox(image, positions, grid, box, padding,
                                     one_thread);
  };
  if (absl::StatusOr<std::optional<SourceWindow>> window =
          SourceDisplayWindow(source);
      window.ok() && window->has_value()) {
    scene.window = DisplayWindow{(*window)->center, (*window)->width};
  }
  scene.window_must_show.push_back(spec.lower_threshold);
  if (spec.upper_threshold.has_value()) {
    scene.window_must_show.push_back(*spec.upper_threshold);
  }
  scene.field = &field;
  const std::string units = source.modality == "CT" ? " HU" : "";
  const std::string object =
      spec.upper_threshold.has_value()
          ? absl::StrFormat("%g to %g%s", spec.lower_threshold,
                            *spec.upper_threshold, units)
          : absl::StrFormat(">= %g%s", spec.lower_threshold, units);
  scene.objects = {
      {0, kOutlineColour, &field, absl::StrCat("surface ", object)}};
  const Vec3 normal = grid.Axis(2);
  const double first = grid.origin[0] * normal[0] + grid.origin[1] * normal[1] +
                       grid.origin[2] * normal[2];
  for (double p : positions) {
    scene.marked_slices.push_back((p - first) / grid.spacing[2]);
  }
  scene.marked_slices_name = "original slices";
  scene.legend.push_back(absl::StrFormat(
      "interslice: INTERPOLATED between %d original slices (not acquired)",
      positions.size()));
  std::string how = absl::StrCat(
      "method ", std::string(SolverMethodName(report.solver.method)),
      ", threshold ", object, ", spacing ", FormatMm(grid.spacing[0]), " x ",
      FormatMm(grid.spacing[1]), " x ", FormatMm(grid.spacing[2]), " mm");
  if (spec.slab_deconvolution) absl::StrAppend(&how, ", slab deconvolution");
  scene.legend.push_back(how);
  if (report.gantry_tilt_degrees != 0) {
    scene.legend.push_back(absl::StrFormat(
        "gantry tilt of %.3g degrees corrected", report.gantry_tilt_degrees));
  }
  return RenderPreviews(scene, PreviewOptions(), context);
}

// The previews as pictures for the DICOM writer.
std::vector<RgbPicture> Pictures(const std::vector<PreviewImage>& images) {
  std::vector<RgbPicture> pictures;
  for (const PreviewImage& image : images) {
    RgbPicture p;
    p.name = image.name;
    p.width = image.width;
    p.height = image.height;
    p.rgb = &image.rgb;
    p.description = image.description;
    p.patient_orientation = image.patient_orientation;
    if (image.plane_axis == 2) p.output_slice = image.plane_index;
    pictures.push_back(p);
  }
  return pictures;
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

  // A SEG and a distance map reference the intensity series on their grid,
  // so either one brings it along (see JobSpec::output_series).
  const bool wants_seg = spec.write_seg || Contains(spec.output_series, "mask");
  const bool wants_distance_map = Contains(spec.output_series, "distance");
  const bool wants_intensity = Contains(spec.output_series, "intensity") ||
                               wants_seg || wants_distance_map;
  const bool wants_previews = !spec.preview_formats.empty();

  // read
  Volume<float> image;
  // The source series' metadata (slices, UIDs, grid) for DICOM outputs;
  // its voxels are moved out.
  DicomSeries source;
  std::vector<double> positions;  // of the slices used, mm along the normal
  {
    StageClock clock(report, context, "read");
    DicomReadOptions options;
    options.series_instance_uid = spec.series_instance_uid;
    options.volume = spec.multiframe_volume;
    options.max_voxels = spec.max_input_voxels;
    INTERSLICE_ASSIGN_OR_RETURN(DicomSeries series,
                                ReadDicomSeries(spec.inputs, options, context));
    report.input_grid = series.image.grid;
    report.skipped_files = series.skipped_files;
    report.gantry_tilt_degrees = series.gantry_tilt_degrees;
    report.min_gap_mm = series.min_gap_mm;
    report.max_gap_mm = series.max_gap_mm;
    report.input_notes = series.notes;
    int64_t first_slice = 0;
    report.roi = spec.roi;
    report.roi_mm = spec.roi_mm;
    if (spec.roi_mm.has_value()) {
      // Mapped with the slices' true positions along the normal (non-uniform
      // spacing, tilt-corrected slices), not the grid's median spacing.
      std::vector<double> offsets;
      offsets.reserve(series.slices.size());
      for (const DicomSliceInfo& slice : series.slices) {
        offsets.push_back(slice.position_along_normal -
                          series.slices.front().position_along_normal);
      }
      INTERSLICE_ASSIGN_OR_RETURN(
          report.roi,
          PhysicalBoxToVoxelBox(*spec.roi_mm, series.image.grid, offsets));
    }
    if (report.roi.has_value()) {
      const VoxelBox& roi = *report.roi;
      INTERSLICE_RETURN_IF_ERROR(ValidateVoxelBox(roi, series.image.grid));
      image = CropVolume(series.image, roi);
      first_slice = roi.begin[2];
    } else {
      image = std::move(series.image);
    }
    for (int64_t k = 0; k < image.grid.size[2]; ++k) {
      positions.push_back(series.slices[first_slice + k].position_along_normal);
    }
    // The crop placed the origin by the median spacing; with non-uniform
    // spacing the first slice used is at its own position.
    const Vec3 normal = image.grid.Axis(2);
    const double offset =
        positions.front() - (series.slices.front().position_along_normal +
                             first_slice * series.image.grid.spacing[2]);
    for (int c = 0; c < 3; ++c) image.grid.origin[c] += offset * normal[c];
    report.input_slices = image.grid.size[2];
    series.image.data = std::vector<float>();
    source = std::move(series);
    if (image.grid.size[2] < 2) {
      return absl::InvalidArgumentError(
          absl::StrCat("interpolation needs at least 2 slices; the ",
                       report.roi.has_value() ? "region of interest" : "series",
                       " has ", image.grid.size[2]));
    }
  }
  if (wants_intensity && spec.dicom_layout == "enhanced" &&
      source.modality != "CT" && source.modality != "MR") {
    // Said now, not after the whole computation (PlanEnhancedIntensity
    // says it again at the write).
    return absl::FailedPreconditionError(absl::StrCat(
        "--dicom-layout enhanced writes Enhanced CT and Enhanced MR only; "
        "this series' modality is '",
        source.modality, "' (use the classic layout)"));
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // contour: 2D signed distance maps of the original slices
  Volume<float> slice_maps;
  {
    StageClock clock(report, context, "contour");
    ContourOptions options;
    options.lower = spec.lower_threshold;
    options.upper = spec.upper_threshold;
    options.band_radius_mm = spec.band_radius_mm;
    if (spec.slab_deconvolution) {
      // Contour the slab deconvolution of the slices instead (JobSpec).
      INTERSLICE_ASSIGN_OR_RETURN(
          Volume<float> estimates,
          DeconvolveSlabsForPlan(image, positions, source.slice_thickness_mm,
                                 spec, report, context));
      INTERSLICE_ASSIGN_OR_RETURN(
          slice_maps, ComputeSliceDistanceMaps(estimates, options, context));
    } else {
      INTERSLICE_ASSIGN_OR_RETURN(
          slice_maps, ComputeSliceDistanceMaps(image, options, context));
    }
    // Release the grey values early unless an intensity series or the
    // previews need them.
    if (!wants_intensity && !wants_previews) image = Volume<float>();
  }

  // stack
  StackedField stacked;
  {
    StageClock clock(report, context, "stack");
    INTERSLICE_ASSIGN_OR_RETURN(const StackPlan plan,
                                PlanStack(positions,
                                          std::min(slice_maps.grid.spacing[0],
                                                   slice_maps.grid.spacing[1]),
                                          spec.z_resolution));
    if (spec.strict_spacing && !plan.uniform) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "non-uniform slice spacing: gaps from %.3f to %.3f mm (median "
          "%.3f mm; missing slices?) and strict spacing was asked for",
          plan.min_gap_mm, plan.max_gap_mm, plan.median_gap_mm));
    }
    if (spec.solver.method == SolverMethod::kMorph) {
      INTERSLICE_ASSIGN_OR_RETURN(MorphedField morphed,
                                  StackMorph(slice_maps, plan, MorphOptions(),
                                             spec.max_output_voxels, context));
      stacked = std::move(morphed.stacked);
    } else {
      INTERSLICE_ASSIGN_OR_RETURN(
          stacked,
          StackLinear(slice_maps, plan, spec.max_output_voxels, context));
    }
    slice_maps = Volume<float>();
    report.insertion_factor = plan.factor;
    report.max_snap_mm = plan.max_snap_mm;
    report.output_grid = stacked.field.grid;
  }

  // The intensity morph (written in the write stage) needs only the source
  // slices and the output grid, so it runs from here on beside the solve,
  // mesh and preview stages, which leave a core idle much of the time (the
  // Encapsulated STL's simplification and the mesh writer are serial): on
  // the CT phantom with the shipped rule, the job takes ~25% less time. It
  // runs on its own thread with the job's thread count (so the job briefly
  // uses one thread more than ComputeContext::threads), reports no progress
  // of its own (Report is never called concurrently; the write stage says
  // "intensity" when it takes the result) and polls the same cancellation.
  // The future is declared after everything it reads, so an early return
  // waits for it before they go.
  std::optional<float> intensity_padding;
  std::future<absl::StatusOr<MorphedIntensity>> morphing;
  if (wants_intensity) {
    INTERSLICE_ASSIGN_OR_RETURN(intensity_padding, SourcePixelPadding(source));
    if (spec.intensity_method == "morph") {
      ComputeContext morph_context = context;
      morph_context.progress = nullptr;
      morphing = std::async(
          std::launch::async, [&image, &positions, grid = stacked.field.grid,
                               padding = intensity_padding,
                               morph_context = std::move(morph_context)] {
            return MorphIntensity(image, positions, grid, padding, nullptr,
                                  IntensityMorphOptions(), morph_context);
          });
    }
  }

  // solve
  {
    StageClock clock(report, context, "solve");
    SolverOptions solver = spec.solver;
    const bool morph_method = spec.solver.method == SolverMethod::kMorph;
    if (morph_method) {
      const MorphOptions morph;
      solver.fidelity = morph.fidelity;
      solver.fidelity_taper = morph.fidelity_taper;
      // The cubic morph is crease-free by construction: no refinement
      // (MorphOptions::refine); kLinear leaves the field as it is and still
      // reports its energy.
      if (!morph.refine) {
        solver.method = SolverMethod::kLinear;
        solver.fidelity = 0;
      }
    }
    INTERSLICE_ASSIGN_OR_RETURN(
        report.solver,
        Solve(stacked.field, stacked.fixed_slices, solver, context));
    if (morph_method) {
      report.solver.method = SolverMethod::kMorph;
      INTERSLICE_RETURN_IF_ERROR(
          RemoveUnsupportedComponents(stacked.field, stacked.fixed_slices,
                                      MorphOptions().component_margin_mm,
                                      context)
              .status());
    }
  }
  const Volume<float>& field = stacked.field;

  // mesh
  Mesh mesh;
  if (!spec.mesh_formats.empty()) {
    StageClock clock(report, context, "mesh");
    SurfaceOptions options;
    options.adaptivity = spec.mesh_adaptivity;
    INTERSLICE_ASSIGN_OR_RETURN(mesh, ExtractSurface(field, options, context));
    report.mesh_vertices = static_cast<int64_t>(mesh.vertices.size());
    report.mesh_triangles = static_cast<int64_t>(mesh.triangles.size());
  }
  // The Encapsulated STL's mesh (JobSpec::dicom_mesh_adaptivity) and how far
  // it lies from the unsimplified surface.
  const bool wants_dicom_mesh =
      wants_intensity && Contains(spec.mesh_formats, "stl");
  Mesh dicom_mesh_storage;
  const Mesh* dicom_mesh = &mesh;
  // The Encapsulated STL's mesh is made beside the preview and write stages
  // (meshoptimizer's simplification is serial: ~2 s of the shipped rule's
  // job on the CT phantom, a core otherwise idle), on its own thread with a
  // context that reports no progress (Report is never concurrent); its
  // stage time is recorded when the write stage takes it. It reads `mesh`
  // and `field`, which nothing changes meanwhile, and writes only its own
  // report fields. The future is declared after what it reads.
  double dicom_mesh_seconds = -1;  // -1: no dicom-mesh stage
  std::future<absl::Status> dicom_meshing;
  if (wants_dicom_mesh) {
    ComputeContext mesh_context = context;
    mesh_context.progress = nullptr;
    dicom_meshing = std::async(
        std::launch::async,
        [&, mesh_context = std::move(mesh_context)]() -> absl::Status {
          const ComputeContext& context = mesh_context;
          const auto started = std::chrono::steady_clock::now();
          // A stage only when it does something: another mesh, or its
          // deviation (the default, 0 for both, stores the surface as
          // extracted). First the adaptivity (another extraction), then the
          // size cap (quadric edge collapse of that mesh).
          const int64_t max_triangles = MaxEncapsulatedStlTriangles(
              spec.dicom_mesh_max_mb,
              static_cast<int64_t>(source.slices.size()));
          const bool reextract =
              spec.dicom_mesh_adaptivity != spec.mesh_adaptivity;
          const bool may_cap =
              max_triangles > 0 &&
              (reextract ||
               static_cast<int64_t>(mesh.triangles.size()) > max_triangles);
          const bool staged =
              reextract || may_cap || spec.dicom_mesh_adaptivity > 0;
          absl::Status status = [&]() -> absl::Status {
            SurfaceOptions options;
            if (reextract) {
              options.adaptivity = spec.dicom_mesh_adaptivity;
              INTERSLICE_ASSIGN_OR_RETURN(
                  dicom_mesh_storage, ExtractSurface(field, options, context));
              dicom_mesh = &dicom_mesh_storage;
            }
            report.dicom_mesh_max_mb = spec.dicom_mesh_max_mb;
            report.dicom_mesh_triangles_before_cap =
                static_cast<int64_t>(dicom_mesh->triangles.size());
            if (max_triangles > 0 &&
                static_cast<int64_t>(dicom_mesh->triangles.size()) >
                    max_triangles) {
              INTERSLICE_ASSIGN_OR_RETURN(
                  SimplifiedMesh simplified,
                  SimplifyMesh(*dicom_mesh, {.max_triangles = max_triangles},
                               context));
              dicom_mesh_storage = std::move(simplified.mesh);
              dicom_mesh = &dicom_mesh_storage;
              report.dicom_mesh_simplify_error_mm = simplified.error_mm;
              report.dicom_mesh_over_cap =
                  simplified.triangles_after > max_triangles;
            }
            report.dicom_mesh_stl_bytes =
                84 + 50 * static_cast<int64_t>(dicom_mesh->triangles.size());
            report.dicom_mesh_adaptivity = spec.dicom_mesh_adaptivity;
            report.dicom_mesh_vertices =
                static_cast<int64_t>(dicom_mesh->vertices.size());
            report.dicom_mesh_triangles =
                static_cast<int64_t>(dicom_mesh->triangles.size());
            if (spec.dicom_mesh_adaptivity > 0) {
              Mesh reference_storage;
              const Mesh* reference = &mesh;
              if (spec.mesh_adaptivity != 0) {
                options.adaptivity = 0;
                INTERSLICE_ASSIGN_OR_RETURN(
                    reference_storage, ExtractSurface(field, options, context));
                reference = &reference_storage;
              }
              // The finest grid spacing: the deviation is known to about half a
              // voxel of the output grid (half the spacing took minutes for the
              // CT phantom's 2.7 million triangles).
              const double resolution = *std::min_element(
                  field.grid.spacing.begin(), field.grid.spacing.end());
              INTERSLICE_ASSIGN_OR_RETURN(
                  const MeshDeviation deviation,
                  MeasureMeshDeviation(*dicom_mesh, *reference, resolution,
                                       context));
              report.dicom_mesh_max_deviation_mm = deviation.max_mm;
              report.dicom_mesh_mean_deviation_mm = deviation.mean_mm;
              report.dicom_mesh_resolution_mm = deviation.resolution_mm;
              report.dicom_mesh_samples_beyond_band = deviation.beyond_band;
            }
            return absl::OkStatus();
          }();
          if (staged) {
            dicom_mesh_seconds = std::chrono::duration<double>(
                                     std::chrono::steady_clock::now() - started)
                                     .count();
          }
          return status;
        });
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // preview: rendered now, written with the other outputs; a failure is a
  // note, never the job's failure (JobSpec::preview_formats).
  std::optional<PreviewSet> previews;
  if (wants_previews) {
    StageClock clock(report, context, "preview");
    absl::StatusOr<PreviewSet> rendered = RenderJobPreviews(
        spec, source, image, positions, field, report, context);
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    if (rendered.ok()) {
      report.preview_notes = rendered->notes;
      previews = *std::move(rendered);
    } else {
      report.preview_notes.push_back(
          absl::StrCat("previews skipped: ", rendered.status().message()));
    }
    if (!wants_intensity) image = Volume<float>();
  }

  // write: every artifact is independent, so they are written in parallel
  // (gzip of the float volumes dominates this stage).
  {
    StageClock clock(report, context, "write");
    std::error_code ec;
    std::filesystem::create_directories(spec.output_dir, ec);
    if (ec || !std::filesystem::is_directory(spec.output_dir)) {
      return absl::FailedPreconditionError(
          absl::StrCat("cannot create output folder ", spec.output_dir, ": ",
                       ec ? ec.message() : "not a folder"));
    }
    const std::filesystem::path dir(spec.output_dir);
    Volume<uint8_t> mask;
    if (!spec.volume_formats.empty() || wants_seg) {
      mask.grid = field.grid;
      mask.data.resize(field.data.size());
      std::transform(field.data.begin(), field.data.end(), mask.data.begin(),
                     [](float v) -> uint8_t { return v >= 0 ? 1 : 0; });
    }
    DicomWriteOptions dicom_options;
    dicom_options.uid_root = spec.uid_root;
    dicom_options.random_uids = spec.random_uids;
    dicom_options.series_number_base = spec.series_number_base;
    dicom_options.derivation_key = DerivationKey(spec, report.roi, field.grid);
    dicom_options.parameter_set = dicom_options.derivation_key;
    dicom_options.parameter_summary =
        ParameterSummary(spec, source.modality, field.grid);
    if (spec.dicom_compression == "rle") {
      dicom_options.intensity_encoding =
          DicomWriteOptions::PixelEncoding::kRleLossless;
    }
    DerivedObjects objects;
    Volume<float> intensity;
    if (wants_intensity) {
      INTERSLICE_ASSIGN_OR_RETURN(
          objects,
          PlanDerivedObjects(source, field.grid.size[2], dicom_options));
      if (spec.dicom_layout == "enhanced") {
        // One Enhanced CT / MR instance instead of an image per slice; the SEG,
        // distance map, previews and STL reference it.
        INTERSLICE_ASSIGN_OR_RETURN(
            objects.intensity,
            PlanEnhancedIntensity(source, objects.intensity, dicom_options));
      }
      const std::optional<float> padding = intensity_padding;
      report.intensity_method = spec.intensity_method;
      if (spec.intensity_method == "morph") {
        dicom_options.intensity_interpolation =
            DicomWriteOptions::IntensityInterpolation::kMorph;
        context.Report({.stage = "intensity", .fraction = 0});
        INTERSLICE_ASSIGN_OR_RETURN(MorphedIntensity morphed, morphing.get());
        context.Report({.stage = "intensity", .fraction = 1});
        intensity = std::move(morphed.values);
        const IntensityMorphStatistics& stats = morphed.statistics;
        report.intensity_gaps = stats.gaps;
        report.intensity_gaps_not_registered = stats.gaps_not_registered;
        report.intensity_fallback_fraction = stats.fallback_fraction;
        report.intensity_mean_displacement_mm = stats.mean_displacement_mm;
        report.intensity_max_displacement_mm = stats.max_displacement_mm;
      } else {
        INTERSLICE_ASSIGN_OR_RETURN(
            intensity, ResampleSourceSlices(image, positions, field.grid,
                                            padding, context));
      }
      image = Volume<float>();
    }

    // Each task writes one artifact and records its kind, path and status.
    struct Task {
      std::string kind;
      std::filesystem::path path;
      std::function<absl::Status()> write;
      absl::Status status;
      // A preview: its failure is a note in the report, not the job's.
      bool optional = false;
    };
    std::vector<Task> tasks;
    // JobSpec::omit_files_dicom_objects_carry: a file whose content one of
    // this job's DICOM objects carries is not written.
    const bool omit = spec.omit_files_dicom_objects_carry;
    for (const std::string& format : spec.volume_formats) {
      const std::string ext = format == "nii"    ? ".nii.gz"
                              : format == "nrrd" ? ".nrrd"
                                                 : ".nii";
      const auto distance_path = dir / ("distance" + ext);
      const auto mask_path = dir / ("mask" + ext);
      if (!(omit && wants_distance_map)) {
        tasks.push_back({"distance", distance_path, [&, distance_path] {
                           return WriteVolume(field, distance_path.string(),
                                              context);
                         }});
      }
      if (!(omit && wants_seg)) {
        tasks.push_back({"mask", mask_path, [&, mask_path] {
                           return WriteVolume(mask, mask_path.string(),
                                              context);
                         }});
      }
    }
    bool surface_stl_written = false;
    bool mesh_file_written = false;
    for (const std::string& format : spec.mesh_formats) {
      if (omit && wants_dicom_mesh && format == "stl") continue;
      surface_stl_written |= format == "stl";
      mesh_file_written = true;
      const auto path = dir / ("surface." + format);
      tasks.push_back({"surface", path,
                       [&, path] { return WriteMesh(mesh, path.string()); }});
    }
    // The note explains the mesh files' coordinates.
    if (mesh_file_written) {
      const auto path = dir / "surface-coordinates.txt";
      tasks.push_back({"surface-coordinates", path, [&, path] {
                         return WriteTextFile(path.string(),
                                              MeshConventionNote(source));
                       }});
    }
    if (wants_intensity) {
      const auto path = dir / "series-intensity";
      // The artifact is the folder either way: the server names its files
      // "series-intensity/IM00001.dcm" ... or "series-intensity/enhanced.dcm"
      // (at most one folder level).
      const bool enhanced = spec.dicom_layout == "enhanced";
      tasks.push_back({"series-intensity", path, [&, path, enhanced] {
                         absl::Status written =
                             enhanced
                                 ? WriteEnhancedIntensityFolder(
                                       source, intensity, objects.intensity,
                                       dicom_options, path)
                                 : WriteIntensityFolder(source, intensity,
                                                        objects.intensity,
                                                        dicom_options, path);
                         // Only this task reads the resampled volume: free
                         // it (one output volume) while the other outputs
                         // are still being written.
                         intensity = Volume<float>();
                         return written;
                       }});
    }
    if (wants_distance_map) {
      const auto path = dir / "distance.dcm";
      tasks.push_back({"distance-map", path, [&, path] {
                         return WriteDistanceMap(
                             source, field, objects.distance_map,
                             objects.intensity, dicom_options, path.string());
                       }});
    }
    if (wants_seg) {
      const auto path = dir / "seg.dcm";
      tasks.push_back(
          {"seg", path, [&, path]() -> absl::Status {
             std::optional<CodedConcept> code;
             if (!spec.segment_code.empty()) {
               INTERSLICE_ASSIGN_OR_RETURN(
                   code, ParseCodedConcept(spec.segment_code));
             }
             INTERSLICE_ASSIGN_OR_RETURN(
                 const SegmentDescription segment,
                 DescribeThresholdSegment(source, spec.lower_threshold,
                                          spec.upper_threshold,
                                          spec.segment_label, code));
             return WriteSegmentation(source, mask, objects.segmentation,
                                      objects.intensity, segment, dicom_options,
                                      path.string());
           }});
    }
    std::vector<RgbPicture> pictures;
    if (previews.has_value() && Contains(spec.preview_formats, "png")) {
      const auto path = dir / "previews";
      tasks.push_back(
          {"previews",
           path,
           [&, path] {
             return WritePreviewPngs(previews->images, path.string()).status();
           },
           {},
           /*optional=*/true});
    }
    if (previews.has_value() && Contains(spec.preview_formats, "dicom")) {
      pictures = Pictures(previews->images);
      const auto path = dir / "previews-dicom";
      tasks.push_back(
          {"previews-dicom",
           path,
           [&, path]() -> absl::Status {
             std::vector<std::string> names;
             for (const RgbPicture& p : pictures) names.push_back(p.name);
             // Derived from the intensity series when the job writes it.
             const DerivedObjectIdentity* referenced =
                 wants_intensity ? &objects.intensity : nullptr;
             INTERSLICE_ASSIGN_OR_RETURN(
                 const DerivedObjectIdentity identity,
                 PlanPreviewSeries(source, names, dicom_options, referenced));
             return WritePreviewSeries(source, field.grid, pictures, identity,
                                       referenced, dicom_options, path.string())
                 .status();
           },
           {},
           /*optional=*/true});
    }
    tbb::task_arena arena(context.threads > 0 ? context.threads
                                              : tbb::task_arena::automatic);
    arena.execute([&] {
      tbb::parallel_for(size_t{0}, tasks.size(), size_t{1},
                        [&](size_t n) { tasks[n].status = tasks[n].write(); });
    });
    for (const Task& task : tasks) {
      if (task.optional && !task.status.ok()) {
        report.preview_notes.push_back(absl::StrCat(
            "previews not written (", task.kind, "): ", task.status.message()));
        continue;
      }
      INTERSLICE_RETURN_IF_ERROR(task.status);
      report.artifacts.push_back(
          {task.kind, task.path.string(), PathSize(task.path)});
    }
    // With DICOM outputs, the STL mesh also goes into the study as an
    // Encapsulated STL object; it embeds surface.stl, so it comes after.
    if (wants_dicom_mesh) {
      INTERSLICE_RETURN_IF_ERROR(dicom_meshing.get());
      if (dicom_mesh_seconds >= 0) {
        report.stages.push_back({"dicom-mesh", dicom_mesh_seconds});
      }
      const auto path = dir / kEncapsulatedStlFileName;
      // Its own mesh, or the surface when surface.stl was not written, goes
      // through a temporary STL file (the writer embeds a file as it is),
      // deleted once embedded.
      std::filesystem::path stl = dir / "surface.stl";
      const bool temporary = dicom_mesh != &mesh || !surface_stl_written;
      if (temporary) {
        stl = dir / ".surface-dicom.stl";
        INTERSLICE_RETURN_IF_ERROR(WriteStl(*dicom_mesh, stl.string()));
      }
      const absl::Status written =
          WriteEncapsulatedStl(source, stl.string(), objects.surface_stl,
                               dicom_options, path.string());
      if (temporary) {
        std::error_code ignored;
        std::filesystem::remove(stl, ignored);
      }
      INTERSLICE_RETURN_IF_ERROR(written);
      report.artifacts.push_back(
          {"surface-stl-dicom", path.string(), PathSize(path)});
    }
  }
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
  struct rusage usage {};
  if (getrusage(RUSAGE_SELF, &usage) != 0) return -1;
  return static_cast<int64_t>(usage.ru_maxrss) * 1024;  // Linux: kilobytes
}

}  // namespace interslice
