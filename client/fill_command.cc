#include "client/fill_command.h"

#include <cstdio>
#include <fstream>

#include "CLI/CLI.hpp"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"

namespace interslice::client {
namespace {

// A slice list may name at most this many slices (bounds "0-2000000000").
constexpr int64_t kMaxListedSlices = 1 << 20;

absl::StatusOr<std::vector<std::string>> ParseFormats(
    const std::string& text, const std::vector<std::string>& allowed,
    const std::string& option) {
  std::vector<std::string> out;
  if (text.empty() || text == "none") return out;
  for (absl::string_view item : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    const std::string value(item);
    if (std::find(allowed.begin(), allowed.end(), value) == allowed.end()) {
      return absl::InvalidArgumentError(
          absl::StrCat(option, ": unknown value '", value, "'"));
    }
    if (std::find(out.begin(), out.end(), value) == out.end()) {
      out.push_back(value);
    }
  }
  return out;
}

}  // namespace

absl::StatusOr<std::vector<int64_t>> ParseSliceList(const std::string& text) {
  std::vector<int64_t> out;
  for (absl::string_view item : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    const auto bad = [&] {
      return absl::InvalidArgumentError(absl::StrCat(
          "--key-slices: '", item,
          "' is not a slice index, a range a-b or a range with step a-b:s"));
    };
    std::vector<absl::string_view> range_step = absl::StrSplit(item, ':');
    std::vector<absl::string_view> ends = absl::StrSplit(range_step[0], '-');
    int64_t a = 0, b = 0, step = 1;
    if (range_step.size() > 2 || ends.size() > 2 ||
        !absl::SimpleAtoi(ends[0], &a) ||
        (ends.size() == 2 && !absl::SimpleAtoi(ends[1], &b)) ||
        (range_step.size() == 2 &&
         (ends.size() != 2 || !absl::SimpleAtoi(range_step[1], &step)))) {
      return bad();
    }
    if (ends.size() == 1) b = a;
    if (a < 0 || b < a || step < 1) return bad();
    for (int64_t k = a; k <= b; k += step) {
      if (static_cast<int64_t>(out.size()) >= kMaxListedSlices) return bad();
      out.push_back(k);
    }
  }
  if (out.empty()) {
    return absl::InvalidArgumentError("--key-slices: no slice given");
  }
  return out;
}

void AddFillOptions(CLI::App& app, FillArguments& args) {
  app.add_option("segmentation", args.segmentation,
                 "Label map (.nii, .nii.gz, .nrrd; integer labels, 0 = "
                 "background) on the reference series' grid, or a DICOM SEG "
                 "(label = segment number) or RTSTRUCT (label = ROI number) "
                 "drawn on the reference series")
      ->required();
  app.add_option("--reference", args.reference,
                 "The DICOM series the segmentation was drawn on (folders "
                 "or files)")
      ->required();
  app.add_option("--series-uid", args.series_uid,
                 "SeriesInstanceUID of the reference when it holds several");
  app.add_option("--labels", args.labels,
                 "Labels to fill, e.g. 1,3,7 (default: all); in a label map "
                 "the others are copied as drawn, in a SEG/RTSTRUCT only "
                 "these segments/ROIs are read");
  app.add_option("--key-slices", args.key_slices,
                 "Key slices for every label, e.g. 0,5,12 or 0-40:5 "
                 "(default: per label, the slices where it is drawn)");
  app.add_option("--method", args.method,
                 "auto (per label, the best of nearest-slice copy, linear "
                 "stacking, their blend and the exact refinement at "
                 "predicting the label's own held-out key slices), direct "
                 "(exact minimiser), cg (the paper's conjugate gradient) or "
                 "linear (no refinement)")
      ->capture_default_str();
  app.add_option("--iterations", args.iterations,
                 "CG iterations (default 15, as in the paper)");
  app.add_option("--factor", args.factor,
                 "Insert N-1 slices per reference slice gap (default 1: the "
                 "reference grid)");
  app.add_option("--spacing", args.spacing, "Target output slice spacing, mm");
  app.add_option("--band", args.band,
                 "Radius in mm of the band of exact 2D distances (default 16 "
                 "pixels)");
  app.add_option("--adaptivity", args.adaptivity,
                 "Mesh adaptivity in [0,1]: higher gives fewer triangles")
      ->capture_default_str();
  app.add_option("--out", args.out, "Output folder (created if missing)")
      ->required();
  app.add_option("--mesh", args.mesh,
                 "Mesh formats, one file per label (label-<L>.<ext>): any of "
                 "stl,ply,obj, or none")
      ->capture_default_str();
  app.add_option("--volume", args.volume,
                 "Label map formats (labels.nii.gz, labels.nrrd): any of "
                 "nii,nrrd, or none")
      ->capture_default_str();
  app.add_flag("--seg", args.seg,
               "Write the filled labels as a multi-segment DICOM SEG "
               "(DIR/seg.dcm) with the input's segment names, colours and "
               "codes");
  app.add_flag("--rtstruct", args.rtstruct,
               "Write the filled labels as an RTSTRUCT of closed planar "
               "contours (DIR/rtstruct.dcm; default for RTSTRUCT input)");
  app.add_flag("--no-rtstruct", args.no_rtstruct,
               "No RTSTRUCT, even for RTSTRUCT input");
  app.add_option("--uid-root", args.uid_root,
                 "UID root of the DICOM outputs (default 2.25 UUIDs)");
  app.add_flag("--random-uids", args.random_uids,
               "Fresh UIDs on every run (default: derived from the input "
               "and the parameters, so a rerun replaces its objects)");
  app.add_option("--report", args.report, "Write a JSON report to this file");
  app.add_option("--threads", args.threads, "Worker threads (0 = all cores)")
      ->capture_default_str();
  app.add_flag("--quiet", args.quiet, "No summary");
}

absl::StatusOr<FillJobSpec> BuildFillJobSpec(const FillArguments& args) {
  FillJobSpec spec;
  spec.segmentation = args.segmentation;
  spec.reference = args.reference;
  spec.series_instance_uid = args.series_uid;
  spec.output_dir = args.out;
  for (absl::string_view item :
       absl::StrSplit(args.labels, ',', absl::SkipEmpty())) {
    int label = 0;
    if (!absl::SimpleAtoi(item, &label) || label < 1 || label > 65535) {
      return absl::InvalidArgumentError(
          absl::StrCat("--labels: '", item, "' is not a label (1..65535)"));
    }
    spec.fill.labels.push_back(label);
  }
  if (!args.key_slices.empty()) {
    absl::StatusOr<std::vector<int64_t>> keys = ParseSliceList(args.key_slices);
    if (!keys.ok()) return keys.status();
    spec.fill.key_slices = *std::move(keys);
  }
  spec.fill.method = FillMethod::kSolver;
  if (args.method == "auto") {
    spec.fill.method = FillMethod::kAuto;
  } else if (args.method == "direct") {
    spec.fill.solver.method = SolverMethod::kDirect;
  } else if (args.method == "cg") {
    spec.fill.solver.method = SolverMethod::kConjugateGradient;
  } else if (args.method == "linear") {
    spec.fill.solver.method = SolverMethod::kLinear;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("--method: unknown method '", args.method,
                     "' (choose from auto, direct, cg, linear)"));
  }
  if (args.iterations.has_value()) {
    if (*args.iterations < 0) {
      return absl::InvalidArgumentError("--iterations must be >= 0");
    }
    spec.fill.solver.max_iterations = *args.iterations;
  }
  if (args.factor.has_value() && args.spacing.has_value()) {
    return absl::InvalidArgumentError(
        "--factor and --spacing are alternatives; give one");
  }
  spec.fill.z_resolution.factor = args.factor;
  spec.fill.z_resolution.spacing_mm = args.spacing;
  if (args.band.has_value()) {
    if (!(*args.band > 0)) {
      return absl::InvalidArgumentError("--band must be positive (mm)");
    }
    spec.fill.band_radius_mm = *args.band;
  }
  spec.mesh_adaptivity = args.adaptivity;
  absl::StatusOr<std::vector<std::string>> mesh =
      ParseFormats(args.mesh, {"stl", "ply", "obj"}, "--mesh");
  if (!mesh.ok()) return mesh.status();
  spec.mesh_formats = *mesh;
  absl::StatusOr<std::vector<std::string>> volume =
      ParseFormats(args.volume, {"nii", "nrrd"}, "--volume");
  if (!volume.ok()) return volume.status();
  spec.volume_formats = *volume;
  if (args.rtstruct && args.no_rtstruct) {
    return absl::InvalidArgumentError(
        "--rtstruct and --no-rtstruct contradict each other");
  }
  spec.write_seg = args.seg;
  if (args.rtstruct) spec.write_rtstruct = true;
  if (args.no_rtstruct) spec.write_rtstruct = false;
  spec.uid_root = args.uid_root;
  spec.random_uids = args.random_uids;
  if (args.threads < 0) {
    return absl::InvalidArgumentError("--threads must be >= 0");
  }
  if (absl::Status s = ValidateFillJobSpec(spec); !s.ok()) return s;
  return spec;
}

int ExecuteFill(const FillArguments& args) {
  absl::StatusOr<FillJobSpec> spec = BuildFillJobSpec(args);
  if (!spec.ok()) {
    std::fprintf(stderr, "interslice: error: %s\n",
                 std::string(spec.status().message()).c_str());
    return 1;
  }
  ComputeContext context;
  context.threads = args.threads;
  absl::StatusOr<FillJobReport> report = RunFillJob(*spec, context);
  if (!report.ok()) {
    std::fprintf(stderr, "interslice: error: %s\n",
                 std::string(report.status().message()).c_str());
    return 1;
  }
  for (const std::string& w : report->warnings) {
    std::fprintf(stderr, "interslice: warning: %s\n", w.c_str());
  }
  if (!args.report.empty()) {
    std::ofstream out(args.report);
    out << FillJobReportToJson(*report) << "\n";
    if (!out.good()) {
      std::fprintf(stderr, "interslice: error: cannot write the report %s\n",
                   args.report.c_str());
      return 1;
    }
  }
  if (!args.quiet) {
    const Grid& g = report->output_grid;
    std::printf(
        "interslice: filled %zu label(s) (%s) on %lld x %lld x %lld voxels, "
        "%zu file(s) in %s\n",
        report->per_label.size(), report->method.c_str(),
        static_cast<long long>(g.size[0]), static_cast<long long>(g.size[1]),
        static_cast<long long>(g.size[2]), report->artifacts.size(),
        args.out.c_str());
    for (const LabelFillInfo& info : report->per_label) {
      std::printf("  label %-5d %zu key slices (%lld drawn), %lld voxels\n",
                  info.label, info.key_slices.size(),
                  static_cast<long long>(info.drawn_slices),
                  static_cast<long long>(info.output_voxels));
    }
    std::printf(
        "  time      read %.2fs fill %.2fs mesh %.2fs write %.2fs; gap voxels "
        "closed %lld\n",
        report->read_seconds, report->fill_seconds, report->mesh_seconds,
        report->write_seconds,
        static_cast<long long>(report->gap_voxels_closed));
  }
  return 0;
}

}  // namespace interslice::client
