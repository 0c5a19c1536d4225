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

// JobSpec::dicom_mesh_adaptivity's default: 0, the mesh as surface.stl.
// OpenVDB's adaptivity is a weak simplifier on a bone surface: on the CT
// phantom with the shipped rule, 1.0 (its most) takes the Encapsulated STL
// from 133 MB to 20 MB (thick) and 26 MB (tilted), with vertices, edge
// midpoints and centroids up to 1.8 / 2.0 mm (mean 0.14 / 0.16 mm) from the
// full surface, and the exact measurement of that costs minutes on a shared
// machine; so adaptivity is asked for, not the default: the default size
// cap (kDefaultDicomMeshMaxMb, quadric edge collapse) is what makes the
// Encapsulated STL fit a PACS.
inline constexpr double kDefaultDicomMeshAdaptivity = 0;

// JobSpec::dicom_mesh_max_mb's default: the Encapsulated STL object is at
// most 25 MB (10^6 bytes, DICOM header included), a size PACS take (issue
// 25). The CT phantom's full surface is 133 MB.
inline constexpr double kDefaultDicomMeshMaxMb = 25;
// The smallest cap other than 0 (none) and the largest, MB.
inline constexpr double kMinDicomMeshMaxMb = 0.1;
inline constexpr double kMaxDicomMeshMaxMb = 4000;
// What the cap leaves for the DICOM object's header around the binary STL:
// a fixed part plus one SourceInstanceSequence item per source image
// (measured: 7.5 KB in all for the 28-slice CT phantom, about 160 bytes an
// item with 64-character UIDs; both kept generous).
inline constexpr int64_t kEncapsulatedStlHeaderReserveBytes = 64 * 1024;
inline constexpr int64_t kEncapsulatedStlBytesPerSourceInstance = 256;
// The most triangles a binary STL may have (84 + 50 bytes per triangle) for
// its Encapsulated STL object, which references `source_instances` images,
// to stay within max_mb; 0 for max_mb 0 (no cap), at least 1 otherwise.
int64_t MaxEncapsulatedStlTriangles(double max_mb, int64_t source_instances);

struct JobSpec {
  // DICOM files and/or directories (searched recursively).
  std::vector<std::string> inputs;
  // Series to read when the input holds several; empty = the only one.
  std::string series_instance_uid;
  // Half-open voxel box in the input series' index space (x = column,
  // y = row, z = slice in sorted order); unset = the whole series.
  std::optional<VoxelBox> roi;
  // The same as a box in patient space (LPS mm, as a viewer's ROI tool gives
  // it), mapped to the series' voxels once it is read: the smallest voxel
  // box covering every voxel centre inside it, clipped to the series, for
  // any orientation and gantry tilt (core/geometry PhysicalBoxToVoxelBox
  // with the slices' true positions). INVALID_ARGUMENT when it misses the
  // series (naming the axis and by how many mm) or when roi is also set.
  std::optional<PhysicalBox> roi_mm;
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
  // Slices whose FrameOfReferenceUIDs differ are normally read when their
  // geometry is one stack, with a note (JobReport::input_notes and
  // input_warnings; core/dicom series_reader.h, "Frames of reference"); with
  // strict_frame_of_reference they are INVALID_ARGUMENT.
  bool strict_frame_of_reference = false;
  // Thick slices (SliceThickness wider than the output z spacing): contour
  // not the slices as read but their slab deconvolution (core/slab
  // DeconvolveSlabs, slab = the series' SliceThickness, the output factor of
  // a uniform plan): an estimate of the thin object at the slice positions,
  // where a thick slice averages it over its slab (docs/eval/candidates.md,
  // "Slab deconvolution"). The original slices of the field are then these
  // estimates' distance maps, not the input's. INVALID_ARGUMENT without a
  // SliceThickness, with non-uniform spacing, or with a slab wider than two
  // slice gaps. The intensity series (output_series "intensity") still
  // carries the values as read.
  bool slab_deconvolution = false;
  SolverOptions solver;        // default: 15 CG iterations, voxel units
  double mesh_adaptivity = 0;  // OpenVDB adaptivity in [0, 1]
  // The mesh stored in the study as Encapsulated STL (written with DICOM
  // outputs when mesh_formats has "stl"): its own OpenVDB adaptivity in
  // [0, 1], so that a PACS gets a mesh of a size it takes while surface.stl
  // keeps mesh_adaptivity. Its distance from the unsimplified surface
  // (adaptivity 0) is measured (core/surface MeasureMeshDeviation) and
  // reported (JobReport::dicom_mesh_*). Default: kDefaultDicomMeshAdaptivity.
  double dicom_mesh_adaptivity = kDefaultDicomMeshAdaptivity;
  // The Encapsulated STL's size cap, MB (10^6 bytes, the DICOM object with
  // its header): 0 = no cap, else in [kMinDicomMeshMaxMb,
  // kMaxDicomMeshMaxMb]. Applied after dicom_mesh_adaptivity: a mesh over
  // MaxEncapsulatedStlTriangles is simplified to that many triangles
  // (core/surface SimplifyMesh, quadric edge collapse) and meshoptimizer's
  // error estimate reported (JobReport::dicom_mesh_simplify_error_mm).
  // surface.stl is never capped. Default: kDefaultDicomMeshMaxMb.
  double dicom_mesh_max_mb = kDefaultDicomMeshMaxMb;
  // Outputs, written into output_dir (created if missing):
  //   volume formats "nii" -> distance.nii.gz, mask.nii.gz;
  //                  "nrrd" -> distance.nrrd, mask.nrrd;
  //                  "nii-uncompressed" -> distance.nii, mask.nii (no
  //                  deflate: the float field barely compresses, 86% of
  //                  raw, and deflating it dominates the write stage);
  //   mesh formats "stl", "ply", "obj" -> surface.<ext>.
  std::vector<std::string> volume_formats = {"nii"};
  std::vector<std::string> mesh_formats = {"stl"};
  // When true, a file whose content one of this job's DICOM objects carries
  // is not written (nor listed in the report): surface.stl when the
  // Encapsulated STL is written, mask.<ext> with the SEG, distance.<ext>
  // with the distance map; surface-coordinates.txt only beside a mesh file.
  // For a job whose DICOM objects are all it delivers (the DICOM node's jobs
  // that send to PACS peers, server/engine/spool.h): the 2.7 million triangles
  // of the CT phantom's surface.stl (133 MB) are then never formatted and
  // written. Default false: every requested format is written.
  bool omit_files_dicom_objects_carry = false;
  //   DICOM objects (see core/dicom_out/dicom_writer.h and
  //   docs/dicom-output.md), by output_series name:
  //     "intensity" -> series-intensity/IM00001.dcm ... (a CT/MR image
  //                    series of the source values on the output grid);
  //     "distance"  -> distance.dcm (Parametric Map of the signed distance,
  //                    float mm);
  //     "mask"      -> seg.dcm (binary DICOM SEG of the mask; the same as
  //                    write_seg).
  //   With any of these and mesh format "stl", the mesh is also written as
  //   surface-stl.dcm (DICOM Encapsulated STL, core/dicom_out/
  //   encapsulated_stl.h) in the same study and frame of reference.
  //   A SEG or a distance map is always written with the intensity series
  //   it references frame by frame (a viewer opens that series and overlays
  //   them), so either one also writes series-intensity/.
  std::vector<std::string> output_series;
  bool write_seg = false;
  // What the SEG's segment is (core/dicom_out DescribeThresholdSegment):
  // segment_label its SegmentLabel (1-64 characters), segment_code its
  // SegmentedPropertyType as "scheme:value:meaning" (ParseCodedConcept, e.g.
  // "SCT:272673000:Bone"). Empty = the default from modality and threshold:
  // "Bone" for CT at >= 200 HU, else "Region above N <units>" coded
  // Anatomical Structure. Either one given is part of the UIDs' derivation
  // (the SEG says something else, so it is another object).
  std::string segment_label;
  std::string segment_code;
  // Pixel data of the intensity series: "none" (default, native Explicit VR
  // Little Endian) or "rle" (encapsulated RLE Lossless: the same values in
  // fewer bytes; see DicomWriteOptions::intensity_encoding). The SEG and the
  // distance map stay native. UIDs do not depend on it (the same instances,
  // transcoded losslessly).
  std::string dicom_compression = "none";
  // Layout of the intensity series: "classic" (default: one CT/MR image per
  // output slice, series-intensity/IM00001.dcm ...) or "enhanced" (one
  // Enhanced CT Image or, for an MR source, Enhanced MR Image instance, frame
  // k = output slice k, series-intensity/enhanced.dcm,
  // core/dicom_out/enhanced_series.h; the SEG and the distance map then
  // reference its frames). Enhanced needs a CT or MR source:
  // FAILED_PRECONDITION otherwise, before any computation. Classic
  // UIDs are unchanged; the enhanced object's are derived from them.
  std::string dicom_layout = "classic";
  // How the intensity series (output_series "intensity", or brought along
  // by a SEG or distance map) gets the grey values of the output slices
  // between two source slices:
  //   "linear" - the two bracketing source slices blended linearly in
  //              modality units at the slice's true position
  //              (ResampleSourceSlices, core/dicom_out);
  //   "morph"  - carried along the motion between them (core/morph
  //              MorphIntensity: the grey images registered by demons, a C1
  //              trajectory and monotone values in z, local fallback to the
  //              linear blend where the registration is unreliable, reported
  //              in JobReport::intensity). Source slices are reproduced
  //              bit-identically either way.
  // The default is the morph: on the thin and the tilted phantom, drop-k
  // at every 2nd, 4th and 8th slice, +1.5 to +2.9 dB PSNR in the body over
  // the better of linear and Catmull-Rom, higher SSIM and sharper oblique
  // bone edges (docs/eval/intensity.md, which also has where it is not
  // better: homogeneous soft tissue at every 2nd slice).
  std::string intensity_method = "morph";
  // UID root for new series/instance UIDs; empty = 2.25 + UUID.
  std::string uid_root;
  // UIDs are derived from the source instances, the job's parameters and the
  // root (a rerun replaces its results on a PACS instead of duplicating
  // them); random_uids makes new ones on every run.
  bool random_uids = false;
  // Series numbers of the derived objects: intensity base + 1, distance map
  // base + 2, SEG base + 3, Encapsulated STL base + 4, previews base + 6;
  // <= 0 = 1000 x the source's SeriesNumber (9000 when it has none). At
  // most INT_MAX - 6.
  int series_number_base = 0;
  // Previews (core/preview/preview.h): the axial, coronal and sagittal
  // planes of the output grid through the object with its outline, the
  // original slices ticked, and a front view of the surface, each with a
  // legend (method, threshold, spacing, "interpolated"), by format:
  //   "png"   -> previews/axial.png, coronal.png, sagittal.png,
  //              3d-front.png (artifact kind "previews", the folder);
  //   "dicom" -> previews-dicom/IM00001.dcm ... (a Secondary Capture series
  //              in the source's study, series number base + 6, derived from
  //              the intensity series when one is written:
  //              core/dicom_out/preview_series.h; kind "previews-dicom").
  // Empty (default here; the job layer's default is "png") = none. They are
  // rendered in stage "preview" after "mesh", from the grey values as read
  // (ResampleSourceSlicesInBox on three planes) and the refined field. A
  // preview that cannot be made or written never fails the job: the reason
  // is in JobReport::preview_notes (and so is anything a person should know
  // about them, e.g. an empty mask).
  std::vector<std::string> preview_formats;
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
  std::string stage;  // read, contour, stack, solve, mesh, preview, write
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
  // The region of interest: as given in mm (JobSpec::roi_mm, unset without
  // one) and the voxel box of the input it became (JobSpec::roi or the
  // mapped roi_mm; unset for the whole series).
  std::optional<PhysicalBox> roi_mm;
  std::optional<VoxelBox> roi;
  int insertion_factor = 1;
  // Largest distance between an original slice's true position and the
  // output node it was placed on, mm (<= half the output z spacing; 0 for a
  // uniform series up to rounding).
  double max_snap_mm = 0;
  int64_t input_slices = 0;
  int64_t skipped_files = 0;
  // The series as read: gantry tilt corrected (degrees; 0 = none), and the
  // smallest and largest gap between consecutive slices (mm).
  double gantry_tilt_degrees = 0;
  double min_gap_mm = 0, max_gap_mm = 0;
  // What the reader inferred about the input (DicomSeries::notes): no UIDs,
  // no patient data.
  std::vector<std::string> input_notes;
  // Those of input_notes a person should see although the job succeeded
  // (DicomSeries::warnings, e.g. differing FrameOfReferenceUIDs accepted).
  // Not a field of the JSON (it is in input.notes): empty after
  // JobReportFromJson.
  std::vector<std::string> input_warnings;
  // JobSpec::slab_deconvolution only: the slab (mm, 0 = not run), the
  // iterations, and the RMS of (slices - slab averages of the estimate)
  // before and after, in modality units.
  double slab_thickness_mm = 0;
  int slab_iterations = 0;
  double slab_residual_before = 0, slab_residual_after = 0;
  // The intensity series, when one was written: its method ("linear" or
  // "morph"; empty when none was written) and, for "morph", the gaps
  // between source slices, those that could not be registered at all
  // (constant slices, a missing block), the fraction of the inserted voxels
  // whose value is mostly the linear fallback, and the mean and largest
  // in-plane motion found (mm).
  std::string intensity_method;
  int intensity_gaps = 0;
  int intensity_gaps_not_registered = 0;
  double intensity_fallback_fraction = 0;
  double intensity_mean_displacement_mm = 0;
  double intensity_max_displacement_mm = 0;
  int64_t mesh_vertices = 0;
  int64_t mesh_triangles = 0;
  // The Encapsulated STL's mesh (JobSpec::dicom_mesh_adaptivity), when one
  // was written (dicom_mesh_adaptivity >= 0, else -1): its size, and the
  // largest and mean distance of its vertices, edge midpoints and triangle
  // centroids from the unsimplified surface, mm, measured on a distance grid
  // of dicom_mesh_resolution_mm (core/surface MeasureMeshDeviation).
  double dicom_mesh_adaptivity = -1;
  int64_t dicom_mesh_vertices = 0;
  int64_t dicom_mesh_triangles = 0;
  double dicom_mesh_max_deviation_mm = 0;
  double dicom_mesh_mean_deviation_mm = 0;
  double dicom_mesh_resolution_mm = 0;
  // Samples farther than the measurement's band (>= 2 mm): then the max is
  // only known to be at least dicom_mesh_max_deviation_mm.
  int64_t dicom_mesh_samples_beyond_band = 0;
  // The size cap (JobSpec::dicom_mesh_max_mb, 0 = none) and what it did:
  // the triangles before it (the surface as extracted at
  // dicom_mesh_adaptivity), meshoptimizer's error estimate in mm (0 when
  // the cap did not bite; SimplifiedMesh::error_mm says what it means), and
  // the embedded binary STL's size. over_cap: the simplifier could not
  // reach the cap (the object is larger than asked).
  double dicom_mesh_max_mb = 0;
  int64_t dicom_mesh_triangles_before_cap = 0;
  double dicom_mesh_simplify_error_mm = 0;
  int64_t dicom_mesh_stl_bytes = 0;
  bool dicom_mesh_over_cap = false;
  // JobSpec::preview_formats only: one sentence each, no patient data (a
  // preview skipped and why, an empty mask, ...).
  std::vector<std::string> preview_notes;
  std::vector<Artifact> artifacts;
  // Peak resident set size of the process that ran the job, bytes
  // (PeakRssBytes); filled by the caller (job/job.h fills it after RunJob).
  // A process that runs one job (`interslice run`, the server's worker
  // process) measures that job, libraries and start-up included; a job run
  // inside a process that runs others (the server with --isolation thread)
  // gets that process's peak since it started, other jobs included: a
  // job's own share of one process is not measurable. -1 when unknown.
  int64_t peak_rss_bytes = 0;
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
// mm}, "input": {..., "notes": [...], "roi": {"begin": [i,j,k], "end":
// [...]} and "roi_mm": {"min": [x,y,z], "max": [...]} when set}, "mesh": {...},
// "previews": {"notes": [...]} (with JobSpec::preview_formats only),
// "artifacts": [...], "peak_rss_bytes": n}.
std::string JobReportToJson(const JobReport& report);

// Reads what JobReportToJson wrote (the server reads a job's report from its
// worker process this way); JobReportToJson(*JobReportFromJson(j)) == j.
// INVALID_ARGUMENT naming the field for malformed or incomplete JSON.
absl::StatusOr<JobReport> JobReportFromJson(const std::string& json);

// Peak resident set size of this process since it started (its execve),
// bytes: VmHWM of /proc/self/status. Not getrusage's ru_maxrss, which Linux
// carries over from the image a process replaced at execve (fs/exec.c), so
// that a process started by fork or vfork (posix_spawn, Python's
// subprocess) from a large parent reported at least the parent's size.
// -1 when /proc/self/status cannot be read.
int64_t PeakRssBytes();

}  // namespace interslice

#endif  // INTERSLICE_CORE_PIPELINE_PIPELINE_H_
