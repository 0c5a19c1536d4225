#include "client/job_spec_proto.h"

namespace interslice::client {

v1::JobSpec JobSpecToProto(const JobSpec& spec) {
  v1::JobSpec p;
  p.set_series_instance_uid(spec.series_instance_uid);
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
  if (spec.band_radius_mm > 0) p.set_band_radius_mm(spec.band_radius_mm);
  if (spec.z_resolution.factor.has_value()) {
    p.set_insertion_factor(*spec.z_resolution.factor);
  } else if (spec.z_resolution.spacing_mm.has_value()) {
    p.set_slice_spacing_mm(*spec.z_resolution.spacing_mm);
  }
  switch (spec.solver.method) {
    case SolverMethod::kLinear:
      p.set_method(v1::SOLVER_METHOD_LINEAR);
      break;
    case SolverMethod::kConjugateGradient:
      p.set_method(v1::SOLVER_METHOD_CONJUGATE_GRADIENT);
      break;
    case SolverMethod::kDirect:
      p.set_method(v1::SOLVER_METHOD_DIRECT);
      break;
    case SolverMethod::kMorph:
      p.set_method(v1::SOLVER_METHOD_MORPH);
      break;
  }
  p.set_max_iterations(spec.solver.max_iterations);
  if (spec.solver.tolerance > 0) p.set_tolerance(spec.solver.tolerance);
  p.set_energy_units(spec.solver.units == EnergyUnits::kMillimetre
                         ? v1::ENERGY_UNITS_MILLIMETRE
                         : v1::ENERGY_UNITS_VOXEL);
  p.set_mesh_adaptivity(spec.mesh_adaptivity);
  p.set_strict_spacing(spec.strict_spacing);
  p.set_uid_root(spec.uid_root);
  p.set_random_uids(spec.random_uids);
  if (spec.series_number_base > 0) {
    p.mutable_derived_series()->set_series_number(spec.series_number_base);
  }
  p.set_multiframe_volume(spec.multiframe_volume);
  if (spec.dicom_compression == "rle") {
    p.mutable_derived_series()->set_pixel_compression(
        v1::DICOM_PIXEL_COMPRESSION_RLE_LOSSLESS);
  }
  p.mutable_segmentation()->set_enabled(spec.write_seg);
  // Sent as asked: the server says clearly if it cannot serve them.
  for (const std::string& content : spec.output_series) {
    p.mutable_derived_series()->add_contents(content);
  }
  v1::OutputSelection* outputs = p.mutable_outputs();
  for (const std::string& f : spec.volume_formats) {
    outputs->add_volume_formats(f == "nrrd" ? v1::VOLUME_FORMAT_NRRD
                                : f == "nii-uncompressed"
                                    ? v1::VOLUME_FORMAT_NIFTI_UNCOMPRESSED
                                    : v1::VOLUME_FORMAT_NIFTI);
  }
  for (const std::string& f : spec.mesh_formats) {
    outputs->add_mesh_formats(f == "ply"   ? v1::MESH_FORMAT_PLY
                              : f == "obj" ? v1::MESH_FORMAT_OBJ
                                           : v1::MESH_FORMAT_STL);
  }
  return p;
}

v1::JobSpec FillJobSpecToProto(const FillJobSpec& spec,
                               const std::string& segmentation_file) {
  v1::JobSpec p;
  p.set_series_instance_uid(spec.series_instance_uid);
  v1::LabelFill* fill = p.mutable_fill();
  fill->set_segmentation_file(segmentation_file);
  for (int label : spec.fill.labels) fill->add_labels(label);
  if (spec.fill.key_slices.has_value()) {
    for (int64_t k : *spec.fill.key_slices) fill->add_key_slices(k);
  }
  if (spec.fill.band_radius_mm > 0) {
    p.set_band_radius_mm(spec.fill.band_radius_mm);
  }
  if (spec.fill.z_resolution.factor.has_value()) {
    p.set_insertion_factor(*spec.fill.z_resolution.factor);
  } else if (spec.fill.z_resolution.spacing_mm.has_value()) {
    p.set_slice_spacing_mm(*spec.fill.z_resolution.spacing_mm);
  }
  p.set_uid_root(spec.uid_root);
  p.set_random_uids(spec.random_uids);
  fill->set_seg(spec.write_seg);
  if (spec.write_rtstruct.has_value()) fill->set_rtstruct(*spec.write_rtstruct);
  // Unset method = the fill's default (auto).
  if (spec.fill.method == FillMethod::kSolver)
    switch (spec.fill.solver.method) {
      case SolverMethod::kLinear:
        p.set_method(v1::SOLVER_METHOD_LINEAR);
        break;
      case SolverMethod::kConjugateGradient:
        p.set_method(v1::SOLVER_METHOD_CONJUGATE_GRADIENT);
        break;
      case SolverMethod::kDirect:
        p.set_method(v1::SOLVER_METHOD_DIRECT);
        break;
      case SolverMethod::kMorph:
        p.set_method(v1::SOLVER_METHOD_MORPH);  // the server refuses it
        break;
    }
  p.set_max_iterations(spec.fill.solver.max_iterations);
  if (spec.fill.solver.tolerance > 0)
    p.set_tolerance(spec.fill.solver.tolerance);
  p.set_energy_units(spec.fill.solver.units == EnergyUnits::kMillimetre
                         ? v1::ENERGY_UNITS_MILLIMETRE
                         : v1::ENERGY_UNITS_VOXEL);
  p.set_mesh_adaptivity(spec.mesh_adaptivity);
  v1::OutputSelection* outputs = p.mutable_outputs();
  for (const std::string& f : spec.volume_formats) {
    outputs->add_volume_formats(f == "nrrd" ? v1::VOLUME_FORMAT_NRRD
                                            : v1::VOLUME_FORMAT_NIFTI);
  }
  for (const std::string& f : spec.mesh_formats) {
    outputs->add_mesh_formats(f == "ply"   ? v1::MESH_FORMAT_PLY
                              : f == "obj" ? v1::MESH_FORMAT_OBJ
                                           : v1::MESH_FORMAT_STL);
  }
  return p;
}

}  // namespace interslice::client
