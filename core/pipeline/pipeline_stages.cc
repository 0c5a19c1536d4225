// The stages of RunJob before the write (pipeline_internal.h): read,
// contour, stack, solve, mesh, the Encapsulated STL's mesh and the previews.
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <future>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/morph/intensity_morph.h"
#include "core/morph/morph.h"
#include "core/pipeline/pipeline_internal.h"
#include "core/preview/preview.h"
#include "core/sdf/signed_distance.h"
#include "core/slab/slab_deconvolution.h"
#include "core/surface/surface.h"

namespace interslice::pipeline_internal {
namespace {

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

// The voxel box of JobSpec::roi_mm in `series`: mapped with the slices' true
// positions along the normal (non-uniform spacing, tilt-corrected slices),
// not the grid's median spacing.
absl::StatusOr<VoxelBox> RoiOfPhysicalBox(const PhysicalBox& roi_mm,
                                          const DicomSeries& series) {
  std::vector<double> offsets;
  offsets.reserve(series.slices.size());
  for (const DicomSliceInfo& slice : series.slices) {
    offsets.push_back(slice.position_along_normal -
                      series.slices.front().position_along_normal);
  }
  return PhysicalBoxToVoxelBox(roi_mm, series.image.grid, offsets);
}

// The Encapsulated STL's mesh into `dicom_mesh` and its facts into the
// report: first the adaptivity (another extraction), then the size cap
// (quadric edge collapse of that mesh), then its deviation from the
// unsimplified surface.
absl::Status MakeDicomMesh(const JobSpec& spec, int64_t max_triangles,
                           bool reextract, const Mesh& mesh,
                           const Volume<float>& field, JobReport& report,
                           PendingDicomMesh& dicom_mesh,
                           const ComputeContext& context) {
  SurfaceOptions options;
  if (reextract) {
    options.adaptivity = spec.dicom_mesh_adaptivity;
    INTERSLICE_ASSIGN_OR_RETURN(dicom_mesh.storage,
                                ExtractSurface(field, options, context));
    dicom_mesh.mesh = &dicom_mesh.storage;
  }
  report.dicom_mesh_max_mb = spec.dicom_mesh_max_mb;
  report.dicom_mesh_triangles_before_cap =
      static_cast<int64_t>(dicom_mesh.mesh->triangles.size());
  if (max_triangles > 0 &&
      static_cast<int64_t>(dicom_mesh.mesh->triangles.size()) > max_triangles) {
    INTERSLICE_ASSIGN_OR_RETURN(
        SimplifiedMesh simplified,
        SimplifyMesh(*dicom_mesh.mesh, {.max_triangles = max_triangles},
                     context));
    dicom_mesh.storage = std::move(simplified.mesh);
    dicom_mesh.mesh = &dicom_mesh.storage;
    report.dicom_mesh_simplify_error_mm = simplified.error_mm;
    report.dicom_mesh_over_cap = simplified.triangles_after > max_triangles;
  }
  report.dicom_mesh_stl_bytes =
      84 + 50 * static_cast<int64_t>(dicom_mesh.mesh->triangles.size());
  report.dicom_mesh_adaptivity = spec.dicom_mesh_adaptivity;
  report.dicom_mesh_vertices =
      static_cast<int64_t>(dicom_mesh.mesh->vertices.size());
  report.dicom_mesh_triangles =
      static_cast<int64_t>(dicom_mesh.mesh->triangles.size());
  if (spec.dicom_mesh_adaptivity > 0) {
    Mesh reference_storage;
    const Mesh* reference = &mesh;
    if (spec.mesh_adaptivity != 0) {
      options.adaptivity = 0;
      INTERSLICE_ASSIGN_OR_RETURN(reference_storage,
                                  ExtractSurface(field, options, context));
      reference = &reference_storage;
    }
    // The finest grid spacing: the deviation is known to about half a
    // voxel of the output grid (half the spacing took minutes for the
    // CT phantom's 2.7 million triangles).
    const double resolution =
        *std::min_element(field.grid.spacing.begin(), field.grid.spacing.end());
    INTERSLICE_ASSIGN_OR_RETURN(
        const MeshDeviation deviation,
        MeasureMeshDeviation(*dicom_mesh.mesh, *reference, resolution,
                             context));
    report.dicom_mesh_max_deviation_mm = deviation.max_mm;
    report.dicom_mesh_mean_deviation_mm = deviation.mean_mm;
    report.dicom_mesh_resolution_mm = deviation.resolution_mm;
    report.dicom_mesh_samples_beyond_band = deviation.beyond_band;
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<SourceSlices> ReadSourceStage(const JobSpec& spec,
                                             JobReport& report,
                                             const ComputeContext& context) {
  StageClock clock(report, context, "read");
  SourceSlices input;
  Volume<float>& image = input.image;
  std::vector<double>& positions = input.positions;
  DicomReadOptions options;
  options.series_instance_uid = spec.series_instance_uid;
  options.volume = spec.multiframe_volume;
  options.max_voxels = spec.max_input_voxels;
  options.strict_frame_of_reference = spec.strict_frame_of_reference;
  INTERSLICE_ASSIGN_OR_RETURN(DicomSeries series,
                              ReadDicomSeries(spec.inputs, options, context));
  report.input_grid = series.image.grid;
  report.skipped_files = series.skipped_files;
  report.gantry_tilt_degrees = series.gantry_tilt_degrees;
  report.min_gap_mm = series.min_gap_mm;
  report.max_gap_mm = series.max_gap_mm;
  report.input_notes = series.notes;
  report.input_warnings = series.warnings;
  int64_t first_slice = 0;
  report.roi = spec.roi;
  report.roi_mm = spec.roi_mm;
  if (spec.roi_mm.has_value()) {
    INTERSLICE_ASSIGN_OR_RETURN(report.roi,
                                RoiOfPhysicalBox(*spec.roi_mm, series));
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
  input.source = std::move(series);
  if (image.grid.size[2] < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat("interpolation needs at least 2 slices; the ",
                     report.roi.has_value() ? "region of interest" : "series",
                     " has ", image.grid.size[2]));
  }
  return input;
}

absl::StatusOr<Volume<float>> ContourStage(const JobSpec& spec,
                                           const WantedOutputs& wants,
                                           SourceSlices& input,
                                           JobReport& report,
                                           const ComputeContext& context) {
  StageClock clock(report, context, "contour");
  Volume<float> slice_maps;
  ContourOptions options;
  options.lower = spec.lower_threshold;
  options.upper = spec.upper_threshold;
  options.band_radius_mm = spec.band_radius_mm;
  if (spec.slab_deconvolution) {
    // Contour the slab deconvolution of the slices instead (JobSpec).
    INTERSLICE_ASSIGN_OR_RETURN(
        Volume<float> estimates,
        DeconvolveSlabsForPlan(input.image, input.positions,
                               input.source.slice_thickness_mm, spec, report,
                               context));
    INTERSLICE_ASSIGN_OR_RETURN(
        slice_maps, ComputeSliceDistanceMaps(estimates, options, context));
  } else {
    INTERSLICE_ASSIGN_OR_RETURN(
        slice_maps, ComputeSliceDistanceMaps(input.image, options, context));
  }
  // Release the grey values early unless an intensity series or the
  // previews need them.
  if (!wants.intensity && !wants.previews) input.image = Volume<float>();
  return slice_maps;
}

absl::StatusOr<StackedField> StackStage(const JobSpec& spec,
                                        const std::vector<double>& positions,
                                        Volume<float> slice_maps,
                                        JobReport& report,
                                        const ComputeContext& context) {
  StageClock clock(report, context, "stack");
  StackedField stacked;
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
  return stacked;
}

// The intensity morph (written in the write stage) needs only the source
// slices and the output grid, so it runs from the stack stage on beside the
// solve, mesh and preview stages, which leave a core idle much of the time
// (the Encapsulated STL's simplification and the mesh writer are serial): on
// the CT phantom with the shipped rule, the job takes ~25% less time. It
// runs on its own thread with the job's thread count (so the job briefly
// uses one thread more than ComputeContext::threads), reports no progress
// of its own (Report is never called concurrently; the write stage says
// "intensity" when it takes the result) and polls the same cancellation.
std::future<absl::StatusOr<MorphedIntensity>> StartIntensityMorph(
    const Volume<float>& image, const std::vector<double>& positions,
    const Grid& grid, std::optional<float> padding,
    const ComputeContext& context) {
  ComputeContext morph_context = context;
  morph_context.progress = nullptr;
  return std::async(
      std::launch::async, [&image, &positions, grid, padding,
                           morph_context = std::move(morph_context)] {
        return MorphIntensity(image, positions, grid, padding, nullptr,
                              IntensityMorphOptions(), morph_context);
      });
}

absl::Status SolveStage(const JobSpec& spec, StackedField& stacked,
                        JobReport& report, const ComputeContext& context) {
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
                                    MorphOptions().component_margin_mm, context)
            .status());
  }
  return absl::OkStatus();
}

absl::StatusOr<Mesh> MeshStage(const JobSpec& spec, const Volume<float>& field,
                               JobReport& report,
                               const ComputeContext& context) {
  StageClock clock(report, context, "mesh");
  SurfaceOptions options;
  options.adaptivity = spec.mesh_adaptivity;
  INTERSLICE_ASSIGN_OR_RETURN(Mesh mesh,
                              ExtractSurface(field, options, context));
  report.mesh_vertices = static_cast<int64_t>(mesh.vertices.size());
  report.mesh_triangles = static_cast<int64_t>(mesh.triangles.size());
  return mesh;
}

// The Encapsulated STL's mesh is made beside the preview and write stages
// (meshoptimizer's simplification is serial: ~2 s of the shipped rule's
// job on the CT phantom, a core otherwise idle), on its own thread with a
// context that reports no progress (Report is never concurrent); its
// stage time is recorded when the write stage takes it. It reads `mesh`
// and `field`, which nothing changes meanwhile, and writes only its own
// report fields.
void StartDicomMesh(const JobSpec& spec, const DicomSeries& source,
                    const Mesh& mesh, const Volume<float>& field,
                    JobReport& report, PendingDicomMesh& dicom_mesh,
                    const ComputeContext& context) {
  ComputeContext mesh_context = context;
  mesh_context.progress = nullptr;
  const int64_t source_instances = static_cast<int64_t>(source.slices.size());
  dicom_mesh.done = std::async(
      std::launch::async,
      [&spec, &mesh, &field, &report, &dicom_mesh, source_instances,
       mesh_context = std::move(mesh_context)]() -> absl::Status {
        const auto started = std::chrono::steady_clock::now();
        // A stage only when it does something: another mesh, or its
        // deviation (the default, 0 for both, stores the surface as
        // extracted). First the adaptivity (another extraction), then the
        // size cap (quadric edge collapse of that mesh).
        const int64_t max_triangles = MaxEncapsulatedStlTriangles(
            spec.dicom_mesh_max_mb, source_instances);
        const bool reextract =
            spec.dicom_mesh_adaptivity != spec.mesh_adaptivity;
        const bool may_cap =
            max_triangles > 0 &&
            (reextract ||
             static_cast<int64_t>(mesh.triangles.size()) > max_triangles);
        const bool staged =
            reextract || may_cap || spec.dicom_mesh_adaptivity > 0;
        absl::Status status =
            MakeDicomMesh(spec, max_triangles, reextract, mesh, field, report,
                          dicom_mesh, mesh_context);
        if (staged) {
          dicom_mesh.seconds = std::chrono::duration<double>(
                                   std::chrono::steady_clock::now() - started)
                                   .count();
        }
        return status;
      });
}

absl::StatusOr<std::optional<PreviewSet>> PreviewStage(
    const JobSpec& spec, const WantedOutputs& wants, SourceSlices& input,
    const Volume<float>& field, JobReport& report,
    const ComputeContext& context) {
  StageClock clock(report, context, "preview");
  std::optional<PreviewSet> previews;
  absl::StatusOr<PreviewSet> rendered = RenderJobPreviews(
      spec, input.source, input.image, input.positions, field, report, context);
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  if (rendered.ok()) {
    report.preview_notes = rendered->notes;
    previews = *std::move(rendered);
  } else {
    report.preview_notes.push_back(
        absl::StrCat("previews skipped: ", rendered.status().message()));
  }
  if (!wants.intensity) input.image = Volume<float>();
  return previews;
}

}  // namespace interslice::pipeline_internal
