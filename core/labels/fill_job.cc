#include "core/labels/fill_job.h"

#include <chrono>
#include <filesystem>
#include <system_error>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom/series_reader.h"
#include "core/labels/segmentation_reader.h"
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

// Prefixes a status message with what was being done.
absl::Status Annotate(const absl::Status& status, const std::string& what) {
  return absl::Status(status.code(),
                      absl::StrCat(what, ": ", status.message()));
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
  if (!(spec.mesh_adaptivity >= 0 && spec.mesh_adaptivity <= 1)) {
    return absl::InvalidArgumentError(
        "fill: mesh adaptivity must be in [0, 1]");
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
  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries(spec.reference, read_options, context);
  if (!series.ok()) {
    return Annotate(series.status(), "reading the reference series");
  }
  report.input_grid = series->image.grid;
  const Grid reference = series->image.grid;
  const ReferenceSeries reference_series{reference, series->series_instance_uid,
                                         series->frame_of_reference_uid};
  *series = DicomSeries();  // only its geometry and UIDs are needed

  absl::StatusOr<LabelVolume> labels;
  if (LooksLikeDicomFile(spec.segmentation)) {
    absl::StatusOr<SegmentationInput> seg =
        ReadDicomLabels(spec.segmentation, reference_series, spec.fill.labels);
    if (!seg.ok()) return seg.status();
    report.input_kind = seg->rtstruct     ? "rtstruct"
                        : seg->fractional ? "seg-fractional"
                                          : "seg-binary";
    report.segments = seg->segments;
    labels = std::move(seg->labels);
  } else {
    absl::StatusOr<Volume<float>> raw = ReadVolumeAsFloat(spec.segmentation);
    if (!raw.ok()) return Annotate(raw.status(), spec.segmentation);
    INTERSLICE_RETURN_IF_ERROR(
        CheckSameGrid(raw->grid, reference, "the label map"));
    labels = LabelVolumeFromFloat(*raw);
    if (!labels.ok()) return Annotate(labels.status(), spec.segmentation);
    report.input_kind = "label-map";
  }
  // The label map's grid equals the reference up to rounding; the
  // reference's (DICOM) geometry is the one carried to the outputs.
  labels->grid = reference;
  report.read_seconds = SecondsSince(start);

  start = std::chrono::steady_clock::now();
  context.Report({.stage = "fill"});
  FillOptions fill = spec.fill;
  fill.keep_fields = !spec.mesh_formats.empty();
  INTERSLICE_ASSIGN_OR_RETURN(FillResult result,
                              FillBetweenSlices(*labels, fill, context));
  report.fill_seconds = SecondsSince(start);
  report.output_grid = result.labels.grid;
  report.factor = result.factor;
  report.method = std::string(SolverMethodName(spec.fill.solver.method));
  report.gap_voxels_closed = result.gap_voxels_closed;
  report.key_voxels_restored = result.key_voxels_restored;
  report.warnings = result.warnings;

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
    INTERSLICE_RETURN_IF_ERROR(WriteVolume(result.labels, path));
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
                 {"mesh", report.mesh_seconds},
                 {"write", report.write_seconds}};
  const Grid& g = report.output_grid;
  j["grid"] = {{"size", g.size},
               {"spacing", g.spacing},
               {"origin", g.origin},
               {"direction", g.direction},
               {"insertion_factor", report.factor}};
  j["method"] = report.method;
  j["input"] = report.input_kind;
  ordered_json segments = ordered_json::array();
  for (const SegmentDescription& d : report.segments) {
    segments.push_back({{"number", d.number},
                        {"label", d.label},
                        {"category", d.category.meaning},
                        {"type", d.type.meaning}});
  }
  j["segments"] = segments;
  ordered_json labels = ordered_json::array();
  for (const LabelFillInfo& info : report.per_label) {
    labels.push_back({{"label", info.label},
                      {"key_slices", info.key_slices},
                      {"drawn_slices", info.drawn_slices},
                      {"voxels", info.output_voxels},
                      {"iterations", info.solver.iterations},
                      {"relative_residual", info.solver.relative_residual}});
  }
  j["labels"] = labels;
  j["gap_voxels_closed"] = report.gap_voxels_closed;
  j["key_voxels_restored"] = report.key_voxels_restored;
  j["warnings"] = report.warnings;
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
