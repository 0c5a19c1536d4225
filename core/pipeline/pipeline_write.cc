// The write stage of RunJob (pipeline_internal.h): the volume and mesh
// files, the DICOM objects and the previews, written in parallel, then the
// Encapsulated STL.
#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <optional>
#include <string>
#include <system_error>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/encapsulated_stl.h"
#include "core/dicom_out/enhanced_series.h"
#include "core/dicom_out/preview_series.h"
#include "core/pipeline/pipeline_internal.h"
#include "core/volume_io/volume_io.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice::pipeline_internal {
namespace {

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

// The solver in words for a series description: what a reader needs to
// know is whether the shape was smoothed between the slices (the conjugate
// gradient and the exact solver minimise the same energy, paper section 3).
std::string_view SolverMethodWords(SolverMethod method) {
  switch (method) {
    case SolverMethod::kLinear:
      return "linear";
    case SolverMethod::kConjugateGradient:
    case SolverMethod::kDirect:
      return "smooth";
    case SolverMethod::kMorph:
      return "registered";
  }
  return "";
}

// What tells this job's segmentation, distance map, mesh and previews apart
// from those of other parameters in the study's series descriptions
// (dicom_writer.h, "Identity"): the threshold(s) (modality units; HU for
// CT), the output slice spacing and the solver in words, e.g. ">=300 HU,
// 0.5 mm, smooth"; at most 40 characters for every finite threshold
// (%.6g).
std::string ParameterSummary(const JobSpec& spec, const std::string& modality,
                             const Grid& output_grid) {
  const std::string unit = modality == "CT" ? " HU" : "";
  const std::string thresholds =
      spec.upper_threshold.has_value()
          ? absl::StrFormat("%.6g..%.6g", spec.lower_threshold,
                            *spec.upper_threshold)
          : absl::StrFormat(">=%.6g", spec.lower_threshold);
  return absl::StrFormat("%s%s, %.3g mm, %s", thresholds, unit,
                         output_grid.spacing[2],
                         SolverMethodWords(spec.solver.method));
}

// The same for the intensity series, which the thresholds and the solver do
// not change: the spacing and how the grey values between the source slices
// were made, e.g. "0.5 mm, motion-compensated".
std::string IntensitySummary(const JobSpec& spec, const Grid& output_grid) {
  return absl::StrFormat(
      "%.3g mm, %s", output_grid.spacing[2],
      spec.intensity_method == "morph" ? "motion-compensated" : "linear");
}

// The voxel box, however it was given (a box in mm that maps to the same
// voxels makes the same objects), and the output grid, appended to a
// derivation key.
void AppendGridKey(const std::optional<VoxelBox>& roi, const Grid& output_grid,
                   std::string& key) {
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
  // Slab deconvolution changes the distance map, the SEG and the mesh
  // (pipeline.h): two jobs that differ only in it once got the same UIDs
  // for different objects, and a PACS that keeps the first instance of a
  // UID (Orthanc's default) showed the other job's results. Absent when off,
  // so that the UIDs of the jobs without it stay as they were.
  if (spec.slab_deconvolution) absl::StrAppend(&key, " slab-deconvolution=1");
  // Absent for the default segment, so that the UIDs of jobs that name
  // none stay as they were.
  if (!spec.segment_label.empty()) {
    absl::StrAppend(&key, " segment-label=", spec.segment_label);
  }
  if (!spec.segment_code.empty()) {
    absl::StrAppend(&key, " segment-code=", spec.segment_code);
  }
  AppendGridKey(roi, output_grid, key);
  return key;
}

// What shapes the intensity series alone, in a canonical text that names
// its UIDs and picks its series numbers' slot (DicomWriteOptions::
// intensity_derivation_key): everything of DerivationKey but what changes
// only the shape objects (thresholds, band, solver, slab deconvolution,
// segment label and code), plus an explicit series number base (the series
// carries its number). Jobs on one series that differ only in those share
// one intensity series in the study instead of storing identical copies.
// A list of its own, not derived from DerivationKey's: a new JobSpec field
// that can change a grey value or the grid must be added here as well as
// there, or two different intensity series would get one set of UIDs
// (PipelineTest.ParametersThatChangeAnObjectChangeItsUidsAndOnlyItsOwn
// checks the fields known today).
std::string IntensityDerivationKey(const JobSpec& spec,
                                   const std::optional<VoxelBox>& roi,
                                   const Grid& output_grid) {
  std::string key =
      absl::StrFormat("intensity-series v1 method=%s strict=%d volume=%s",
                      spec.intensity_method, spec.strict_spacing ? 1 : 0,
                      spec.multiframe_volume);
  if (spec.series_number_base > 0) {
    absl::StrAppend(&key, " number-base=", spec.series_number_base);
  }
  AppendGridKey(roi, output_grid, key);
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

absl::Status CreateOutputFolder(const std::string& output_dir) {
  std::error_code ec;
  std::filesystem::create_directories(output_dir, ec);
  if (ec || !std::filesystem::is_directory(output_dir)) {
    return absl::FailedPreconditionError(
        absl::StrCat("cannot create output folder ", output_dir, ": ",
                     ec ? ec.message() : "not a folder"));
  }
  return absl::OkStatus();
}

// The object of the field: 1 where it is >= 0.
Volume<uint8_t> ThresholdMask(const Volume<float>& field) {
  Volume<uint8_t> mask;
  mask.grid = field.grid;
  mask.data.resize(field.data.size());
  std::transform(field.data.begin(), field.data.end(), mask.data.begin(),
                 [](float v) -> uint8_t { return v >= 0 ? 1 : 0; });
  return mask;
}

DicomWriteOptions JobDicomWriteOptions(const JobSpec& spec,
                                       const JobReport& report,
                                       const DicomSeries& source,
                                       const Grid& output_grid) {
  DicomWriteOptions dicom_options;
  dicom_options.uid_root = spec.uid_root;
  dicom_options.random_uids = spec.random_uids;
  dicom_options.series_number_base = spec.series_number_base;
  dicom_options.derivation_key = DerivationKey(spec, report.roi, output_grid);
  dicom_options.parameter_set = dicom_options.derivation_key;
  // Random UIDs are random for every object: nothing to share.
  if (!spec.random_uids) {
    dicom_options.intensity_derivation_key =
        IntensityDerivationKey(spec, report.roi, output_grid);
  }
  dicom_options.parameter_summary =
      ParameterSummary(spec, source.modality, output_grid);
  dicom_options.intensity_summary = IntensitySummary(spec, output_grid);
  // The Encapsulated STL's own simplification changes that object alone:
  // its UIDs, not the other objects', name it (empty for the defaults, whose
  // UIDs stay as they were).
  if (spec.dicom_mesh_adaptivity != kDefaultDicomMeshAdaptivity ||
      spec.dicom_mesh_max_mb != kDefaultDicomMeshMaxMb) {
    dicom_options.surface_derivation_key =
        absl::StrFormat("adaptivity=%.9g max-mb=%.9g",
                        spec.dicom_mesh_adaptivity, spec.dicom_mesh_max_mb);
  }
  if (spec.dicom_compression == "rle") {
    dicom_options.intensity_encoding =
        DicomWriteOptions::PixelEncoding::kRleLossless;
  }
  return dicom_options;
}

// The identities of the derived DICOM objects, in the layout asked for.
absl::StatusOr<DerivedObjects> PlanJobDerivedObjects(
    const JobSpec& spec, const DicomSeries& source, const Grid& output_grid,
    const DicomWriteOptions& dicom_options) {
  INTERSLICE_ASSIGN_OR_RETURN(
      DerivedObjects objects,
      PlanDerivedObjects(source, output_grid.size[2], dicom_options));
  if (spec.dicom_layout == "enhanced") {
    // One Enhanced CT / MR instance instead of an image per slice; the SEG,
    // distance map, previews and STL reference it.
    INTERSLICE_ASSIGN_OR_RETURN(
        objects.intensity,
        PlanEnhancedIntensity(source, objects.intensity, dicom_options));
  }
  return objects;
}

// The intensity series' values on the output grid: the morph's (taken from
// its thread, with its statistics into the report) or the linear
// resampling of the source slices.
absl::StatusOr<Volume<float>> IntensityOnOutputGrid(
    const JobSpec& spec, const SourceSlices& input, const Grid& output_grid,
    PendingIntensity& pending, DicomWriteOptions& dicom_options,
    JobReport& report, const ComputeContext& context) {
  const std::optional<float> padding = pending.padding;
  report.intensity_method = spec.intensity_method;
  if (spec.intensity_method == "morph") {
    dicom_options.intensity_interpolation =
        DicomWriteOptions::IntensityInterpolation::kMorph;
    context.Report({.stage = "intensity", .fraction = 0});
    INTERSLICE_ASSIGN_OR_RETURN(MorphedIntensity morphed,
                                pending.morphing.get());
    context.Report({.stage = "intensity", .fraction = 1});
    const IntensityMorphStatistics& stats = morphed.statistics;
    report.intensity_gaps = stats.gaps;
    report.intensity_gaps_not_registered = stats.gaps_not_registered;
    report.intensity_fallback_fraction = stats.fallback_fraction;
    report.intensity_mean_displacement_mm = stats.mean_displacement_mm;
    report.intensity_max_displacement_mm = stats.max_displacement_mm;
    return std::move(morphed.values);
  }
  return ResampleSourceSlices(input.image, input.positions, output_grid,
                              padding, context);
}

// Each task writes one artifact and records its kind, path and status.
struct WriteTask {
  std::string kind;
  std::filesystem::path path;
  std::function<absl::Status()> write;
  absl::Status status;
  // A preview: its failure is a note in the report, not the job's.
  bool optional = false;
};

// What the write tasks read; everything outlives them.
struct WriteInputs {
  const JobSpec& spec;
  const WantedOutputs& wants;
  const std::filesystem::path& dir;
  const DicomSeries& source;
  const Volume<float>& field;
  const Volume<uint8_t>& mask;
  const Mesh& mesh;
  // The intensity series' values: freed by the task that writes them.
  Volume<float>& intensity;
  const DerivedObjects& objects;
  const DicomWriteOptions& dicom_options;
  const ComputeContext& context;
};

// The distance and mask volume files of every volume format.
void AddVolumeFileTasks(const WriteInputs& in, std::vector<WriteTask>& tasks) {
  // JobSpec::omit_files_dicom_objects_carry: a file whose content one of
  // this job's DICOM objects carries is not written.
  const bool omit = in.spec.omit_files_dicom_objects_carry;
  for (const std::string& format : in.spec.volume_formats) {
    const std::string ext = format == "nii"    ? ".nii.gz"
                            : format == "nrrd" ? ".nrrd"
                                               : ".nii";
    const auto distance_path = in.dir / ("distance" + ext);
    const auto mask_path = in.dir / ("mask" + ext);
    if (!(omit && in.wants.distance_map)) {
      tasks.push_back({"distance", distance_path, [&in, distance_path] {
                         return WriteVolume(in.field, distance_path.string(),
                                            in.context);
                       }});
    }
    if (!(omit && in.wants.seg)) {
      tasks.push_back({"mask", mask_path, [&in, mask_path] {
                         return WriteVolume(in.mask, mask_path.string(),
                                            in.context);
                       }});
    }
  }
}

// The mesh file of every mesh format and the note on their coordinates.
// Returns whether surface.stl is written.
bool AddMeshFileTasks(const WriteInputs& in, std::vector<WriteTask>& tasks) {
  const bool omit = in.spec.omit_files_dicom_objects_carry;
  bool surface_stl_written = false;
  bool mesh_file_written = false;
  for (const std::string& format : in.spec.mesh_formats) {
    if (omit && in.wants.dicom_mesh && format == "stl") continue;
    surface_stl_written |= format == "stl";
    mesh_file_written = true;
    const auto path = in.dir / ("surface." + format);
    tasks.push_back({"surface", path, [&in, path] {
                       return WriteMesh(in.mesh, path.string());
                     }});
  }
  // The note explains the mesh files' coordinates.
  if (mesh_file_written) {
    const auto path = in.dir / "surface-coordinates.txt";
    tasks.push_back({"surface-coordinates", path, [&in, path] {
                       return WriteTextFile(path.string(),
                                            MeshConventionNote(in.source));
                     }});
  }
  return surface_stl_written;
}

// The intensity series, the distance map and the SEG.
void AddDicomObjectTasks(const WriteInputs& in, std::vector<WriteTask>& tasks) {
  if (in.wants.intensity) {
    const auto path = in.dir / "series-intensity";
    // The artifact is the folder either way: the server names its files
    // "series-intensity/IM00001.dcm" ... or "series-intensity/enhanced.dcm"
    // (at most one folder level).
    const bool enhanced = in.spec.dicom_layout == "enhanced";
    tasks.push_back(
        {"series-intensity", path, [&in, path, enhanced] {
           absl::Status written =
               enhanced ? WriteEnhancedIntensityFolder(in.source, in.intensity,
                                                       in.objects.intensity,
                                                       in.dicom_options, path)
                        : WriteIntensityFolder(in.source, in.intensity,
                                               in.objects.intensity,
                                               in.dicom_options, path);
           // Only this task reads the resampled volume: free
           // it (one output volume) while the other outputs
           // are still being written.
           in.intensity = Volume<float>();
           return written;
         }});
  }
  if (in.wants.distance_map) {
    const auto path = in.dir / "distance.dcm";
    tasks.push_back({"distance-map", path, [&in, path] {
                       return WriteDistanceMap(in.source, in.field,
                                               in.objects.distance_map,
                                               in.objects.intensity,
                                               in.dicom_options, path.string());
                     }});
  }
  if (in.wants.seg) {
    const auto path = in.dir / "seg.dcm";
    tasks.push_back({"seg", path, [&in, path]() -> absl::Status {
                       const JobSpec& spec = in.spec;
                       std::optional<CodedConcept> code;
                       if (!spec.segment_code.empty()) {
                         INTERSLICE_ASSIGN_OR_RETURN(
                             code, ParseCodedConcept(spec.segment_code));
                       }
                       INTERSLICE_ASSIGN_OR_RETURN(
                           const SegmentDescription segment,
                           DescribeThresholdSegment(
                               in.source, spec.lower_threshold,
                               spec.upper_threshold, spec.segment_label, code));
                       return WriteSegmentation(
                           in.source, in.mask, in.objects.segmentation,
                           in.objects.intensity, segment, in.dicom_options,
                           path.string());
                     }});
  }
}

// The previews as PNG files and as a Secondary Capture series (`pictures`:
// what the latter shows; it must outlive the tasks).
void AddPreviewTasks(const WriteInputs& in,
                     const std::optional<PreviewSet>& previews,
                     std::vector<RgbPicture>& pictures,
                     std::vector<WriteTask>& tasks) {
  if (previews.has_value() && Contains(in.spec.preview_formats, "png")) {
    const auto path = in.dir / "previews";
    tasks.push_back(
        {"previews",
         path,
         [&previews, path] {
           return WritePreviewPngs(previews->images, path.string()).status();
         },
         {},
         /*optional=*/true});
  }
  if (previews.has_value() && Contains(in.spec.preview_formats, "dicom")) {
    pictures = Pictures(previews->images);
    const auto path = in.dir / "previews-dicom";
    tasks.push_back({"previews-dicom",
                     path,
                     [&in, &pictures, path]() -> absl::Status {
                       std::vector<std::string> names;
                       for (const RgbPicture& p : pictures)
                         names.push_back(p.name);
                       // Derived from the intensity series when the job writes
                       // it.
                       const DerivedObjectIdentity* referenced =
                           in.wants.intensity ? &in.objects.intensity : nullptr;
                       INTERSLICE_ASSIGN_OR_RETURN(
                           const DerivedObjectIdentity identity,
                           PlanPreviewSeries(in.source, names, in.dicom_options,
                                             referenced));
                       return WritePreviewSeries(
                                  in.source, in.field.grid, pictures, identity,
                                  referenced, in.dicom_options, path.string())
                           .status();
                     },
                     {},
                     /*optional=*/true});
  }
}

// Runs every task on the context's threads, then records each artifact in
// the report (a failed preview as a note); the first failed task in task
// order fails the job.
absl::Status RunWriteTasks(std::vector<WriteTask>& tasks, JobReport& report,
                           const ComputeContext& context) {
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(size_t{0}, tasks.size(), size_t{1},
                      [&](size_t n) { tasks[n].status = tasks[n].write(); });
  });
  for (const WriteTask& task : tasks) {
    if (task.optional && !task.status.ok()) {
      report.preview_notes.push_back(absl::StrCat(
          "previews not written (", task.kind, "): ", task.status.message()));
      continue;
    }
    INTERSLICE_RETURN_IF_ERROR(task.status);
    report.artifacts.push_back(
        {task.kind, task.path.string(), PathSize(task.path)});
  }
  return absl::OkStatus();
}

// With DICOM outputs, the STL mesh also goes into the study as an
// Encapsulated STL object; it embeds surface.stl, so it comes after.
absl::Status WriteEncapsulatedStlArtifact(const WriteInputs& in,
                                          PendingDicomMesh& dicom_mesh,
                                          bool surface_stl_written,
                                          JobReport& report) {
  INTERSLICE_RETURN_IF_ERROR(dicom_mesh.done.get());
  if (dicom_mesh.seconds >= 0) {
    report.stages.push_back({"dicom-mesh", dicom_mesh.seconds});
  }
  const auto path = in.dir / kEncapsulatedStlFileName;
  // Its own mesh, or the surface when surface.stl was not written, goes
  // through a temporary STL file (the writer embeds a file as it is),
  // deleted once embedded.
  std::filesystem::path stl = in.dir / "surface.stl";
  const bool temporary = dicom_mesh.mesh != &in.mesh || !surface_stl_written;
  if (temporary) {
    stl = in.dir / ".surface-dicom.stl";
    INTERSLICE_RETURN_IF_ERROR(WriteStl(*dicom_mesh.mesh, stl.string()));
  }
  const absl::Status written =
      WriteEncapsulatedStl(in.source, stl.string(), in.objects.surface_stl,
                           in.dicom_options, path.string());
  if (temporary) {
    std::error_code ignored;
    std::filesystem::remove(stl, ignored);
  }
  INTERSLICE_RETURN_IF_ERROR(written);
  report.artifacts.push_back(
      {"surface-stl-dicom", path.string(), PathSize(path)});
  return absl::OkStatus();
}

}  // namespace

// write: every artifact is independent, so they are written in parallel
// (gzip of the float volumes dominates this stage).
absl::Status WriteStage(const JobSpec& spec, const WantedOutputs& wants,
                        SourceSlices& input, const Volume<float>& field,
                        const Mesh& mesh,
                        const std::optional<PreviewSet>& previews,
                        PendingIntensity& intensity,
                        PendingDicomMesh& dicom_mesh, JobReport& report,
                        const ComputeContext& context) {
  StageClock clock(report, context, "write");
  INTERSLICE_RETURN_IF_ERROR(CreateOutputFolder(spec.output_dir));
  const std::filesystem::path dir(spec.output_dir);
  Volume<uint8_t> mask;
  if (!spec.volume_formats.empty() || wants.seg) mask = ThresholdMask(field);
  DicomWriteOptions dicom_options =
      JobDicomWriteOptions(spec, report, input.source, field.grid);
  DerivedObjects objects;
  Volume<float> intensity_values;
  if (wants.intensity) {
    INTERSLICE_ASSIGN_OR_RETURN(
        objects,
        PlanJobDerivedObjects(spec, input.source, field.grid, dicom_options));
    INTERSLICE_ASSIGN_OR_RETURN(
        intensity_values,
        IntensityOnOutputGrid(spec, input, field.grid, intensity, dicom_options,
                              report, context));
    input.image = Volume<float>();
  }

  const WriteInputs in{spec,    wants,         dir,    input.source,
                       field,   mask,          mesh,   intensity_values,
                       objects, dicom_options, context};
  std::vector<WriteTask> tasks;
  AddVolumeFileTasks(in, tasks);
  const bool surface_stl_written = AddMeshFileTasks(in, tasks);
  AddDicomObjectTasks(in, tasks);
  std::vector<RgbPicture> pictures;
  AddPreviewTasks(in, previews, pictures, tasks);
  INTERSLICE_RETURN_IF_ERROR(RunWriteTasks(tasks, report, context));
  if (wants.dicom_mesh) {
    INTERSLICE_RETURN_IF_ERROR(WriteEncapsulatedStlArtifact(
        in, dicom_mesh, surface_stl_written, report));
  }
  return absl::OkStatus();
}

}  // namespace interslice::pipeline_internal
