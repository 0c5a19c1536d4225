// A job: one DICOM series (or a region of interest of it) through every
// stage: read -> contour (2D signed distance maps) -> stack -> solve ->
// mesh -> write. Used in-process by `interslice run` and by the server's
// workers, so both give byte-identical results for the same spec.
#ifndef INTERSLICE_CORE_PIPELINE_PIPELINE_H_
#define INTERSLICE_CORE_PIPELINE_PIPELINE_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/solver/solver.h"
#include "core/stack/stacking.h"

namespace interslice {

struct JobSpec {
  // DICOM files and/or directories (searched recursively).
  std::vector<std::string> inputs;
  // Series to read when the input holds several; empty = the only one.
  std::string series_instance_uid;
  // Half-open voxel box in the input series' index space (x = column,
  // y = row, z = slice in sorted order); unset = the whole series.
  std::optional<VoxelBox> roi;
  // Object = voxels with lower <= value (<= upper), in modality units (HU).
  float lower_threshold = 0;
  std::optional<float> upper_threshold;
  // Band of exact 2D distances, mm; <= 0 = automatic (see sdf module).
  double band_radius_mm = 0;
  ZResolution z_resolution;  // default: nearly isotropic
  // Non-uniform slice spacing (missing slices, irregular gaps) is normally
  // handled by snapping each original slice to the nearest output node (see
  // PlanStack); with strict_spacing it is INVALID_ARGUMENT naming the
  // smallest and largest gap.
  bool strict_spacing = false;
  SolverOptions solver;        // default: 15 CG iterations, voxel units
  double mesh_adaptivity = 0;  // OpenVDB adaptivity in [0, 1]
  // Outputs, written into output_dir (created if missing):
  //   volume formats "nii" -> distance.nii.gz, mask.nii.gz;
  //                  "nrrd" -> distance.nrrd, mask.nrrd;
  //   mesh formats "stl", "ply", "obj" -> surface.<ext>.
  std::vector<std::string> volume_formats = {"nii"};
  std::vector<std::string> mesh_formats = {"stl"};
  //   derived DICOM series "mask", "distance", "intensity" ->
  //                  series-<content>/IM00001.dcm ... (one file per slice);
  //   write_seg -> seg.dcm (binary DICOM SEG of the mask).
  std::vector<std::string> output_series;
  bool write_seg = false;
  // UID root for new series/instance UIDs; empty = 2.25 + UUID.
  std::string uid_root;
  // Multi-frame series holding several volumes: which one (as named in the
  // error listing them); empty = the only one.
  std::string multiframe_volume;
  std::string output_dir;
  // Upper bound on voxels of the refined grid, checked before allocation.
  int64_t max_output_voxels = int64_t{1} << 30;
  // Upper bound on voxels of the series as read (Columns x Rows x slices),
  // checked from the headers before any pixel data is decoded; this is what
  // bounds a small compressed upload that claims a huge image.
  int64_t max_input_voxels = int64_t{1} << 31;
};

struct StageTiming {
  std::string stage;  // read, contour, stack, solve, mesh, write
  double seconds = 0;
};

struct Artifact {
  std::string kind;  // "distance", "mask", "surface"
  std::string path;
  int64_t size_bytes = 0;
};

struct JobReport {
  std::vector<StageTiming> stages;
  SolverResult solver;
  EnergyUnits energy_units = EnergyUnits::kVoxel;
  Grid input_grid;   // the series as read (before the ROI)
  Grid output_grid;  // the refined grid written out
  int insertion_factor = 1;
  // Largest distance between an original slice's true position and the
  // output node it was placed on, mm (<= half the output z spacing; 0 for a
  // uniform series up to rounding).
  double max_snap_mm = 0;
  int64_t input_slices = 0;
  int64_t skipped_files = 0;
  int64_t mesh_vertices = 0;
  int64_t mesh_triangles = 0;
  std::vector<Artifact> artifacts;
  int64_t peak_rss_bytes = 0;  // filled by callers that know it (the CLI)
};

// INVALID_ARGUMENT naming the field for a spec that cannot run (no inputs,
// no output dir, unknown format, non-finite or inverted thresholds, ...).
absl::Status ValidateJobSpec(const JobSpec& spec);

// Runs the job. Errors come from the stages (see their headers); CANCELLED
// or DEADLINE_EXCEEDED when context.cancel fires. Outputs are written only
// after every computation succeeded, each file atomically.
absl::StatusOr<JobReport> RunJob(const JobSpec& spec,
                                 const ComputeContext& context);

// The report as JSON: {"stages": {"read": s, ...}, "solver": {"method",
// "iterations", "relative_residual", "energy", "initial_energy",
// "energy_units", "converged"}, "grid": {"size": [x,y,z], "spacing": [...],
// "origin": [...], "direction": [...], "insertion_factor": n, "max_snap_mm":
// mm}, "input": {...}, "mesh": {...},
// "artifacts": [...], "peak_rss_bytes": n}.
std::string JobReportToJson(const JobReport& report);

// Peak resident set size of this process, bytes (getrusage).
int64_t PeakRssBytes();

}  // namespace interslice

#endif  // INTERSLICE_CORE_PIPELINE_PIPELINE_H_
