#include "job/options.h"

#include <algorithm>
#include <cmath>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "core/dicom_out/dicom_writer.h"
#include "job/errors.h"

namespace interslice::job {
namespace {

// CG iteration cap when only a tolerance is given: far beyond what any
// reasonable problem needs, but it still bounds the run.
constexpr int kToleranceIterationCap = 100000;
// A slice list may name at most this many slices (bounds "0-2000000000").
constexpr int64_t kMaxListedSlices = 1 << 20;
// Insertion factors beyond this are refused before any work (a factor of
// 1024 already turns a 5 mm gap into 5 um slices).
constexpr int64_t kMaxFactor = 1024;

using IO = InterpolationOptions;
using FO = FillJobOptions;

constexpr OptionDef<IO> kInterpolationOptions[] = {
    {"threshold", "spec.threshold", ValueKind::kNumber, &IO::threshold,
     "Object threshold in modality units (HU for CT): voxels with value >= "
     "threshold are inside",
     kEveryDoor, /*required=*/true},
    {"upper", "spec.upper_threshold", ValueKind::kNumber, &IO::upper,
     "Optional upper threshold (HU): inside means threshold <= value <= "
     "upper"},
    {"series_uid", "spec.series_instance_uid", ValueKind::kText,
     &IO::series_uid,
     "SeriesInstanceUID to use when the input holds several series",
     kCommandLine | kWire},
    {"roi", "spec.roi", ValueKind::kBox, &IO::roi,
     "Region of interest x0,y0,z0,x1,y1,z1: a half-open voxel box in the "
     "input's index space (z in sorted slice order)"},
    {"roi_mm", "spec.roi_mm", ValueKind::kMmBox, &IO::roi_mm,
     "Region of interest x0,y0,z0,x1,y1,z1 in patient coordinates (LPS mm, "
     "two opposite corners in any order, as a viewer's ROI tool gives "
     "them): the smallest voxel box covering every voxel centre inside, for "
     "any orientation; excludes --roi"},
    {"method", "spec.method", ValueKind::kText, &IO::method,
     "direct (exact minimiser), cg (the paper's conjugate gradient), linear "
     "(no refinement) or morph (registration-based stacking along a smooth, "
     "C1-in-z trajectory, values interpolated without overshoot; no solver, "
     "docs/eval/candidates.md)"},
    {"iterations", "spec.max_iterations", ValueKind::kInteger, &IO::iterations,
     "CG iterations (default 15, as in the paper)"},
    {"tolerance", "spec.tolerance", ValueKind::kNumber, &IO::tolerance,
     "CG: stop at this relative residual |r|/|r0|"},
    {"energy_units", "spec.energy_units", ValueKind::kText, &IO::energy_units,
     "voxel (the paper's, default) or mm"},
    {"factor", "spec.insertion_factor", ValueKind::kInteger, &IO::factor,
     "Insert N-1 slices per gap (N >= 1)"},
    {"spacing", "spec.slice_spacing_mm", ValueKind::kNumber, &IO::spacing,
     "Target output slice spacing in mm (default: the in-plane spacing, i.e. "
     "isotropic)"},
    {"output_series", "spec.derived_series.contents", ValueKind::kList,
     &IO::output_series,
     "DICOM objects to write, any of intensity (image series "
     "DIR/series-intensity/), distance (Parametric Map DIR/distance.dcm, mm), "
     "mask (SEG DIR/seg.dcm); a SEG or distance map also writes the "
     "intensity series it references"},
    {"seg", "spec.segmentation.enabled", ValueKind::kFlag, &IO::seg,
     "Write the mask as a binary DICOM SEG (DIR/seg.dcm; same as "
     "--output-series mask)"},
    {"segment_label", "spec.segmentation.segment_label", ValueKind::kText,
     &IO::segment_label,
     "Label of the SEG's segment, e.g. Brain (default: Bone for CT at >= 200 "
     "HU, else 'Region above N <units>'; with --segment-code, its meaning)"},
    {"segment_code", "spec.segmentation.segment_code", ValueKind::kText,
     &IO::segment_code,
     "Coded type of the SEG's segment as scheme:value:meaning, e.g. "
     "SCT:12738006:Brain (default: SCT:272673000:Bone for CT at >= 200 HU, "
     "else SCT:91723000:Anatomical Structure)"},
    {"dicom_compression", "spec.derived_series.pixel_compression",
     ValueKind::kText, &IO::dicom_compression,
     "Pixel data of the DICOM intensity series: none (native) or rle (RLE "
     "Lossless: the same values, fewer bytes)"},
    {"dicom_layout", "spec.derived_series.layout", ValueKind::kText,
     &IO::dicom_layout,
     "Layout of the DICOM intensity series: classic (one CT/MR image per "
     "slice, DIR/series-intensity/IM00001.dcm ...) or enhanced (one Enhanced "
     "CT or Enhanced MR multi-frame instance, "
     "DIR/series-intensity/enhanced.dcm; CT and MR sources only)"},
    {"intensity_method", "spec.derived_series.intensity_method",
     ValueKind::kText, &IO::intensity_method,
     "Grey values of the DICOM intensity series between source slices: morph "
     "(carried along the motion between neighbouring slices, locally linear "
     "where the registration is unreliable; docs/eval/intensity.md) or "
     "linear (the two bracketing slices blended)"},
    {"uid_root", "spec.uid_root", ValueKind::kText, &IO::uid_root,
     "UID root for the new DICOM UIDs (default 2.25 + UUID)"},
    {"random_uids", "spec.random_uids", ValueKind::kFlag, &IO::random_uids,
     "New random DICOM UIDs on every run (default: derived from the source "
     "and the job, so a rerun replaces its results)"},
    {"series_number_base", "spec.derived_series.series_number",
     ValueKind::kInteger, &IO::series_number_base,
     "Series numbers of the DICOM outputs: intensity BASE+1, distance "
     "BASE+2, SEG BASE+3, Encapsulated STL BASE+4, previews BASE+6 (default "
     "1000 x the source's SeriesNumber)"},
    {"multiframe_volume", "spec.multiframe_volume", ValueKind::kText,
     &IO::multiframe_volume,
     "Which volume of a multi-frame series to read, as named in the error "
     "that lists them"},
    {"strict_spacing", "spec.strict_spacing", ValueKind::kFlag,
     &IO::strict_spacing,
     "Fail on non-uniform slice spacing (missing slices) instead of placing "
     "each slice on the nearest output slice"},
    {"strict_frame_of_reference", "spec.strict_frame_of_reference",
     ValueKind::kFlag, &IO::strict_frame_of_reference,
     "Fail when the slices' FrameOfReferenceUIDs differ (e.g. an anonymiser "
     "gave each file its own) instead of reading them as one stack when "
     "their geometry is one, with a note in the report"},
    {"slab_deconvolution", "spec.slab_deconvolution", ValueKind::kFlag,
     &IO::slab_deconvolution,
     "Thick slices: contour an estimate of the thin object at each slice "
     "position (slab deconvolution by the series' SliceThickness) instead of "
     "the slab-averaged slices (docs/eval/candidates.md)"},
    {"band", "spec.band_radius_mm", ValueKind::kNumber, &IO::band,
     "Radius in mm of the band of exact 2D distances (default 16 pixels)"},
    {"adaptivity", "spec.mesh_adaptivity", ValueKind::kNumber, &IO::adaptivity,
     "Mesh adaptivity in [0,1]: higher gives fewer triangles"},
    {"dicom_mesh_adaptivity", "spec.dicom_mesh_adaptivity", ValueKind::kNumber,
     &IO::dicom_mesh_adaptivity,
     "Adaptivity in [0,1] of the mesh stored in the study as Encapsulated STL "
     "(default 0: as surface.stl; 1 takes the CT phantom's from 133 to 20 MB, "
     "up to 1.8 mm off; the report's dicom_mesh gives the measured distance "
     "from the full surface); surface.stl keeps --adaptivity"},
    {"dicom_mesh_max_mb", "spec.dicom_mesh_max_mb", ValueKind::kNumber,
     &IO::dicom_mesh_max_mb,
     "Size cap in MB (10^6 bytes) of the Encapsulated STL object (default 25; "
     "0 = none): a larger mesh is simplified by quadric edge collapse "
     "(meshoptimizer) after --dicom-mesh-adaptivity, and the report's "
     "dicom_mesh gives its triangles and error estimate; surface.stl is never "
     "capped"},
    {"mesh", "spec.outputs.mesh_formats", ValueKind::kList, &IO::mesh,
     "Mesh formats: any of stl,ply,obj, or none"},
    {"volume", "spec.outputs.volume_formats", ValueKind::kList, &IO::volume,
     "Volume formats: any of nii (.nii.gz), nrrd, nii-uncompressed (.nii: no "
     "compression time), or none"},
    {"previews", "spec.previews.formats", ValueKind::kList, &IO::previews,
     "Previews of what the job made (axial, coronal, sagittal planes with the "
     "outline and the original slices marked, a 3D front view, each with a "
     "legend): png (DIR/previews/*.png), dicom (a Secondary Capture series "
     "DIR/previews-dicom/ in the source's study, sent with the other DICOM "
     "results), both, or none"},
};

constexpr OptionDef<FO> kFillOptions[] = {
    {"series_uid", "spec.series_instance_uid", ValueKind::kText,
     &FO::series_uid,
     "SeriesInstanceUID of the reference when it holds several",
     kCommandLine | kWire},
    {"labels", "spec.fill.labels", ValueKind::kIntegerList, &FO::labels,
     "Labels to fill, e.g. 1,3,7 (default: all); in a label map the others "
     "are copied as drawn, in a SEG/RTSTRUCT only these segments/ROIs are "
     "read"},
    {"key_slices", "spec.fill.key_slices", ValueKind::kIntegerList,
     &FO::key_slices,
     "Key slices for every label, e.g. 0,5,12 or 0-40:5 (default: per label, "
     "the slices where it is drawn)"},
    {"method", "spec.method", ValueKind::kText, &FO::method,
     "auto (per label, the best of nearest-slice copy, linear stacking, "
     "their blend, the exact refinement and the morph at predicting the "
     "label's own held-out key slices), direct (exact minimiser), cg (the "
     "paper's conjugate gradient), linear (no refinement) or morph "
     "(registration of the label's key slices, carried along a smooth "
     "trajectory)"},
    {"iterations", "spec.max_iterations", ValueKind::kInteger, &FO::iterations,
     "CG iterations (default 15, as in the paper)"},
    {"tolerance", "spec.tolerance", ValueKind::kNumber, &FO::tolerance,
     "CG: stop at this relative residual |r|/|r0|"},
    {"energy_units", "spec.energy_units", ValueKind::kText, &FO::energy_units,
     "voxel (the paper's, default) or mm"},
    {"factor", "spec.insertion_factor", ValueKind::kInteger, &FO::factor,
     "Insert N-1 slices per reference slice gap (default 1: the reference "
     "grid)"},
    {"spacing", "spec.slice_spacing_mm", ValueKind::kNumber, &FO::spacing,
     "Target output slice spacing, mm"},
    {"band", "spec.band_radius_mm", ValueKind::kNumber, &FO::band,
     "Radius in mm of the band of exact 2D distances (default 16 pixels)"},
    {"adaptivity", "spec.mesh_adaptivity", ValueKind::kNumber, &FO::adaptivity,
     "Mesh adaptivity in [0,1]: higher gives fewer triangles"},
    {"mesh", "spec.outputs.mesh_formats", ValueKind::kList, &FO::mesh,
     "Mesh formats, one file per label (label-<L>.<ext>): any of stl,ply,obj, "
     "or none"},
    {"volume", "spec.outputs.volume_formats", ValueKind::kList, &FO::volume,
     "Label map formats (labels.nii.gz, labels.nrrd): any of nii,nrrd, or "
     "none"},
    {"seg", "spec.fill.seg", ValueKind::kFlag, &FO::seg,
     "Write the filled labels as a multi-segment DICOM SEG (DIR/seg.dcm) "
     "with the input's segment names, colours and codes"},
    {"rtstruct", "spec.fill.rtstruct", ValueKind::kFlag, &FO::rtstruct,
     "Write the filled labels as an RTSTRUCT of closed planar contours "
     "(DIR/rtstruct.dcm; default: on for RTSTRUCT input)"},
    {"intensity_method", "spec.fill.intensity_method", ValueKind::kText,
     &FO::intensity_method,
     "Grey values of the intensity series a finer grid (--factor, --spacing) "
     "writes for the DICOM outputs to lie on: morph or linear (as run)"},
    {"label_names", "spec.fill.label_names_file", ValueKind::kText,
     &FO::label_names,
     "Names, colours and codes of a label map's labels for seg.dcm and "
     "rtstruct.dcm: a colour table (.csv or .txt, one label a line: "
     "label,name,R,G,B[,scheme^value^meaning]) or a JSON sidecar (.json); "
     "default: a .seg.nrrd's own segments, else \"Label N\". Label maps "
     "only (a SEG or RTSTRUCT names its segments itself)",
     kCommandLine | kWire},
    {"uid_root", "spec.uid_root", ValueKind::kText, &FO::uid_root,
     "UID root of the DICOM outputs (default 2.25 UUIDs)"},
    {"random_uids", "spec.random_uids", ValueKind::kFlag, &FO::random_uids,
     "Fresh UIDs on every run (default: derived from the input and the "
     "parameters, so a rerun replaces its objects)"},
    {"previews", "spec.previews.formats", ValueKind::kList, &FO::previews,
     "Previews of the fill (axial, coronal, sagittal planes with each filled "
     "label outlined in its colour and the key slices marked, a 3D front "
     "view, each with a legend): png (DIR/previews/*.png), dicom (a "
     "Secondary Capture series DIR/previews-dicom/ in the reference's "
     "study), both, or none"},
};

template <typename Options>
const OptionDef<Options>* Find(std::span<const OptionDef<Options>> table,
                               absl::string_view key) {
  for (const OptionDef<Options>& def : table) {
    if (def.key == key) return &def;
  }
  return nullptr;
}

absl::StatusOr<bool> ParseFlag(absl::string_view key, absl::string_view text) {
  const std::string t = absl::AsciiStrToLower(absl::StripAsciiWhitespace(text));
  if (t == "true" || t == "yes" || t == "on" || t == "1") return true;
  if (t == "false" || t == "no" || t == "off" || t == "0") return false;
  return OptionError(key, absl::StrCat("expected true or false, got '",
                                       std::string(text), "'"));
}

template <typename Options>
absl::Status Set(std::span<const OptionDef<Options>> table, Options& options,
                 absl::string_view key, absl::string_view text) {
  const OptionDef<Options>* def = Find(table, key);
  if (def == nullptr) return OptionError(key, "unknown option");
  const std::string value(absl::StripAsciiWhitespace(text));
  struct Visitor {
    Options& o;
    absl::string_view key;
    const std::string& value;
    absl::Status operator()(std::string Options::*m) const {
      o.*m = value;
      return absl::OkStatus();
    }
    absl::Status operator()(bool Options::*m) const {
      absl::StatusOr<bool> v = ParseFlag(key, value);
      if (!v.ok()) return v.status();
      o.*m = *v;
      return absl::OkStatus();
    }
    absl::Status operator()(std::optional<bool> Options::*m) const {
      absl::StatusOr<bool> v = ParseFlag(key, value);
      if (!v.ok()) return v.status();
      o.*m = *v;
      return absl::OkStatus();
    }
    absl::Status Number(double* out) const {
      if (!absl::SimpleAtod(value, out)) {
        return OptionError(
            key, absl::StrCat("expected a number, got '", value, "'"));
      }
      return absl::OkStatus();
    }
    absl::Status operator()(double Options::*m) const {
      return Number(&(o.*m));
    }
    absl::Status operator()(std::optional<double> Options::*m) const {
      double v = 0;
      if (absl::Status s = Number(&v); !s.ok()) return s;
      o.*m = v;
      return absl::OkStatus();
    }
    absl::Status operator()(std::optional<int64_t> Options::*m) const {
      int64_t v = 0;
      if (!absl::SimpleAtoi(value, &v)) {
        return OptionError(
            key, absl::StrCat("expected an integer, got '", value, "'"));
      }
      o.*m = v;
      return absl::OkStatus();
    }
  };
  return std::visit(Visitor{options, key, value}, def->member);
}

// A comma-separated list of names from `allowed`, or "none" / empty for no
// entry; repeats are dropped.
absl::StatusOr<std::vector<std::string>> ParseNames(
    const std::string& text, const std::vector<std::string>& allowed,
    absl::string_view key) {
  std::vector<std::string> out;
  if (text.empty() || text == "none") return out;
  for (absl::string_view item : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    std::string value(absl::StripAsciiWhitespace(item));
    if (std::find(allowed.begin(), allowed.end(), value) == allowed.end()) {
      return OptionError(
          key, absl::StrCat("unknown value '", value, "' (choose from ",
                            absl::StrJoin(allowed, ", "), ", or none)"));
    }
    if (std::find(out.begin(), out.end(), value) == out.end()) {
      out.push_back(value);
    }
  }
  return out;
}

absl::StatusOr<VoxelBox> ParseRoi(const std::string& text) {
  const std::vector<std::string> parts = absl::StrSplit(text, ',');
  if (parts.size() != 6) {
    return OptionError("roi",
                       "expected six integers x0,y0,z0,x1,y1,z1 (a half-open "
                       "voxel box)");
  }
  int64_t v[6];
  for (int n = 0; n < 6; ++n) {
    if (!absl::SimpleAtoi(absl::StripAsciiWhitespace(parts[n]), &v[n])) {
      return OptionError("roi",
                         absl::StrCat("'", parts[n], "' is not an integer"));
    }
  }
  return VoxelBox{{v[0], v[1], v[2]}, {v[3], v[4], v[5]}};
}

// Two opposite corners in any order -> the box.
absl::StatusOr<PhysicalBox> ParseRoiMm(const std::string& text) {
  const std::vector<std::string> parts = absl::StrSplit(text, ',');
  if (parts.size() != 6) {
    return OptionError("roi_mm",
                       "expected six numbers x0,y0,z0,x1,y1,z1 (two opposite "
                       "corners in LPS mm)");
  }
  double v[6];
  for (int n = 0; n < 6; ++n) {
    if (!absl::SimpleAtod(absl::StripAsciiWhitespace(parts[n]), &v[n]) ||
        !std::isfinite(v[n])) {
      return OptionError(
          "roi_mm", absl::StrCat("'", parts[n], "' is not a finite number"));
    }
  }
  PhysicalBox box;
  for (int a = 0; a < 3; ++a) {
    box.min[a] = std::min(v[a], v[a + 3]);
    box.max[a] = std::max(v[a], v[a + 3]);
  }
  return box;
}

absl::StatusOr<SolverMethod> ParseSolverMethod(const std::string& name,
                                               absl::string_view key,
                                               absl::string_view choices) {
  for (SolverMethod m :
       {SolverMethod::kDirect, SolverMethod::kConjugateGradient,
        SolverMethod::kLinear, SolverMethod::kMorph}) {
    if (SolverMethodName(m) == name) return m;
  }
  return OptionError(key,
                     absl::StrCat("unknown method '", name, "' (choose from ",
                                  std::string(choices), ")"));
}

absl::StatusOr<EnergyUnits> ParseEnergyUnits(const std::string& name) {
  for (EnergyUnits u : {EnergyUnits::kVoxel, EnergyUnits::kMillimetre}) {
    if (EnergyUnitsName(u) == name) return u;
  }
  return OptionError("energy_units", absl::StrCat("unknown units '", name,
                                                  "' (choose from voxel, mm)"));
}

// Iterations and tolerance of the solver, shared by both kinds of job.
absl::Status SetIterations(const std::optional<int64_t>& iterations,
                           const std::optional<double>& tolerance,
                           SolverOptions* solver) {
  if (iterations.has_value()) {
    if (*iterations < 0 || *iterations > std::numeric_limits<int>::max()) {
      return OptionError("iterations", "must be >= 0");
    }
    solver->max_iterations = static_cast<int>(*iterations);
  } else if (tolerance.has_value()) {
    solver->max_iterations = kToleranceIterationCap;
  }
  if (tolerance.has_value()) {
    if (!(*tolerance > 0) || !std::isfinite(*tolerance)) {
      return OptionError("tolerance", "must be positive");
    }
    solver->tolerance = *tolerance;
  }
  return absl::OkStatus();
}

absl::Status SetZResolution(const std::optional<int64_t>& factor,
                            const std::optional<double>& spacing,
                            ZResolution* z) {
  if (factor.has_value() && spacing.has_value()) {
    return OptionError("factor",
                       "factor and spacing are alternatives; give one");
  }
  if (factor.has_value()) {
    if (*factor < 1 || *factor > kMaxFactor) {
      return OptionError("factor", absl::StrCat("must be 1..", kMaxFactor));
    }
    z->factor = static_cast<int>(*factor);
  }
  if (spacing.has_value()) {
    if (!(*spacing > 0) || !std::isfinite(*spacing)) {
      return OptionError("spacing", "must be positive (mm)");
    }
    z->spacing_mm = *spacing;
  }
  return absl::OkStatus();
}

absl::Status CheckBand(const std::optional<double>& band) {
  if (band.has_value() && !(*band > 0 && std::isfinite(*band))) {
    return OptionError("band", "must be positive (mm)");
  }
  return absl::OkStatus();
}

absl::Status CheckIntensityMethod(const std::string& method) {
  if (method != "morph" && method != "linear") {
    return OptionError("intensity_method",
                       absl::StrCat("unknown value '", method,
                                    "' (choose from morph, linear)"));
  }
  return absl::OkStatus();
}

absl::Status CheckAdaptivity(double adaptivity) {
  if (!(adaptivity >= 0 && adaptivity <= 1)) {
    return OptionError("adaptivity", "must be in [0, 1]");
  }
  return absl::OkStatus();
}

}  // namespace

std::span<const OptionDef<InterpolationOptions>> InterpolationOptionTable() {
  return kInterpolationOptions;
}
std::span<const OptionDef<FillJobOptions>> FillOptionTable() {
  return kFillOptions;
}

const OptionDef<InterpolationOptions>* FindOption(
    std::span<const OptionDef<InterpolationOptions>> table,
    absl::string_view key) {
  return Find(table, key);
}
const OptionDef<FillJobOptions>* FindOption(
    std::span<const OptionDef<FillJobOptions>> table, absl::string_view key) {
  return Find(table, key);
}

std::string CommandLineName(absl::string_view key) {
  std::string name = absl::StrCat("--", std::string(key));
  std::replace(name.begin(), name.end(), '_', '-');
  return name;
}

absl::Status SetOption(InterpolationOptions& options, absl::string_view key,
                       absl::string_view text) {
  return Set(InterpolationOptionTable(), options, key, text);
}
absl::Status SetOption(FillJobOptions& options, absl::string_view key,
                       absl::string_view text) {
  return Set(FillOptionTable(), options, key, text);
}

absl::StatusOr<std::vector<int64_t>> ParseSliceList(absl::string_view text) {
  std::vector<int64_t> out;
  for (absl::string_view item : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    item = absl::StripAsciiWhitespace(item);
    const auto bad = [&] {
      return OptionError(
          "key_slices",
          absl::StrCat("'", item,
                       "' is not a slice index, a range a-b or a range with "
                       "step a-b:s"));
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
  if (out.empty()) return OptionError("key_slices", "no slice given");
  std::set<int64_t> seen;
  for (int64_t k : out) {
    if (!seen.insert(k).second) {
      return OptionError("key_slices",
                         absl::StrCat("slice ", k, " is repeated"));
    }
  }
  return out;
}

absl::StatusOr<JobSpec> BuildJobSpec(const InterpolationOptions& o) {
  JobSpec spec;
  spec.inputs = o.inputs;
  spec.output_dir = o.out;
  spec.series_instance_uid = o.series_uid;
  if (!o.threshold.has_value()) {
    return OptionError("threshold", "missing (it is required)");
  }
  if (!std::isfinite(*o.threshold)) {
    return OptionError("threshold", "must be a finite number");
  }
  spec.lower_threshold = static_cast<float>(*o.threshold);
  if (o.upper.has_value()) {
    if (!std::isfinite(*o.upper) || *o.upper < *o.threshold) {
      return OptionError("upper", "must be finite and not below the threshold");
    }
    spec.upper_threshold = static_cast<float>(*o.upper);
  }
  if (!o.roi.empty()) {
    absl::StatusOr<VoxelBox> roi = ParseRoi(o.roi);
    if (!roi.ok()) return roi.status();
    spec.roi = *roi;
  }
  if (!o.roi_mm.empty()) {
    if (!o.roi.empty()) {
      return OptionError("roi_mm",
                         "cannot be combined with roi: give the region of "
                         "interest either in voxels (roi) or in mm (roi_mm)");
    }
    absl::StatusOr<PhysicalBox> roi_mm = ParseRoiMm(o.roi_mm);
    if (!roi_mm.ok()) return roi_mm.status();
    spec.roi_mm = *roi_mm;
  }
  absl::StatusOr<SolverMethod> method =
      ParseSolverMethod(o.method, "method", "direct, cg, linear, morph");
  if (!method.ok()) return method.status();
  spec.solver.method = *method;
  if (absl::Status s = SetIterations(o.iterations, o.tolerance, &spec.solver);
      !s.ok()) {
    return s;
  }
  absl::StatusOr<EnergyUnits> units = ParseEnergyUnits(o.energy_units);
  if (!units.ok()) return units.status();
  spec.solver.units = *units;
  if (absl::Status s = SetZResolution(o.factor, o.spacing, &spec.z_resolution);
      !s.ok()) {
    return s;
  }
  spec.strict_spacing = o.strict_spacing;
  spec.strict_frame_of_reference = o.strict_frame_of_reference;
  spec.slab_deconvolution = o.slab_deconvolution;
  absl::StatusOr<std::vector<std::string>> series = ParseNames(
      o.output_series, {"mask", "distance", "intensity"}, "output_series");
  if (!series.ok()) return series.status();
  spec.output_series = *series;
  if (o.dicom_compression != "none" && o.dicom_compression != "rle") {
    return OptionError("dicom_compression",
                       absl::StrCat("unknown value '", o.dicom_compression,
                                    "' (choose from none, rle)"));
  }
  spec.dicom_compression = o.dicom_compression;
  if (o.dicom_layout != "classic" && o.dicom_layout != "enhanced") {
    return OptionError("dicom_layout",
                       absl::StrCat("unknown value '", o.dicom_layout,
                                    "' (choose from classic, enhanced)"));
  }
  spec.dicom_layout = o.dicom_layout;
  if (absl::Status s = CheckIntensityMethod(o.intensity_method); !s.ok()) {
    return s;
  }
  spec.intensity_method = o.intensity_method;
  spec.write_seg = o.seg;
  const bool writes_seg =
      o.seg || std::find(spec.output_series.begin(), spec.output_series.end(),
                         "mask") != spec.output_series.end();
  for (const auto& [key, value] :
       {std::pair<absl::string_view, const std::string*>{"segment_label",
                                                         &o.segment_label},
        {"segment_code", &o.segment_code}}) {
    if (!value->empty() && !writes_seg) {
      return OptionError(key,
                         "names the SEG's segment, but no SEG is written (add "
                         "seg, or mask to output_series)");
    }
  }
  if (!o.segment_label.empty()) {
    if (absl::Status s = ValidateSegmentLabel(o.segment_label); !s.ok()) {
      return OptionError("segment_label", s.message());
    }
    spec.segment_label = o.segment_label;
  }
  if (!o.segment_code.empty()) {
    if (absl::Status s = ParseCodedConcept(o.segment_code).status(); !s.ok()) {
      return OptionError("segment_code", s.message());
    }
    spec.segment_code = o.segment_code;
  }
  spec.uid_root = o.uid_root;
  spec.random_uids = o.random_uids;
  if (o.series_number_base.has_value()) {
    if (*o.series_number_base < 1 ||
        *o.series_number_base > kMaxSeriesNumberBase) {
      return OptionError(
          "series_number_base",
          absl::StrCat("must be between 1 and ", kMaxSeriesNumberBase));
    }
    spec.series_number_base = static_cast<int>(*o.series_number_base);
  }
  spec.multiframe_volume = o.multiframe_volume;
  if (absl::Status s = CheckBand(o.band); !s.ok()) return s;
  if (o.band.has_value()) spec.band_radius_mm = *o.band;
  if (absl::Status s = CheckAdaptivity(o.adaptivity); !s.ok()) return s;
  spec.mesh_adaptivity = o.adaptivity;
  if (o.dicom_mesh_adaptivity.has_value()) {
    if (!(*o.dicom_mesh_adaptivity >= 0 && *o.dicom_mesh_adaptivity <= 1)) {
      return OptionError("dicom_mesh_adaptivity", "must be in [0, 1]");
    }
    spec.dicom_mesh_adaptivity = *o.dicom_mesh_adaptivity;
  }
  if (o.dicom_mesh_max_mb.has_value()) {
    const double mb = *o.dicom_mesh_max_mb;
    if (!(mb == 0 || (mb >= kMinDicomMeshMaxMb && mb <= kMaxDicomMeshMaxMb))) {
      return OptionError(
          "dicom_mesh_max_mb",
          absl::StrCat("must be 0 (no cap) or between ", kMinDicomMeshMaxMb,
                       " and ", kMaxDicomMeshMaxMb, " MB"));
    }
    spec.dicom_mesh_max_mb = mb;
  }
  absl::StatusOr<std::vector<std::string>> mesh =
      ParseNames(o.mesh, {"stl", "ply", "obj"}, "mesh");
  if (!mesh.ok()) return mesh.status();
  spec.mesh_formats = *mesh;
  absl::StatusOr<std::vector<std::string>> volume =
      ParseNames(o.volume, {"nii", "nrrd", "nii-uncompressed"}, "volume");
  if (!volume.ok()) return volume.status();
  spec.volume_formats = *volume;
  absl::StatusOr<std::vector<std::string>> previews =
      ParseNames(o.previews, {"png", "dicom"}, "previews");
  if (!previews.ok()) return previews.status();
  spec.preview_formats = *previews;
  if (absl::Status s = ValidateJobSpec(spec); !s.ok()) return s;
  return spec;
}

absl::StatusOr<FillJobSpec> BuildFillJobSpec(const FillJobOptions& o) {
  FillJobSpec spec;
  spec.segmentation = o.segmentation;
  spec.reference = o.reference;
  spec.output_dir = o.out;
  spec.series_instance_uid = o.series_uid;
  std::set<int> labels;
  for (absl::string_view item :
       absl::StrSplit(o.labels, ',', absl::SkipEmpty())) {
    item = absl::StripAsciiWhitespace(item);
    int label = 0;
    if (!absl::SimpleAtoi(item, &label) || label < 1 || label > 65535) {
      return OptionError("labels",
                         absl::StrCat(item, " is not a label (1..65535)"));
    }
    if (!labels.insert(label).second) {
      return OptionError("labels",
                         absl::StrCat("label ", label, " is repeated"));
    }
    spec.fill.labels.push_back(label);
  }
  if (!o.key_slices.empty()) {
    absl::StatusOr<std::vector<int64_t>> keys = ParseSliceList(o.key_slices);
    if (!keys.ok()) return keys.status();
    spec.fill.key_slices = *std::move(keys);
  }
  if (o.method == "auto") {
    spec.fill.method = FillMethod::kAuto;
  } else {
    absl::StatusOr<SolverMethod> method = ParseSolverMethod(
        o.method, "method", "auto, direct, cg, linear, morph");
    if (!method.ok()) return method.status();
    spec.fill.method = FillMethod::kSolver;
    spec.fill.solver.method = *method;
  }
  if (absl::Status s =
          SetIterations(o.iterations, o.tolerance, &spec.fill.solver);
      !s.ok()) {
    return s;
  }
  absl::StatusOr<EnergyUnits> units = ParseEnergyUnits(o.energy_units);
  if (!units.ok()) return units.status();
  spec.fill.solver.units = *units;
  if (absl::Status s =
          SetZResolution(o.factor, o.spacing, &spec.fill.z_resolution);
      !s.ok()) {
    return s;
  }
  if (absl::Status s = CheckBand(o.band); !s.ok()) return s;
  if (o.band.has_value()) spec.fill.band_radius_mm = *o.band;
  if (absl::Status s = CheckAdaptivity(o.adaptivity); !s.ok()) return s;
  spec.mesh_adaptivity = o.adaptivity;
  absl::StatusOr<std::vector<std::string>> mesh =
      ParseNames(o.mesh, {"stl", "ply", "obj"}, "mesh");
  if (!mesh.ok()) return mesh.status();
  spec.mesh_formats = *mesh;
  absl::StatusOr<std::vector<std::string>> volume =
      ParseNames(o.volume, {"nii", "nrrd"}, "volume");
  if (!volume.ok()) return volume.status();
  spec.volume_formats = *volume;
  absl::StatusOr<std::vector<std::string>> previews =
      ParseNames(o.previews, {"png", "dicom"}, "previews");
  if (!previews.ok()) return previews.status();
  spec.preview_formats = *previews;
  spec.write_seg = o.seg;
  spec.write_rtstruct = o.rtstruct;
  if (absl::Status s = CheckIntensityMethod(o.intensity_method); !s.ok()) {
    return s;
  }
  spec.intensity_method = o.intensity_method;
  spec.uid_root = o.uid_root;
  spec.random_uids = o.random_uids;
  if (!o.label_names.empty()) {
    // The extension selects the reader (core/labels/segment_names.h); the
    // name itself is not echoed (on the wire it is the client's).
    const std::string lower = absl::AsciiStrToLower(o.label_names);
    if (!absl::EndsWith(lower, ".csv") && !absl::EndsWith(lower, ".txt") &&
        !absl::EndsWith(lower, ".json")) {
      return OptionError("label_names",
                         "must name a colour table (.csv, .txt) or a JSON "
                         "sidecar (.json)");
    }
    spec.label_names = o.label_names;
  }
  if (absl::Status s = ValidateFillJobSpec(spec); !s.ok()) return s;
  return spec;
}

}  // namespace interslice::job
