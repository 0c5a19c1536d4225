#include "job/wire.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "job/errors.h"

namespace interslice::job {
namespace {

// The wire's enums and the names the options use for them (the core's
// names, core/solver SolverMethodName and EnergyUnitsName, and the format
// names of core/pipeline's JobSpec).
constexpr std::pair<SolverMethod, v1::SolverMethod> kMethods[] = {
    {SolverMethod::kConjugateGradient, v1::SOLVER_METHOD_CONJUGATE_GRADIENT},
    {SolverMethod::kDirect, v1::SOLVER_METHOD_DIRECT},
    {SolverMethod::kLinear, v1::SOLVER_METHOD_LINEAR},
    {SolverMethod::kMorph, v1::SOLVER_METHOD_MORPH},
};
constexpr std::pair<EnergyUnits, v1::EnergyUnits> kUnits[] = {
    {EnergyUnits::kVoxel, v1::ENERGY_UNITS_VOXEL},
    {EnergyUnits::kMillimetre, v1::ENERGY_UNITS_MILLIMETRE},
};
constexpr std::pair<absl::string_view, v1::VolumeFormat> kVolumeFormats[] = {
    {"nii", v1::VOLUME_FORMAT_NIFTI},
    {"nrrd", v1::VOLUME_FORMAT_NRRD},
    {"nii-uncompressed", v1::VOLUME_FORMAT_NIFTI_UNCOMPRESSED},
};
constexpr std::pair<absl::string_view, v1::IntensityInterpolation>
    kIntensityMethods[] = {
        {"linear", v1::INTENSITY_INTERPOLATION_LINEAR},
        {"morph", v1::INTENSITY_INTERPOLATION_MORPH},
};
constexpr std::pair<absl::string_view, v1::MeshFormat> kMeshFormats[] = {
    {"stl", v1::MESH_FORMAT_STL},
    {"ply", v1::MESH_FORMAT_PLY},
    {"obj", v1::MESH_FORMAT_OBJ},
};
constexpr std::pair<absl::string_view, v1::PreviewFormat> kPreviewFormats[] = {
    {"png", v1::PREVIEW_FORMAT_PNG},
    {"dicom", v1::PREVIEW_FORMAT_DICOM},
};

v1::IntensityInterpolation WireIntensityMethod(const std::string& name) {
  for (const auto& [n, wire] : kIntensityMethods) {
    if (n == name) return wire;
  }
  return v1::INTENSITY_INTERPOLATION_UNSPECIFIED;
}

// The option name of a wire intensity method; UNSPECIFIED gives the
// options' default.
absl::StatusOr<std::string> IntensityMethodName(int wire,
                                                const std::string& unset) {
  if (wire == v1::INTENSITY_INTERPOLATION_UNSPECIFIED) return unset;
  for (const auto& [n, w] : kIntensityMethods) {
    if (w == wire) return std::string(n);
  }
  return OptionError("intensity_method",
                     absl::StrCat("unknown intensity method ", wire));
}

v1::SolverMethod WireMethod(SolverMethod m) {
  for (const auto& [core, wire] : kMethods) {
    if (core == m) return wire;
  }
  return v1::SOLVER_METHOD_UNSPECIFIED;
}

// The option name of a wire method; UNSPECIFIED gives `unset`.
absl::StatusOr<std::string> MethodName(int wire, std::string unset) {
  if (wire == v1::SOLVER_METHOD_UNSPECIFIED) return unset;
  for (const auto& [core, w] : kMethods) {
    if (w == wire) return std::string(SolverMethodName(core));
  }
  return OptionError("method", absl::StrCat("unknown method ", wire));
}

absl::StatusOr<std::string> UnitsName(int wire) {
  if (wire == v1::ENERGY_UNITS_UNSPECIFIED) return std::string("voxel");
  for (const auto& [core, w] : kUnits) {
    if (w == wire) return std::string(EnergyUnitsName(core));
  }
  return OptionError("energy_units", absl::StrCat("unknown units ", wire));
}

template <typename Enum, size_t N>
absl::StatusOr<std::string> FormatNames(
    const google::protobuf::RepeatedField<int>& formats,
    const std::pair<absl::string_view, Enum> (&table)[N],
    absl::string_view key) {
  std::vector<std::string> names;
  for (int f : formats) {
    absl::string_view name;
    for (const auto& [n, w] : table) {
      if (w == f) name = n;
    }
    if (name.empty()) {
      return OptionError(key, absl::StrCat("unknown format ", f));
    }
    names.emplace_back(name);
  }
  // No entry on the wire means none (the selection is present).
  return names.empty() ? std::string("none") : absl::StrJoin(names, ",");
}

template <typename Enum, size_t N>
void AddFormats(const std::vector<std::string>& names,
                const std::pair<absl::string_view, Enum> (&table)[N],
                google::protobuf::RepeatedField<int>* out) {
  for (const std::string& name : names) {
    for (const auto& [n, w] : table) {
      if (n == name) out->Add(w);
    }
  }
}

// The options both kinds share, from the wire.
template <typename Options>
absl::Status CommonFromWire(const v1::JobSpec& p, Options& o) {
  o.series_uid = p.series_instance_uid();
  if (p.has_max_iterations()) o.iterations = p.max_iterations();
  if (p.has_tolerance()) o.tolerance = p.tolerance();
  absl::StatusOr<std::string> units = UnitsName(p.energy_units());
  if (!units.ok()) return units.status();
  o.energy_units = *units;
  switch (p.z_resolution_case()) {
    case v1::JobSpec::kInsertionFactor:
      o.factor = p.insertion_factor();
      break;
    case v1::JobSpec::kSliceSpacingMm:
      o.spacing = p.slice_spacing_mm();
      break;
    default:
      break;
  }
  if (p.has_band_radius_mm()) o.band = p.band_radius_mm();
  o.adaptivity = p.mesh_adaptivity();
  o.uid_root = p.uid_root();
  o.random_uids = p.random_uids();
  // Absent: the options' default (PNG); present and empty: none.
  if (p.has_previews()) {
    absl::StatusOr<std::string> previews =
        FormatNames(p.previews().formats(), kPreviewFormats, "previews");
    if (!previews.ok()) return previews.status();
    o.previews = *previews;
  }
  return absl::OkStatus();
}

template <typename Spec>
void CommonToWire(const Spec& spec, const SolverOptions& solver,
                  const ZResolution& z, double band, v1::JobSpec& p) {
  p.set_series_instance_uid(spec.series_instance_uid);
  p.set_max_iterations(solver.max_iterations);
  if (solver.tolerance > 0) p.set_tolerance(solver.tolerance);
  for (const auto& [core, wire] : kUnits) {
    if (core == solver.units) p.set_energy_units(wire);
  }
  if (z.factor.has_value()) {
    p.set_insertion_factor(*z.factor);
  } else if (z.spacing_mm.has_value()) {
    p.set_slice_spacing_mm(*z.spacing_mm);
  }
  if (band > 0) p.set_band_radius_mm(band);
  p.set_mesh_adaptivity(spec.mesh_adaptivity);
  p.set_uid_root(spec.uid_root);
  p.set_random_uids(spec.random_uids);
  v1::OutputSelection* outputs = p.mutable_outputs();
  AddFormats(spec.volume_formats, kVolumeFormats,
             outputs->mutable_volume_formats());
  AddFormats(spec.mesh_formats, kMeshFormats, outputs->mutable_mesh_formats());
  // Always present, so that "none" travels as none.
  AddFormats(spec.preview_formats, kPreviewFormats,
             p.mutable_previews()->mutable_formats());
}

absl::Status NotForFill(absl::string_view field) {
  return absl::InvalidArgumentError(absl::StrCat(
      "spec.", field, " is not used by fill jobs (spec.fill is set)"));
}

}  // namespace

v1::JobSpec ToWire(const JobSpec& spec) {
  v1::JobSpec p;
  CommonToWire(spec, spec.solver, spec.z_resolution, spec.band_radius_mm, p);
  p.set_threshold(spec.lower_threshold);
  if (spec.upper_threshold.has_value()) {
    p.set_upper_threshold(*spec.upper_threshold);
  }
  if (spec.roi.has_value()) {
    v1::VoxelBox* r = p.mutable_roi();
    r->set_x0(spec.roi->begin[0]);
    r->set_y0(spec.roi->begin[1]);
    r->set_z0(spec.roi->begin[2]);
    r->set_x1(spec.roi->end[0]);
    r->set_y1(spec.roi->end[1]);
    r->set_z1(spec.roi->end[2]);
  }
  if (spec.roi_mm.has_value()) {
    v1::PatientBox* r = p.mutable_roi_mm();
    r->set_x0(spec.roi_mm->min[0]);
    r->set_y0(spec.roi_mm->min[1]);
    r->set_z0(spec.roi_mm->min[2]);
    r->set_x1(spec.roi_mm->max[0]);
    r->set_y1(spec.roi_mm->max[1]);
    r->set_z1(spec.roi_mm->max[2]);
  }
  p.set_method(WireMethod(spec.solver.method));
  p.set_strict_spacing(spec.strict_spacing);
  p.set_strict_frame_of_reference(spec.strict_frame_of_reference);
  p.set_slab_deconvolution(spec.slab_deconvolution);
  if (spec.series_number_base > 0) {
    p.mutable_derived_series()->set_series_number(spec.series_number_base);
  }
  p.set_multiframe_volume(spec.multiframe_volume);
  p.set_dicom_mesh_adaptivity(spec.dicom_mesh_adaptivity);
  p.set_dicom_mesh_max_mb(spec.dicom_mesh_max_mb);
  if (spec.dicom_compression == "rle") {
    p.mutable_derived_series()->set_pixel_compression(
        v1::DICOM_PIXEL_COMPRESSION_RLE_LOSSLESS);
  }
  p.mutable_derived_series()->set_intensity_method(
      WireIntensityMethod(spec.intensity_method));
  if (spec.dicom_layout == "enhanced") {
    p.mutable_derived_series()->set_layout(v1::DICOM_LAYOUT_ENHANCED);
  }
  p.mutable_segmentation()->set_enabled(spec.write_seg);
  p.mutable_segmentation()->set_segment_label(spec.segment_label);
  p.mutable_segmentation()->set_segment_code(spec.segment_code);
  for (const std::string& content : spec.output_series) {
    p.mutable_derived_series()->add_contents(content);
  }
  return p;
}

v1::JobSpec ToWire(const FillJobSpec& spec,
                   const std::string& segmentation_file,
                   const std::string& label_names_file) {
  v1::JobSpec p;
  CommonToWire(spec, spec.fill.solver, spec.fill.z_resolution,
               spec.fill.band_radius_mm, p);
  v1::LabelFill* fill = p.mutable_fill();
  fill->set_segmentation_file(segmentation_file);
  fill->set_label_names_file(label_names_file);
  for (int label : spec.fill.labels) fill->add_labels(label);
  if (spec.fill.key_slices.has_value()) {
    for (int64_t k : *spec.fill.key_slices) fill->add_key_slices(k);
  }
  fill->set_seg(spec.write_seg);
  if (spec.write_rtstruct.has_value()) fill->set_rtstruct(*spec.write_rtstruct);
  fill->set_intensity_method(WireIntensityMethod(spec.intensity_method));
  // Unset method = the fill's default (auto, per label).
  if (spec.fill.method == FillMethod::kSolver) {
    p.set_method(WireMethod(spec.fill.solver.method));
  }
  return p;
}

absl::StatusOr<InterpolationOptions> InterpolationOptionsFromWire(
    const v1::JobSpec& p) {
  InterpolationOptions o;
  if (absl::Status s = CommonFromWire(p, o); !s.ok()) return s;
  if (p.has_threshold()) o.threshold = p.threshold();
  if (p.has_upper_threshold()) o.upper = p.upper_threshold();
  if (p.has_roi()) {
    const v1::VoxelBox& r = p.roi();
    o.roi =
        absl::StrJoin({r.x0(), r.y0(), r.z0(), r.x1(), r.y1(), r.z1()}, ",");
  }
  if (p.has_roi_mm()) {
    const v1::PatientBox& r = p.roi_mm();
    // %.17g: the doubles as sent, back through the option's parser.
    o.roi_mm = absl::StrFormat("%.17g,%.17g,%.17g,%.17g,%.17g,%.17g", r.x0(),
                               r.y0(), r.z0(), r.x1(), r.y1(), r.z1());
  }
  absl::StatusOr<std::string> method = MethodName(p.method(), "cg");
  if (!method.ok()) return method.status();
  o.method = *method;
  o.strict_spacing = p.strict_spacing();
  o.strict_frame_of_reference = p.strict_frame_of_reference();
  o.slab_deconvolution = p.slab_deconvolution();
  const v1::DicomSeriesOutput& d = p.derived_series();
  if (d.enabled()) {
    return absl::InvalidArgumentError(
        "spec.derived_series.enabled is not used; list the contents");
  }
  if (!d.series_description().empty()) {
    return absl::InvalidArgumentError(
        "spec.derived_series.series_description is not supported; each "
        "object gets a description of what it holds");
  }
  o.output_series = absl::StrJoin(d.contents(), ",");
  // 0 = the default numbering (the wire has no absent int32).
  if (d.series_number() != 0) o.series_number_base = d.series_number();
  switch (d.pixel_compression()) {
    case v1::DICOM_PIXEL_COMPRESSION_UNSPECIFIED:
    case v1::DICOM_PIXEL_COMPRESSION_NONE:
      o.dicom_compression = "none";
      break;
    case v1::DICOM_PIXEL_COMPRESSION_RLE_LOSSLESS:
      o.dicom_compression = "rle";
      break;
    default:
      return OptionError(
          "dicom_compression",
          absl::StrCat("unknown compression ", d.pixel_compression()));
  }
  switch (d.layout()) {
    case v1::DICOM_LAYOUT_UNSPECIFIED:
    case v1::DICOM_LAYOUT_CLASSIC:
      o.dicom_layout = "classic";
      break;
    case v1::DICOM_LAYOUT_ENHANCED:
      o.dicom_layout = "enhanced";
      break;
    default:
      return OptionError("dicom_layout",
                         absl::StrCat("unknown layout ", d.layout()));
  }
  absl::StatusOr<std::string> intensity =
      IntensityMethodName(d.intensity_method(), o.intensity_method);
  if (!intensity.ok()) return intensity.status();
  o.intensity_method = *intensity;
  o.seg = p.segmentation().enabled();
  o.segment_label = p.segmentation().segment_label();
  o.segment_code = p.segmentation().segment_code();
  o.multiframe_volume = p.multiframe_volume();
  if (p.has_dicom_mesh_adaptivity()) {
    o.dicom_mesh_adaptivity = p.dicom_mesh_adaptivity();
  }
  if (p.has_dicom_mesh_max_mb()) o.dicom_mesh_max_mb = p.dicom_mesh_max_mb();
  if (p.has_outputs()) {
    absl::StatusOr<std::string> volume =
        FormatNames(p.outputs().volume_formats(), kVolumeFormats, "volume");
    if (!volume.ok()) return volume.status();
    o.volume = *volume;
    absl::StatusOr<std::string> mesh =
        FormatNames(p.outputs().mesh_formats(), kMeshFormats, "mesh");
    if (!mesh.ok()) return mesh.status();
    o.mesh = *mesh;
  }
  return o;
}

absl::StatusOr<FillJobOptions> FillOptionsFromWire(const v1::JobSpec& p) {
  // Fields of interpolation jobs that mean nothing for a fill: refused, so
  // that a client never believes they were applied.
  if (p.has_threshold()) return NotForFill("threshold");
  if (p.has_upper_threshold()) return NotForFill("upper_threshold");
  if (p.has_roi()) return NotForFill("roi");
  if (p.has_roi_mm()) return NotForFill("roi_mm");
  if (p.strict_spacing()) return NotForFill("strict_spacing");
  if (p.strict_frame_of_reference()) {
    return NotForFill("strict_frame_of_reference");
  }
  if (p.slab_deconvolution()) return NotForFill("slab_deconvolution");
  if (!p.multiframe_volume().empty()) return NotForFill("multiframe_volume");
  if (p.has_dicom_mesh_adaptivity()) {
    return NotForFill("dicom_mesh_adaptivity");
  }
  if (p.has_dicom_mesh_max_mb()) return NotForFill("dicom_mesh_max_mb");
  if (p.derived_series().ByteSizeLong() > 0) {
    return NotForFill("derived_series");
  }
  if (p.segmentation().ByteSizeLong() > 0) return NotForFill("segmentation");
  if (p.has_pacs_source()) return NotForFill("pacs_source");
  const v1::LabelFill& f = p.fill();
  if (f.segmentation_file().empty()) {
    return absl::InvalidArgumentError(
        "spec.fill.segmentation_file is required (the FileChunk.file_name of "
        "the uploaded segmentation)");
  }
  if (!f.label_names_file().empty() &&
      f.label_names_file() == f.segmentation_file()) {
    return absl::InvalidArgumentError(
        "spec.fill.label_names_file names the segmentation's file; the label "
        "names are a file of their own");
  }
  FillJobOptions o;
  if (absl::Status s = CommonFromWire(p, o); !s.ok()) return s;
  o.label_names = f.label_names_file();
  o.labels = absl::StrJoin(f.labels(), ",");
  o.key_slices = absl::StrJoin(f.key_slices(), ",");
  if (f.key_slices_size() > 0) {
    for (int64_t k : f.key_slices()) {
      if (k < 0) {
        return OptionError("key_slices",
                           absl::StrCat(k, " is not a slice index (>= 0)"));
      }
    }
  }
  absl::StatusOr<std::string> method = MethodName(p.method(), "auto");
  if (!method.ok()) return method.status();
  o.method = *method;
  o.seg = f.seg();
  if (f.has_rtstruct()) o.rtstruct = f.rtstruct();
  absl::StatusOr<std::string> intensity =
      IntensityMethodName(f.intensity_method(), o.intensity_method);
  if (!intensity.ok()) return intensity.status();
  o.intensity_method = *intensity;
  if (p.has_outputs()) {
    absl::StatusOr<std::string> volume =
        FormatNames(p.outputs().volume_formats(), kVolumeFormats, "volume");
    if (!volume.ok()) return volume.status();
    o.volume = *volume;
    absl::StatusOr<std::string> mesh =
        FormatNames(p.outputs().mesh_formats(), kMeshFormats, "mesh");
    if (!mesh.ok()) return mesh.status();
    o.mesh = *mesh;
  }
  return o;
}

absl::StatusOr<JobSpec> JobSpecFromWire(const v1::JobSpec& p) {
  absl::StatusOr<InterpolationOptions> options =
      InterpolationOptionsFromWire(p);
  if (!options.ok()) return ForDoor(options.status(), ErrorDoor::kWire);
  // Placeholders for what the server supplies, so that the core's check
  // runs on everything else.
  options->inputs = {"upload"};
  options->out = "out";
  absl::StatusOr<JobSpec> spec = BuildJobSpec(*options);
  if (!spec.ok()) return ForDoor(spec.status(), ErrorDoor::kWire);
  spec->inputs.clear();
  spec->output_dir.clear();
  return spec;
}

absl::StatusOr<FillJobSpec> FillJobSpecFromWire(const v1::JobSpec& p) {
  absl::StatusOr<FillJobOptions> options = FillOptionsFromWire(p);
  if (!options.ok()) return ForDoor(options.status(), ErrorDoor::kWire, true);
  options->segmentation = "segmentation";
  options->reference = {"upload"};
  options->out = "out";
  absl::StatusOr<FillJobSpec> spec = BuildFillJobSpec(*options);
  if (!spec.ok()) return ForDoor(spec.status(), ErrorDoor::kWire, true);
  spec->segmentation.clear();
  spec->label_names.clear();  // the upload's name; UseSpool sets the path
  spec->reference.clear();
  spec->output_dir.clear();
  return spec;
}

}  // namespace interslice::job
