#include "core/labels/fill_job.h"

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <optional>
#include <system_error>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/label_segmentation.h"
#include "core/dicom_out/preview_series.h"
#include "core/dicom_out/rtstruct.h"
#include "core/labels/label_contours.h"
#include "core/labels/label_map_io.h"
#include "core/labels/segment_names.h"
#include "core/labels/segmentation_reader.h"
#include "core/morph/intensity_morph.h"
#include "core/preview/preview.h"
#include "core/surface/surface.h"
#include "core/volume_io/volume_io.h"
#include "nlohmann/json.hpp"

namespace interslice {
namespace {

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
      .count();
}

int64_t FileSize(const std::string& path) {
  std::error_code ec;
  const auto size = std::filesystem::file_size(path, ec);
  return ec ? 0 : static_cast<int64_t>(size);
}

int64_t FolderSize(const std::string& path) {
  int64_t total = 0;
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator(path, ec)) {
    total += FileSize(entry.path().string());
  }
  return total;
}

bool Contains(const std::vector<std::string>& list, const std::string& item) {
  return std::find(list.begin(), list.end(), item) != list.end();
}

// Prefixes a status message with what was being done.
absl::Status Annotate(const absl::Status& status, const std::string& what) {
  return absl::Status(status.code(),
                      absl::StrCat(what, ": ", status.message()));
}

// A canonical text of what determines the filled labels (the derivation
// key of the DICOM outputs' UIDs): the fill's parameters and a hash of the
// input labels (FNV-1a, 64 bit).
std::string DerivationKey(const FillJobSpec& spec, const LabelVolume& input,
                          int factor) {
  uint64_t hash = 1469598103934665603ull;
  for (uint16_t v : input.data) {
    hash = (hash ^ (v & 0xff)) * 1099511628211ull;
    hash = (hash ^ (v >> 8)) * 1099511628211ull;
  }
  std::string key = absl::StrFormat(
      "interslice fill v1\nlabels %016x\nmethod %s %s iterations %d "
      "tolerance %g\nfactor %d band %g margin %d\nfill",
      hash, FillMethodName(spec.fill.method),
      SolverMethodName(spec.fill.solver.method),
      spec.fill.solver.max_iterations, spec.fill.solver.tolerance, factor,
      spec.fill.band_radius_mm, spec.fill.margin_pixels);
  for (int l : spec.fill.labels) absl::StrAppend(&key, " ", l);
  if (spec.fill.key_slices.has_value()) {
    absl::StrAppend(&key, "\nkeys");
    for (int64_t k : *spec.fill.key_slices) absl::StrAppend(&key, " ", k);
  }
  return key;
}

// seg.dcm, rtstruct.dcm and (on a finer grid) the series-intensity/ they
// reference; see fill_job.h.
absl::Status WriteDicomOutputs(const FillJobSpec& spec,
                               const DicomSeries& source,
                               const SegmentationInput& input,
                               const FillResult& result, bool write_rtstruct,
                               bool derive_series,
                               const std::vector<RgbPicture>& previews,
                               const ComputeContext& context,
                               FillJobReport& report) {
  const std::filesystem::path dir(spec.output_dir);
  const Grid& grid = result.labels.grid;
  DicomWriteOptions options;
  options.uid_root = spec.uid_root;
  options.random_uids = spec.random_uids;
  options.derivation_key = DerivationKey(spec, input.labels, result.factor);
  // The grey values of a derived series depend on how they are interpolated
  // (a linear series keeps the UIDs it always had).
  if (derive_series && spec.intensity_method != "linear") {
    absl::StrAppend(&options.derivation_key, "\nintensity ",
                    spec.intensity_method);
  }
  options.derivation_description =
      "interslice fill between key slices (Csebfalvi et al. 2001)";
  // The series descriptions (dicom_writer.h, "Identity"): what the SEG is
  // and, for a derived intensity series, its spacing and grey values.
  options.parameter_summary = "filled between drawn slices";
  options.intensity_summary = absl::StrFormat(
      "%.3g mm, %s", grid.spacing[2],
      spec.intensity_method == "morph" ? "motion-compensated" : "linear");
  INTERSLICE_ASSIGN_OR_RETURN(
      const DerivedObjects objects,
      PlanDerivedObjects(source, grid.size[2], options));
  DerivedObjectIdentity referenced;
  const bool seg_or_rtstruct = spec.write_seg || write_rtstruct;
  if (!derive_series) {
    INTERSLICE_ASSIGN_OR_RETURN(referenced, ReferencedImagesOfSource(source));
  } else if (seg_or_rtstruct) {
    // A finer grid has slices the reference series has no image for (and a
    // multi-frame or anonymised reference cannot be referenced image by
    // image): the objects lie on a derived intensity series, as run's do.
    std::vector<double> positions;
    for (const DicomSliceInfo& slice : source.slices) {
      positions.push_back(slice.position_along_normal);
    }
    INTERSLICE_ASSIGN_OR_RETURN(std::optional<float> padding,
                                SourcePixelPadding(source));
    // The grey values as `run` makes them (pipeline.h, intensity_method).
    Volume<float> intensity;
    if (spec.intensity_method == "morph") {
      options.intensity_interpolation =
          DicomWriteOptions::IntensityInterpolation::kMorph;
      INTERSLICE_ASSIGN_OR_RETURN(
          MorphedIntensity morphed,
          MorphIntensity(source.image, positions, grid, padding, nullptr,
                         IntensityMorphOptions(), context));
      intensity = std::move(morphed.values);
    } else {
      INTERSLICE_ASSIGN_OR_RETURN(
          intensity, ResampleSourceSlices(source.image, positions, grid,
                                          padding, context));
    }
    const std::string folder = (dir / "series-intensity").string();
    INTERSLICE_ASSIGN_OR_RETURN(
        std::vector<std::string> written,
        WriteIntensitySeries(source, intensity, objects.intensity, options,
                             folder));
    int64_t bytes = 0;
    for (const std::string& f : written) bytes += FileSize(f);
    report.artifacts.push_back({"series-intensity", 0, folder, bytes});
    referenced = objects.intensity;
  }
  if (spec.write_seg) {
    const std::string path = (dir / "seg.dcm").string();
    INTERSLICE_RETURN_IF_ERROR(Annotate(
        WriteLabelSegmentation(source, result.labels, input.segments,
                               objects.segmentation, referenced, options, path),
        "writing seg.dcm"));
    report.artifacts.push_back({"seg", 0, path, FileSize(path)});
  }
  if (write_rtstruct) {
    INTERSLICE_ASSIGN_OR_RETURN(
        LabelContours contours,
        ExtractLabelContours(result.labels, {}, context));
    std::vector<RoiContours> rois;
    for (auto& [label, slices] : contours.polygons) {
      RoiContours roi;
      roi.roi = DefaultLabelSegment(label);
      for (const LabelSegment& s : input.segments) {
        if (s.number != label) continue;
        if (!s.label.empty()) roi.roi.label = s.label;
        if (s.rgb.has_value() || s.cielab.has_value()) {
          roi.roi.rgb = s.rgb;
          roi.roi.cielab = s.cielab;
        }
      }
      for (auto& [k, polygons] : slices) roi.slices[k] = std::move(polygons);
      rois.push_back(std::move(roi));
    }
    // Its own UIDs: the SEG's plan under a key that names the RTSTRUCT.
    DicomWriteOptions rt_options = options;
    rt_options.derivation_key += "\nrtstruct";
    INTERSLICE_ASSIGN_OR_RETURN(
        const DerivedObjects rt_objects,
        PlanDerivedObjects(source, grid.size[2], rt_options));
    DerivedObjectIdentity identity = rt_objects.segmentation;
    identity.study_instance_uid = objects.segmentation.study_instance_uid;
    identity.frame_of_reference_uid =
        objects.segmentation.frame_of_reference_uid;
    identity.series_number = objects.segmentation.series_number + 2;
    INTERSLICE_ASSIGN_OR_RETURN(
        identity.series_description,
        DescribeDerivedSeries(source, "Structure set",
                              options.parameter_summary));
    const std::string path = (dir / "rtstruct.dcm").string();
    INTERSLICE_RETURN_IF_ERROR(
        Annotate(WriteRtStructureSet(source, grid, rois, identity, referenced,
                                     options, path),
                 "writing rtstruct.dcm"));
    report.artifacts.push_back({"rtstruct", 0, path, FileSize(path)});
  }
  if (!previews.empty()) {
    // Derived from the images the labels lie on: the reference's own, or
    // the intensity series written beside them; on a finer grid without a
    // SEG or RTSTRUCT, from the reference series as a whole.
    const DerivedObjectIdentity* on =
        !derive_series || seg_or_rtstruct ? &referenced : nullptr;
    std::vector<std::string> names;
    for (const RgbPicture& p : previews) names.push_back(p.name);
    const std::string folder = (dir / "previews-dicom").string();
    absl::StatusOr<DerivedObjectIdentity> identity =
        PlanPreviewSeries(source, names, options, &objects.segmentation);
    absl::Status written = identity.status();
    if (identity.ok()) {
      written = WritePreviewSeries(source, grid, previews, *identity, on,
                                   options, folder)
                    .status();
    }
    if (written.ok()) {
      report.artifacts.push_back(
          {"previews-dicom", 0, folder, FolderSize(folder)});
    } else {
      report.preview_notes.push_back(absl::StrCat(
          "previews not written (previews-dicom): ", written.message()));
    }
  }
  return absl::OkStatus();
}

// The previews of the fill: the reference's grey values on the output grid,
// each filled label outlined in its colour, the key slices ticked, and the
// labels' fields as surfaces (FillJobSpec::preview_formats).
absl::StatusOr<PreviewSet> RenderFillPreviews(const FillJobSpec& spec,
                                              const DicomSeries& source,
                                              const SegmentationInput& input,
                                              const FillResult& result,
                                              const ComputeContext& context) {
  const Grid& grid = result.labels.grid;
  INTERSLICE_ASSIGN_OR_RETURN(const std::optional<float> padding,
                              SourcePixelPadding(source));
  std::vector<double> positions;
  for (const DicomSliceInfo& slice : source.slices) {
    positions.push_back(slice.position_along_normal);
  }
  PreviewScene scene;
  scene.grid = grid;
  const CancellationToken* cancel = context.cancel;
  const Volume<float>& image = source.image;
  scene.intensity = [&image, positions, &grid, padding,
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
  scene.labels = &result.labels;
  std::vector<int64_t> keys;
  std::string methods;
  for (const LabelFillInfo& info : result.per_label) {
    LabelSegment segment = DefaultLabelSegment(info.label);
    for (const LabelSegment& s : input.segments) {
      if (s.number == info.label) segment = s;
    }
    // Segment names are typed by people: only the number is drawn.
    scene.objects.push_back({info.label, SegmentRgb(segment),
                             info.field.data.empty() ? nullptr : &info.field,
                             absl::StrCat("label ", info.label)});
    keys.insert(keys.end(), info.key_slices.begin(), info.key_slices.end());
    absl::StrAppend(&methods, methods.empty() ? "" : ", ", info.label, " ",
                    info.method);
  }
  std::sort(keys.begin(), keys.end());
  keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
  for (int64_t k : keys) {
    scene.marked_slices.push_back(static_cast<double>(k * result.factor));
  }
  scene.marked_slices_name = "key slices";
  scene.legend.push_back(absl::StrFormat(
      "interslice fill: labels FILLED between %d key slices (not drawn)",
      keys.size()));
  const std::string method =
      spec.fill.method == FillMethod::kAuto
          ? (result.per_label.size() <= 6
                 ? absl::StrCat("auto (label ", methods, ")")
                 : std::string("auto (chosen per label: see the report)"))
          : std::string(SolverMethodName(spec.fill.solver.method));
  scene.legend.push_back(
      absl::StrFormat("method %s, spacing %.4g x %.4g x %.4g mm", method,
                      grid.spacing[0], grid.spacing[1], grid.spacing[2]));
  return RenderPreviews(scene, PreviewOptions(), context);
}

}  // namespace

absl::Status ValidateFillJobSpec(const FillJobSpec& spec) {
  if (spec.segmentation.empty()) {
    return absl::InvalidArgumentError("fill: no segmentation given");
  }
  if (spec.reference.empty()) {
    return absl::InvalidArgumentError(
        "fill: no reference series given (--reference DICOM_DIR)");
  }
  if (spec.output_dir.empty()) {
    return absl::InvalidArgumentError("fill: no output folder given (--out)");
  }
  for (const std::string& f : spec.volume_formats) {
    if (f != "nii" && f != "nrrd") {
      return absl::InvalidArgumentError(absl::StrCat(
          "fill: unknown volume format '", f, "' (expected nii or nrrd)"));
    }
  }
  for (const std::string& f : spec.mesh_formats) {
    if (f != "stl" && f != "ply" && f != "obj") {
      return absl::InvalidArgumentError(absl::StrCat(
          "fill: unknown mesh format '", f, "' (expected stl, ply or obj)"));
    }
  }
  if (spec.intensity_method != "linear" && spec.intensity_method != "morph") {
    return absl::InvalidArgumentError(
        absl::StrCat("fill: unknown intensity method '", spec.intensity_method,
                     "' (choose from linear, morph)"));
  }
  if (!(spec.mesh_adaptivity >= 0 && spec.mesh_adaptivity <= 1)) {
    return absl::InvalidArgumentError(
        "fill: mesh adaptivity must be in [0, 1]");
  }
  for (const std::string& f : spec.preview_formats) {
    if (f != "png" && f != "dicom") {
      return absl::InvalidArgumentError(absl::StrCat(
          "fill: unknown preview format '", f, "' (expected png or dicom)"));
    }
  }
  // A malformed UID root fails now, not after the fill.
  if (!spec.uid_root.empty()) {
    if (absl::Status s = DeriveDicomUid(spec.uid_root, "check").status();
        !s.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("fill: --uid-root: ", s.message()));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<FillJobReport> RunFillJob(const FillJobSpec& spec,
                                         const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateFillJobSpec(spec));
  FillJobReport report;

  auto start = std::chrono::steady_clock::now();
  context.Report({.stage = "read"});
  DicomReadOptions read_options;
  read_options.series_instance_uid = spec.series_instance_uid;
  read_options.max_voxels = spec.max_input_voxels;
  // A fill's DICOM segmentation is matched to the reference by its one
  // Frame of Reference (segmentation_reader.h), and its outputs carry it:
  // slices of several frames of reference are refused here as before
  // (interpolation jobs accept them when the geometry is one stack).
  read_options.strict_frame_of_reference = true;
  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries(spec.reference, read_options, context);
  if (!series.ok()) {
    return Annotate(series.status(), "reading the reference series");
  }
  report.input_grid = series->image.grid;
  const Grid reference = series->image.grid;
  ReferenceSeries reference_series{reference, series->series_instance_uid,
                                   series->frame_of_reference_uid};
  reference_series.image_sop_instance_uids.emplace();
  for (const DicomSliceInfo& slice : series->slices) {
    // An anonymised image has none: no reference can name it.
    if (slice.sop_instance_uid.empty()) continue;
    reference_series.image_sop_instance_uids->push_back(slice.sop_instance_uid);
  }
  // The DICOM outputs lie on the reference's own images when they are on
  // its grid and it can be referenced image by image; otherwise on a derived
  // intensity series, which needs the grey values.
  const bool derive_series = spec.fill.z_resolution.factor.has_value() ||
                             spec.fill.z_resolution.spacing_mm.has_value() ||
                             !ReferencedImagesOfSource(*series).ok();
  // Its geometry, UIDs and files are kept for the DICOM outputs; the grey
  // values only for a derived intensity series.
  DicomSeries source = *std::move(series);
  const bool wants_previews = !spec.preview_formats.empty();
  const bool dicom_out_possible =
      spec.write_seg || spec.write_rtstruct != false;
  if ((!dicom_out_possible || !derive_series) && !wants_previews) {
    std::vector<float>().swap(source.image.data);
  }

  SegmentationInput input;
  std::optional<LabelMapFile> label_map_file;
  if (LooksLikeDicomFile(spec.segmentation)) {
    absl::StatusOr<SegmentationInput> seg =
        ReadDicomLabels(spec.segmentation, reference_series, spec.fill.labels);
    if (!seg.ok()) return seg.status();
    input = *std::move(seg);
    report.input_kind = input.rtstruct     ? "rtstruct"
                        : input.fractional ? "seg-fractional"
                                           : "seg-binary";
    report.segments = input.segments;
    // Contours are always placed by position; silently so only when their
    // references agree that they were drawn on this series.
    if (input.unresolved_image_references > 0) {
      report.warnings.push_back(absl::StrFormat(
          "%d of the RTSTRUCT's %d contour image references name no image of "
          "the reference series: its contours were matched to the "
          "reference's slices by position",
          input.unresolved_image_references, input.image_references));
    }
  } else {
    // Any layout of the reference's voxels (label_map_io.h); the
    // reference's (DICOM) geometry is the one carried to the DICOM outputs,
    // the file's own layout and header to the label map outputs.
    absl::StatusOr<LabelMapOnReference> map =
        ReadLabelMapOnReference(spec.segmentation, reference);
    if (!map.ok()) return map.status();
    input.labels = std::move(map->labels);
    label_map_file = std::move(map->file);
    report.input_kind = "label-map";
    report.input_layout = label_map_file->mapping.Describe();
    // Segment names: a Slicer .seg.nrrd's own, replaced by a sidecar's.
    absl::StatusOr<std::vector<LabelSegment>> segments =
        SegmentsFromSlicerFields(label_map_file->header.key_values);
    std::string source = "the segmentation's segments";
    if (segments.ok() && !spec.label_names.empty()) {
      segments = ReadSegmentNames(spec.label_names);
      source = "the label names";
    }
    if (!segments.ok()) return segments.status();
    if (!segments->empty()) {
      INTERSLICE_RETURN_IF_ERROR(CheckSegmentsAgainstLabels(
          *segments, LabelsPresent(input.labels), source));
    }
    input.segments = *std::move(segments);
    report.segments = input.segments;
  }
  if (!spec.label_names.empty() && report.input_kind != "label-map") {
    return absl::InvalidArgumentError(
        "label names are for a label map; a SEG or RTSTRUCT names its "
        "segments itself");
  }
  const bool write_rtstruct = spec.write_rtstruct.value_or(input.rtstruct);
  // The grey values stay for a derived intensity series and the previews.
  const bool needs_grey_values =
      derive_series && (spec.write_seg || write_rtstruct);
  if (!needs_grey_values && !wants_previews) {
    std::vector<float>().swap(source.image.data);
  }
  report.read_seconds = SecondsSince(start);

  start = std::chrono::steady_clock::now();
  context.Report({.stage = "fill"});
  FillOptions fill = spec.fill;
  fill.keep_fields = !spec.mesh_formats.empty() || wants_previews;
  if (input.rtstruct) fill.contours = &input.contours;
  INTERSLICE_ASSIGN_OR_RETURN(FillResult result,
                              FillBetweenSlices(input.labels, fill, context));
  for (const LabelFillInfo& info : result.per_label) {
    for (int64_t k : info.key_slices) {
      if (input.contours.Find(info.label, k) != nullptr) {
        ++report.polygon_key_slices;
      }
    }
  }
  report.fill_seconds = SecondsSince(start);
  report.output_grid = result.labels.grid;
  report.factor = result.factor;
  report.method = spec.fill.method == FillMethod::kAuto
                      ? std::string(FillMethodName(FillMethod::kAuto))
                      : std::string(SolverMethodName(spec.fill.solver.method));
  report.gap_voxels_closed = result.gap_voxels_closed;
  report.key_voxels_restored = result.key_voxels_restored;
  report.warnings.insert(report.warnings.end(), result.warnings.begin(),
                         result.warnings.end());

  start = std::chrono::steady_clock::now();
  std::vector<std::pair<int, Mesh>> meshes;
  if (!spec.mesh_formats.empty()) {
    context.Report({.stage = "mesh"});
    SurfaceOptions surface;
    surface.adaptivity = spec.mesh_adaptivity;
    for (const LabelFillInfo& info : result.per_label) {
      if (info.field.data.empty() || info.output_voxels == 0) continue;
      absl::StatusOr<Mesh> mesh = ExtractSurface(info.field, surface, context);
      if (!mesh.ok()) {
        return Annotate(mesh.status(),
                        absl::StrFormat("meshing label %d", info.label));
      }
      if (!mesh->triangles.empty())
        meshes.emplace_back(info.label, *std::move(mesh));
    }
  }
  report.mesh_seconds = SecondsSince(start);

  // Previews: rendered now, written with the other outputs; a failure is a
  // note, never the job's.
  std::optional<PreviewSet> previews;
  if (wants_previews) {
    start = std::chrono::steady_clock::now();
    context.Report({.stage = "preview"});
    absl::StatusOr<PreviewSet> rendered =
        RenderFillPreviews(spec, source, input, result, context);
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    if (rendered.ok()) {
      report.preview_notes = rendered->notes;
      previews = *std::move(rendered);
    } else {
      report.preview_notes.push_back(
          absl::StrCat("previews skipped: ", rendered.status().message()));
    }
    if (!needs_grey_values) std::vector<float>().swap(source.image.data);
    report.preview_seconds = SecondsSince(start);
  }

  start = std::chrono::steady_clock::now();
  context.Report({.stage = "write"});
  std::error_code ec;
  std::filesystem::create_directories(spec.output_dir, ec);
  if (ec || !std::filesystem::is_directory(spec.output_dir)) {
    return absl::InternalError(absl::StrCat(
        "cannot create output folder ", spec.output_dir, ": ", ec.message()));
  }
  const std::filesystem::path dir(spec.output_dir);
  for (const std::string& format : spec.volume_formats) {
    const std::string path =
        (dir / (format == "nii" ? "labels.nii.gz" : "labels.nrrd")).string();
    if (label_map_file.has_value()) {
      INTERSLICE_RETURN_IF_ERROR(
          WriteLabelMapLike(result.labels, *label_map_file, path, context));
    } else {
      INTERSLICE_RETURN_IF_ERROR(WriteVolume(result.labels, path, context));
    }
    report.artifacts.push_back({"labels", 0, path, FileSize(path)});
  }
  for (const auto& [label, mesh] : meshes) {
    for (const std::string& format : spec.mesh_formats) {
      const std::string path =
          (dir / absl::StrFormat("label-%d.%s", label, format)).string();
      INTERSLICE_RETURN_IF_ERROR(WriteMesh(mesh, path));
      report.artifacts.push_back({"surface", label, path, FileSize(path)});
    }
  }
  if (previews.has_value() && Contains(spec.preview_formats, "png")) {
    const std::string folder = (dir / "previews").string();
    absl::Status written = WritePreviewPngs(previews->images, folder).status();
    if (written.ok()) {
      report.artifacts.push_back({"previews", 0, folder, FolderSize(folder)});
    } else {
      report.preview_notes.push_back(
          absl::StrCat("previews not written (previews): ", written.message()));
    }
  }
  std::vector<RgbPicture> pictures;
  if (previews.has_value() && Contains(spec.preview_formats, "dicom")) {
    for (const PreviewImage& image : previews->images) {
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
  }
  if (spec.write_seg || write_rtstruct || !pictures.empty()) {
    INTERSLICE_RETURN_IF_ERROR(WriteDicomOutputs(spec, source, input, result,
                                                 write_rtstruct, derive_series,
                                                 pictures, context, report));
  }
  report.write_seconds = SecondsSince(start);
  for (LabelFillInfo& info : result.per_label) {
    info.field = Volume<float>();
    report.per_label.push_back(std::move(info));
  }
  return report;
}

std::string FillJobReportToJson(const FillJobReport& report) {
  using nlohmann::ordered_json;
  ordered_json j;
  j["stages"] = {{"read", report.read_seconds},
                 {"fill", report.fill_seconds},
                 {"mesh", report.mesh_seconds}};
  if (report.preview_seconds > 0 || !report.preview_notes.empty()) {
    j["stages"]["preview"] = report.preview_seconds;
  }
  j["stages"]["write"] = report.write_seconds;
  const Grid& g = report.output_grid;
  j["grid"] = {{"size", g.size},
               {"spacing", g.spacing},
               {"origin", g.origin},
               {"direction", g.direction},
               {"insertion_factor", report.factor}};
  j["method"] = report.method;
  j["input"] = report.input_kind;
  if (!report.input_layout.empty()) j["input_layout"] = report.input_layout;
  ordered_json segments = ordered_json::array();
  for (const LabelSegment& d : report.segments) {
    const std::array<uint8_t, 3> rgb = SegmentRgb(d);
    segments.push_back({{"number", d.number},
                        {"label", d.label},
                        {"rgb", rgb},
                        {"category", d.category.meaning},
                        {"type", d.type.meaning}});
  }
  j["segments"] = segments;
  ordered_json labels = ordered_json::array();
  for (const LabelFillInfo& info : report.per_label) {
    labels.push_back({{"label", info.label},
                      {"key_slices", info.key_slices},
                      {"drawn_slices", info.drawn_slices},
                      {"method", info.method},
                      {"voxels", info.output_voxels},
                      {"iterations", info.solver.iterations},
                      {"relative_residual", info.solver.relative_residual}});
  }
  j["labels"] = labels;
  j["polygon_key_slices"] = report.polygon_key_slices;
  j["gap_voxels_closed"] = report.gap_voxels_closed;
  j["key_voxels_restored"] = report.key_voxels_restored;
  j["warnings"] = report.warnings;
  if (report.preview_seconds > 0 || !report.preview_notes.empty()) {
    j["previews"] = {{"notes", report.preview_notes}};
  }
  ordered_json artifacts = ordered_json::array();
  for (const FillArtifact& a : report.artifacts) {
    artifacts.push_back({{"kind", a.kind},
                         {"label", a.label},
                         {"path", a.path},
                         {"size_bytes", a.size_bytes}});
  }
  j["artifacts"] = artifacts;
  return j.dump(2);
}

}  // namespace interslice
