#include "server/spec_mapping.h"

#include <cmath>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"

namespace interslice::server {
namespace {

// The same cap as `interslice run` applies when only a tolerance is given.
constexpr int kToleranceIterationCap = 100000;

}  // namespace

absl::StatusOr<JobSpec> JobSpecFromProto(const v1::JobSpec& p) {
  if (p.derived_series().enabled()) {
    return absl::InvalidArgumentError(
        "spec.derived_series.enabled is not used; list the contents");
  }
  JobSpec spec;
  for (const std::string& content : p.derived_series().contents()) {
    if (content != "mask" && content != "distance" && content != "intensity") {
      return absl::InvalidArgumentError(
          absl::StrCat("spec.derived_series.contents: unknown content '",
                       content, "' (choose from mask, distance, intensity)"));
    }
    spec.output_series.push_back(content);
  }
  spec.strict_spacing = p.strict_spacing();
  spec.write_seg = p.segmentation().enabled();
  spec.uid_root = p.uid_root();
  spec.random_uids = p.random_uids();
  if (p.derived_series().series_number() < 0 ||
      p.derived_series().series_number() > 2147483644) {
    return absl::InvalidArgumentError(
        "spec.derived_series.series_number must be between 0 and 2147483644");
  }
  spec.series_number_base = p.derived_series().series_number();
  switch (p.derived_series().pixel_compression()) {
    case v1::DICOM_PIXEL_COMPRESSION_UNSPECIFIED:
    case v1::DICOM_PIXEL_COMPRESSION_NONE:
      spec.dicom_compression = "none";
      break;
    case v1::DICOM_PIXEL_COMPRESSION_RLE_LOSSLESS:
      spec.dicom_compression = "rle";
      break;
    default:
      return absl::InvalidArgumentError(
          "spec.derived_series.pixel_compression: unknown compression");
  }
  if (!p.derived_series().series_description().empty()) {
    return absl::InvalidArgumentError(
        "spec.derived_series.series_description is not supported; each "
        "object gets a description of what it holds");
  }
  spec.multiframe_volume = p.multiframe_volume();
  spec.series_instance_uid = p.series_instance_uid();
  if (!p.has_threshold()) {
    return absl::InvalidArgumentError("spec.threshold is required");
  }
  spec.lower_threshold = p.threshold();
  if (p.has_upper_threshold()) spec.upper_threshold = p.upper_threshold();
  if (p.has_roi()) {
    const v1::VoxelBox& r = p.roi();
    spec.roi = VoxelBox{{r.x0(), r.y0(), r.z0()}, {r.x1(), r.y1(), r.z1()}};
  }
  if (p.has_band_radius_mm()) {
    if (!(p.band_radius_mm() > 0) || !std::isfinite(p.band_radius_mm())) {
      return absl::InvalidArgumentError("spec.band_radius_mm must be positive");
    }
    spec.band_radius_mm = p.band_radius_mm();
  }
  switch (p.z_resolution_case()) {
    case v1::JobSpec::kInsertionFactor:
      spec.z_resolution.factor = p.insertion_factor();
      break;
    case v1::JobSpec::kSliceSpacingMm:
      spec.z_resolution.spacing_mm = p.slice_spacing_mm();
      break;
    default:
      break;
  }
  switch (p.method()) {
    case v1::SOLVER_METHOD_UNSPECIFIED:
    case v1::SOLVER_METHOD_CONJUGATE_GRADIENT:
      spec.solver.method = SolverMethod::kConjugateGradient;
      break;
    case v1::SOLVER_METHOD_LINEAR:
      spec.solver.method = SolverMethod::kLinear;
      break;
    case v1::SOLVER_METHOD_DIRECT:
      spec.solver.method = SolverMethod::kDirect;
      break;
    case v1::SOLVER_METHOD_MORPH:
      spec.solver.method = SolverMethod::kMorph;
      break;
    default:
      return absl::InvalidArgumentError("spec.method: unknown method");
  }
  if (p.has_max_iterations()) {
    if (p.max_iterations() < 0) {
      return absl::InvalidArgumentError("spec.max_iterations must be >= 0");
    }
    spec.solver.max_iterations = p.max_iterations();
  } else if (p.has_tolerance()) {
    spec.solver.max_iterations = kToleranceIterationCap;
  }
  if (p.has_tolerance()) {
    if (!(p.tolerance() > 0) || !std::isfinite(p.tolerance())) {
      return absl::InvalidArgumentError("spec.tolerance must be positive");
    }
    spec.solver.tolerance = p.tolerance();
  }
  switch (p.energy_units()) {
    case v1::ENERGY_UNITS_UNSPECIFIED:
    case v1::ENERGY_UNITS_VOXEL:
      spec.solver.units = EnergyUnits::kVoxel;
      break;
    case v1::ENERGY_UNITS_MILLIMETRE:
      spec.solver.units = EnergyUnits::kMillimetre;
      break;
    default:
      return absl::InvalidArgumentError("spec.energy_units: unknown units");
  }
  spec.mesh_adaptivity = p.mesh_adaptivity();
  if (p.has_outputs()) {
    spec.volume_formats.clear();
    spec.mesh_formats.clear();
    auto add = [](std::vector<std::string>& list, const std::string& v) {
      if (std::find(list.begin(), list.end(), v) == list.end()) {
        list.push_back(v);
      }
    };
    for (int f : p.outputs().volume_formats()) {
      if (f == v1::VOLUME_FORMAT_NIFTI) {
        add(spec.volume_formats, "nii");
      } else if (f == v1::VOLUME_FORMAT_NRRD) {
        add(spec.volume_formats, "nrrd");
      } else if (f == v1::VOLUME_FORMAT_NIFTI_UNCOMPRESSED) {
        add(spec.volume_formats, "nii-uncompressed");
      } else {
        return absl::InvalidArgumentError(
            "spec.outputs.volume_formats: unknown format");
      }
    }
    for (int f : p.outputs().mesh_formats()) {
      if (f == v1::MESH_FORMAT_STL) {
        add(spec.mesh_formats, "stl");
      } else if (f == v1::MESH_FORMAT_PLY) {
        add(spec.mesh_formats, "ply");
      } else if (f == v1::MESH_FORMAT_OBJ) {
        add(spec.mesh_formats, "obj");
      } else {
        return absl::InvalidArgumentError(
            "spec.outputs.mesh_formats: unknown format");
      }
    }
  }
  // Validate everything but the folders, which the server supplies.
  JobSpec probe = spec;
  probe.inputs = {"upload"};
  probe.output_dir = "out";
  absl::Status valid = ValidateJobSpec(probe);
  if (!valid.ok()) return valid;
  return spec;
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
  return "application/octet-stream";
}

}  // namespace interslice::server
