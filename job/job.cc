#include "job/job.h"

#include <algorithm>
#include <filesystem>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/dicom/series_index.h"
#include "job/wire.h"

namespace interslice::job {
namespace {

namespace fs = std::filesystem;

constexpr const char* kSegmentationFolder = "segmentation";

std::string FileName(const std::string& path) {
  return fs::path(path).filename().string();
}

std::vector<std::string> InterpolationSummary(const JobReport& report,
                                              const std::string& out_dir) {
  std::vector<std::string> lines;
  const Grid& g = report.output_grid;
  lines.push_back(absl::StrFormat("interslice: wrote %d file(s) to %s",
                                  report.artifacts.size(), out_dir));
  lines.push_back(absl::StrFormat(
      "  grid      %d x %d x %d voxels, spacing %.4g x %.4g x %.4g mm (%d "
      "slices inserted per gap)",
      g.size[0], g.size[1], g.size[2], g.spacing[0], g.spacing[1], g.spacing[2],
      report.insertion_factor - 1));
  if (std::optional<std::string> region = RegionSummaryLine(report)) {
    lines.push_back(*std::move(region));
  }
  if (report.gantry_tilt_degrees != 0) {
    lines.push_back(absl::StrFormat(
        "  tilt      gantry tilt of %.3g degrees corrected (slices resampled "
        "onto an orthogonal grid)",
        report.gantry_tilt_degrees));
  }
  if (report.slab_thickness_mm > 0) {
    lines.push_back(absl::StrFormat(
        "  slabs     %.3g mm slabs deconvolved in %d iterations (residual "
        "%.3g -> %.3g)",
        report.slab_thickness_mm, report.slab_iterations,
        report.slab_residual_before, report.slab_residual_after));
  }
  if (report.max_snap_mm > 1e-6) {
    lines.push_back(absl::StrFormat(
        "  spacing   non-uniform: slices moved up to %.3g mm to the nearest "
        "output slice",
        report.max_snap_mm));
  }
  lines.push_back(absl::StrFormat(
      "  solver    %s, %d iterations, relative residual %.3g, energy %.6g -> "
      "%.6g (%s units)",
      SolverMethodName(report.solver.method), report.solver.iterations,
      report.solver.relative_residual, report.solver.initial_energy,
      report.solver.energy, EnergyUnitsName(report.energy_units)));
  if (report.mesh_triangles > 0 || report.mesh_vertices > 0) {
    lines.push_back(absl::StrFormat("  surface   %d triangles, %d vertices",
                                    report.mesh_triangles,
                                    report.mesh_vertices));
  }
  if (report.dicom_mesh_adaptivity >= 0) {
    // The distance from the full surface only when it was measured
    // (dicom_mesh_resolution_mm > 0): a capped mesh without it is not
    // "within 0 mm".
    const std::string deviation =
        report.dicom_mesh_resolution_mm > 0
            ? absl::StrFormat(
                  ", %s %.3g mm (mean %.3g mm) from the full surface",
                  report.dicom_mesh_samples_beyond_band > 0 ? "at least"
                                                            : "within",
                  report.dicom_mesh_max_deviation_mm,
                  report.dicom_mesh_mean_deviation_mm)
        : report.dicom_mesh_triangles < report.dicom_mesh_triangles_before_cap
            ? ", distance from the full surface not measured"
            : "";
    lines.push_back(absl::StrFormat(
        "  DICOM mesh %d triangles (adaptivity %g)%s",
        report.dicom_mesh_triangles, report.dicom_mesh_adaptivity, deviation));
    if (report.dicom_mesh_triangles < report.dicom_mesh_triangles_before_cap ||
        report.dicom_mesh_over_cap) {
      lines.push_back(absl::StrFormat(
          "  DICOM mesh capped at %g MB: %d -> %d triangles (STL %.1f MB), "
          "simplifier's error estimate %.3g mm%s",
          report.dicom_mesh_max_mb, report.dicom_mesh_triangles_before_cap,
          report.dicom_mesh_triangles, report.dicom_mesh_stl_bytes / 1e6,
          report.dicom_mesh_simplify_error_mm,
          report.dicom_mesh_over_cap ? " (could not reach the cap)" : ""));
    }
  }
  std::string timings;
  double total = 0;
  for (const StageTiming& s : report.stages) {
    absl::StrAppendFormat(&timings, " %s %.2fs", s.stage, s.seconds);
    total += s.seconds;
  }
  lines.push_back(
      absl::StrFormat("  time     %s (total %.2fs), peak memory %.0f MiB",
                      timings, total, report.peak_rss_bytes / 1048576.0));
  for (const Artifact& a : report.artifacts) {
    lines.push_back(absl::StrFormat("  %-20s %s", a.kind, a.path));
  }
  return lines;
}

std::vector<std::string> FillSummary(const FillJobReport& report,
                                     const std::string& out_dir) {
  std::vector<std::string> lines;
  const Grid& g = report.output_grid;
  lines.push_back(absl::StrFormat(
      "interslice: filled %d label(s) (%s) on %d x %d x %d voxels, %d file(s) "
      "in %s",
      report.per_label.size(), report.method, g.size[0], g.size[1], g.size[2],
      report.artifacts.size(), out_dir));
  for (const LabelFillInfo& info : report.per_label) {
    lines.push_back(absl::StrFormat(
        "  label %-5d %d key slices (%d drawn), %d voxels", info.label,
        info.key_slices.size(), info.drawn_slices, info.output_voxels));
  }
  lines.push_back(absl::StrFormat(
      "  time      read %.2fs fill %.2fs mesh %.2fs preview %.2fs write %.2fs; "
      "gap voxels closed %d",
      report.read_seconds, report.fill_seconds, report.mesh_seconds,
      report.preview_seconds, report.write_seconds, report.gap_voxels_closed));
  return lines;
}

class InterpolationJob final : public JobKind {
 public:
  explicit InterpolationJob(JobSpec spec) : spec_(std::move(spec)) {}

  absl::string_view name() const override { return "interpolate"; }
  int min_upload_files() const override { return 1; }
  bool writes_dicom() const override {
    return !spec_.output_series.empty() || spec_.write_seg ||
           std::find(spec_.preview_formats.begin(), spec_.preview_formats.end(),
                     "dicom") != spec_.preview_formats.end();
  }

  absl::Status UseSpool(const std::string& upload_dir,
                        const std::string& output_dir,
                        int64_t max_output_voxels) override {
    spec_.inputs = {upload_dir};
    spec_.output_dir = output_dir;
    if (max_output_voxels > 0) spec_.max_output_voxels = max_output_voxels;
    relative_paths_ = true;
    return absl::OkStatus();
  }

  void OmitFilesDicomObjectsCarry() override {
    spec_.omit_files_dicom_objects_carry = true;
  }

  absl::StatusOr<JobResult> Run(const ComputeContext& context) const override {
    absl::StatusOr<JobReport> report = RunJob(spec_, context);
    if (!report.ok()) return report.status();
    report->peak_rss_bytes = PeakRssBytes();
    JobResult result;
    result.stages = report->stages;
    result.artifacts = report->artifacts;
    result.peak_rss_bytes = report->peak_rss_bytes;
    result.warnings = report->input_warnings;
    result.warnings.insert(result.warnings.end(), report->preview_notes.begin(),
                           report->preview_notes.end());
    result.summary = InterpolationSummary(*report, spec_.output_dir);
    if (relative_paths_) {
      for (Artifact& a : report->artifacts) a.path = FileName(a.path);
    }
    result.report_json = JobReportToJson(*report);
    return result;
  }

 private:
  JobSpec spec_;
  bool relative_paths_ = false;
};

class FillJob final : public JobKind {
 public:
  // `uploads`: the segmentation, then the label names if the wire spec
  // names them (empty for a job made from a core spec: its files are
  // where the spec says).
  FillJob(FillJobSpec spec, std::vector<NamedUpload> uploads)
      : spec_(std::move(spec)), uploads_(std::move(uploads)) {}

  absl::string_view name() const override { return "fill"; }
  // The segmentation, its label names if any, and at least one file of its
  // reference series.
  int min_upload_files() const override {
    return std::max<int>(2, static_cast<int>(uploads_.size()) + 1);
  }
  // A fill job's DICOM results (SEG, RTSTRUCT) are delivered when it writes
  // any; one that writes none makes a delivery of no instances.
  bool writes_dicom() const override { return true; }
  std::vector<NamedUpload> named_uploads() const override { return uploads_; }

  absl::Status UseSpool(const std::string& upload_dir,
                        const std::string& output_dir,
                        int64_t max_output_voxels) override {
    std::error_code ec;
    spec_.reference.clear();
    for (const auto& entry : fs::directory_iterator(upload_dir, ec)) {
      if (entry.is_regular_file(ec)) {
        spec_.reference.push_back(entry.path().string());
      }
    }
    std::sort(spec_.reference.begin(), spec_.reference.end());
    if (uploads_.empty()) {
      return absl::FailedPreconditionError(
          "the fill job does not name its segmentation upload");
    }
    // Each named upload where every door stores it.
    std::vector<std::string> paths;
    for (const NamedUpload& upload : uploads_) {
      const fs::path path = fs::path(upload_dir) / upload.path;
      if (!fs::is_regular_file(path, ec)) {
        return absl::FailedPreconditionError(
            absl::StrCat("the file that ", upload.field,
                         " names is missing from the fill job's upload"));
      }
      paths.push_back(path.string());
    }
    spec_.segmentation = paths[0];
    spec_.label_names = paths.size() > 1 ? paths[1] : "";
    if (spec_.reference.empty()) {
      return absl::FailedPreconditionError(
          "the fill job's upload holds no reference series files");
    }
    spec_.output_dir = output_dir;
    if (max_output_voxels > 0) spec_.fill.max_output_voxels = max_output_voxels;
    relative_paths_ = true;
    return absl::OkStatus();
  }

  absl::StatusOr<JobResult> Run(const ComputeContext& context) const override {
    absl::StatusOr<FillJobReport> report = RunFillJob(spec_, context);
    if (!report.ok()) return report.status();
    JobResult result;
    result.stages = {{"read", report->read_seconds},
                     {"fill", report->fill_seconds},
                     {"mesh", report->mesh_seconds}};
    if (!spec_.preview_formats.empty()) {
      result.stages.push_back({"preview", report->preview_seconds});
    }
    result.stages.push_back({"write", report->write_seconds});
    for (const FillArtifact& a : report->artifacts) {
      result.artifacts.push_back({a.kind, a.path, a.size_bytes});
    }
    result.warnings = report->warnings;
    result.warnings.insert(result.warnings.end(), report->preview_notes.begin(),
                           report->preview_notes.end());
    result.summary = FillSummary(*report, spec_.output_dir);
    result.peak_rss_bytes = PeakRssBytes();
    if (relative_paths_) {
      for (FillArtifact& a : report->artifacts) a.path = FileName(a.path);
    }
    result.report_json = FillJobReportToJson(*report);
    return result;
  }

 private:
  FillJobSpec spec_;
  const std::vector<NamedUpload> uploads_;
  bool relative_paths_ = false;
};

}  // namespace

std::optional<std::string> RegionSummaryLine(const JobReport& report) {
  if (!report.roi.has_value()) return std::nullopt;
  const VoxelBox& v = *report.roi;
  std::string line = absl::StrFormat(
      "  region    voxels x %d..%d, y %d..%d, z %d..%d (half-open)", v.begin[0],
      v.end[0], v.begin[1], v.end[1], v.begin[2], v.end[2]);
  if (report.roi_mm.has_value()) {
    const PhysicalBox& b = *report.roi_mm;
    absl::StrAppendFormat(
        &line, " from the box (%.6g, %.6g, %.6g)..(%.6g, %.6g, %.6g) LPS mm",
        b.min[0], b.min[1], b.min[2], b.max[0], b.max[1], b.max[2]);
  }
  return line;
}

std::unique_ptr<JobKind> MakeInterpolationJob(JobSpec spec) {
  return std::make_unique<InterpolationJob>(std::move(spec));
}

std::unique_ptr<JobKind> MakeFillJob(FillJobSpec spec) {
  return std::make_unique<FillJob>(std::move(spec), std::vector<NamedUpload>());
}

absl::StatusOr<std::unique_ptr<JobKind>> MakeJobFromWire(
    const v1::JobSpec& spec) {
  if (IsFillSpec(spec)) {
    absl::StatusOr<FillJobSpec> fill = FillJobSpecFromWire(spec);
    if (!fill.ok()) return fill.status();
    const v1::LabelFill& wire = spec.fill();
    std::vector<NamedUpload> uploads = {
        {"spec.fill.segmentation_file", wire.segmentation_file(),
         SegmentationUploadPath(wire.segmentation_file())}};
    if (!wire.label_names_file().empty()) {
      uploads.push_back({"spec.fill.label_names_file", wire.label_names_file(),
                         LabelNamesUploadPath(wire.label_names_file())});
    }
    return std::unique_ptr<JobKind>(
        std::make_unique<FillJob>(*std::move(fill), std::move(uploads)));
  }
  absl::StatusOr<JobSpec> interpolation = JobSpecFromWire(spec);
  if (!interpolation.ok()) return interpolation.status();
  return MakeInterpolationJob(*std::move(interpolation));
}

std::string SegmentationUploadPath(const std::string& client_name) {
  std::string lower = client_name;
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

std::string LabelNamesUploadPath(const std::string& client_name) {
  std::string lower = client_name;
  std::transform(lower.begin(), lower.end(), lower.begin(),
                 [](unsigned char c) { return std::tolower(c); });
  std::string extension = ".csv";
  for (const char* e : {".json", ".txt"}) {
    if (absl::EndsWith(lower, e)) extension = e;
  }
  return absl::StrCat(kSegmentationFolder, "/label-names", extension);
}

absl::StatusOr<SourceSeries> DescribeSourceSeries(
    const std::string& upload_dir, const std::string& series_uid,
    const ComputeContext& context) {
  std::vector<std::string> files;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(upload_dir, ec)) {
    if (entry.is_regular_file(ec)) files.push_back(entry.path().string());
  }
  if (ec) return absl::NotFoundError("cannot list the job's files");
  std::sort(files.begin(), files.end());
  absl::StatusOr<DicomFileIndex> index = IndexDicomFiles(files, context);
  if (!index.ok()) return index.status();
  absl::StatusOr<const DicomSeriesGroup*> series =
      FindDicomSeries(*index, series_uid);
  if (!series.ok()) return series.status();
  SourceSeries source;
  source.series_instance_uid = (*series)->summary.series_instance_uid;
  source.modality = (*series)->summary.modality;
  source.instance_count = (*series)->summary.image_count;
  for (size_t member : (*series)->members) {
    const std::string& study = index->headers[member].study_uid;
    if (!study.empty()) {
      source.study_instance_uid = study;
      break;
    }
  }
  return source;
}

std::string MediaTypeForArtifact(const std::string& name) {
  if (absl::EndsWith(name, ".nii.gz")) return "application/gzip";
  if (absl::EndsWith(name, ".nrrd")) return "application/octet-stream";
  if (absl::EndsWith(name, ".nii")) return "application/octet-stream";
  if (absl::EndsWith(name, ".stl")) return "model/stl";
  if (absl::EndsWith(name, ".ply")) return "application/ply";
  if (absl::EndsWith(name, ".obj")) return "model/obj";
  if (absl::EndsWith(name, ".dcm")) return "application/dicom";
  if (absl::EndsWith(name, ".txt")) return "text/plain";
  if (absl::EndsWith(name, ".png")) return "image/png";
  return "application/octet-stream";
}

}  // namespace interslice::job
