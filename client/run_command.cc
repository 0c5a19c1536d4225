#include "client/run_command.h"

#include <cstdio>
#include <fstream>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/progress_display.h"

namespace interslice::client {
namespace {

void PrintSummary(const JobReport& report, const std::string& out_dir) {
  const Grid& g = report.output_grid;
  std::printf("interslice: wrote %zu file(s) to %s\n", report.artifacts.size(),
              out_dir.c_str());
  std::printf(
      "  grid      %lld x %lld x %lld voxels, spacing %.4g x %.4g x "
      "%.4g mm (%d slices inserted per gap)\n",
      static_cast<long long>(g.size[0]), static_cast<long long>(g.size[1]),
      static_cast<long long>(g.size[2]), g.spacing[0], g.spacing[1],
      g.spacing[2], report.insertion_factor - 1);
  if (report.gantry_tilt_degrees != 0) {
    std::printf(
        "  tilt      gantry tilt of %.3g degrees corrected (slices resampled "
        "onto an orthogonal grid)\n",
        report.gantry_tilt_degrees);
  }
  if (report.slab_thickness_mm > 0) {
    std::printf(
        "  slabs     %.3g mm slabs deconvolved in %d iterations (residual "
        "%.3g -> %.3g)\n",
        report.slab_thickness_mm, report.slab_iterations,
        report.slab_residual_before, report.slab_residual_after);
  }
  if (report.max_snap_mm > 1e-6) {
    std::printf(
        "  spacing   non-uniform: slices moved up to %.3g mm to the nearest "
        "output slice\n",
        report.max_snap_mm);
  }
  std::printf(
      "  solver    %s, %d iterations, relative residual %.3g, "
      "energy %.6g -> %.6g (%s units)\n",
      std::string(SolverMethodName(report.solver.method)).c_str(),
      report.solver.iterations, report.solver.relative_residual,
      report.solver.initial_energy, report.solver.energy,
      std::string(EnergyUnitsName(report.energy_units)).c_str());
  if (report.mesh_triangles > 0 || report.mesh_vertices > 0) {
    std::printf("  surface   %lld triangles, %lld vertices\n",
                static_cast<long long>(report.mesh_triangles),
                static_cast<long long>(report.mesh_vertices));
  }
  std::string timings;
  double total = 0;
  for (const StageTiming& s : report.stages) {
    absl::StrAppendFormat(&timings, " %s %.2fs", s.stage, s.seconds);
    total += s.seconds;
  }
  std::printf("  time     %s (total %.2fs), peak memory %.0f MiB\n",
              timings.c_str(), total, report.peak_rss_bytes / 1048576.0);
  for (const Artifact& a : report.artifacts) {
    std::printf("  %-20s %s\n", a.kind.c_str(), a.path.c_str());
  }
}

}  // namespace

void AddRunOptions(CLI::App& app, RunArguments& args) {
  app.add_option("inputs", args.inputs,
                 "DICOM folder(s) or file(s); folders are searched recursively")
      ->required();
  app.add_option("--threshold", args.threshold,
                 "Object threshold in modality units (HU for CT): voxels with "
                 "value >= threshold are inside")
      ->required();
  app.add_option("--upper", args.upper,
                 "Optional upper threshold (HU): inside means threshold <= "
                 "value <= upper");
  app.add_option(
      "--series-uid", args.series_uid,
      "SeriesInstanceUID to use when the input holds several series");
  app.add_option("--roi", args.roi,
                 "Region of interest x0,y0,z0,x1,y1,z1: a half-open voxel box "
                 "in the input's index space (z in sorted slice order)");
  app.add_option(
         "--method", args.method,
         "direct (exact minimiser), cg (the paper's conjugate "
         "gradient), linear (no refinement) or morph "
         "(registration-based stacking along a smooth, C1-in-z trajectory, "
         "values interpolated without overshoot; no solver, "
         "docs/eval/candidates.md)")
      ->capture_default_str();
  app.add_option("--iterations", args.iterations,
                 "CG iterations (default 15, as in the paper)");
  app.add_option("--tolerance", args.tolerance,
                 "CG: stop at this relative residual |r|/|r0|");
  app.add_option("--energy-units", args.energy_units,
                 "voxel (the paper's, default) or mm")
      ->capture_default_str();
  app.add_option("--factor", args.factor, "Insert N-1 slices per gap (N >= 1)");
  app.add_option("--spacing", args.spacing,
                 "Target output slice spacing in mm (default: the in-plane "
                 "spacing, i.e. isotropic)");
  app.add_option("--output-series", args.output_series,
                 "DICOM objects to write, any of intensity (image series "
                 "DIR/series-intensity/), distance (Parametric Map "
                 "DIR/distance.dcm, mm), mask (SEG DIR/seg.dcm); a SEG or "
                 "distance map also writes the intensity series it "
                 "references");
  app.add_flag("--seg", args.seg,
               "Write the mask as a binary DICOM SEG (DIR/seg.dcm; same as "
               "--output-series mask)");
  app.add_option("--dicom-compression", args.dicom_compression,
                 "Pixel data of the DICOM intensity series: none (native) "
                 "or rle (RLE Lossless: the same values, fewer bytes)")
      ->capture_default_str();
  app.add_option("--uid-root", args.uid_root,
                 "UID root for the new DICOM UIDs (default 2.25 + UUID)");
  app.add_flag("--random-uids", args.random_uids,
               "New random DICOM UIDs on every run (default: derived from "
               "the source and the job, so a rerun replaces its results)");
  app.add_option("--series-number-base", args.series_number_base,
                 "Series numbers of the DICOM outputs: intensity BASE+1, "
                 "distance BASE+2, SEG BASE+3 (default 1000 x the source's "
                 "SeriesNumber)");
  app.add_option("--multiframe-volume", args.multiframe_volume,
                 "Which volume of a multi-frame series to read, as named in "
                 "the error that lists them");
  app.add_flag("--strict-spacing", args.strict_spacing,
               "Fail on non-uniform slice spacing (missing slices) instead "
               "of placing each slice on the nearest output slice");
  app.add_flag(
      "--slab-deconvolution", args.slab_deconvolution,
      "Thick slices: contour an estimate of the thin object at each "
      "slice position (slab deconvolution by the series' "
      "SliceThickness) instead of the slab-averaged slices; in-process "
      "only (docs/eval/candidates.md)");
  app.add_option("--band", args.band,
                 "Radius in mm of the band of exact 2D distances (default 16 "
                 "pixels)");
  app.add_option("--adaptivity", args.adaptivity,
                 "Mesh adaptivity in [0,1]: higher gives fewer triangles")
      ->capture_default_str();
  app.add_option("--out", args.out, "Output folder (created if missing)")
      ->required();
  app.add_option("--mesh", args.mesh,
                 "Mesh formats: any of stl,ply,obj, or none")
      ->capture_default_str();
  app.add_option("--volume", args.volume,
                 "Volume formats: any of nii (.nii.gz), nrrd, "
                 "nii-uncompressed (.nii: no compression time), or none")
      ->capture_default_str();
  app.add_option("--report", args.report, "Write a JSON report to this file");
  app.add_option("--threads", args.threads, "Worker threads (0 = all cores)")
      ->capture_default_str();
  app.add_flag("--quiet", args.quiet, "No progress display or summary");
}

int ExecuteRun(const RunArguments& args) {
  absl::StatusOr<JobSpec> spec = BuildJobSpec(args);
  if (!spec.ok()) {
    std::fprintf(stderr, "interslice: error: %s\n",
                 std::string(spec.status().message()).c_str());
    return 1;
  }
  ProgressDisplay display(stderr, !args.quiet);
  ComputeContext context;
  context.threads = args.threads;
  context.progress = [&display](const ProgressEvent& e) { display.Update(e); };
  absl::StatusOr<JobReport> report = RunJob(*spec, context);
  display.Finish();
  if (!report.ok()) {
    std::fprintf(stderr, "interslice: error: %s\n",
                 std::string(report.status().message()).c_str());
    return 1;
  }
  report->peak_rss_bytes = PeakRssBytes();
  if (!args.report.empty()) {
    std::ofstream file(args.report);
    file << JobReportToJson(*report) << "\n";
    file.close();
    if (!file) {
      std::fprintf(stderr, "interslice: error: cannot write report %s\n",
                   args.report.c_str());
      return 1;
    }
  }
  if (!args.quiet) PrintSummary(*report, spec->output_dir);
  return 0;
}

}  // namespace interslice::client
