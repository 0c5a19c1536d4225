// A fill job: a segmentation drawn on some slices of a reference DICOM series
// through FillBetweenSlices (label_fill.h) to files. Used in-process by
// `interslice fill`.
//
// Input: a label map (.nii, .nii.gz, .nrrd; integer labels, 0 = background)
// on the voxels of the reference series in any index layout (axes permuted
// or flipped, label_map_io.h; the reference is read with core/dicom), or a
// DICOM SEG drawn on the reference series (any DICOM file is read as one; label
// = SegmentNumber; segmentation_reader.h). Output files in output_dir (created
// if missing), each written atomically after every computation succeeded:
//   volume formats "nii" -> labels.nii.gz, "nrrd" -> labels.nrrd: the label
//   map on the output grid, for label map input in the input's layout and
//   header (WriteLabelMapLike: axis order, directions, origin, NIfTI
//   qform/sform codes, NRRD fields, voxel type), else uint16 in the
//   reference's layout;
//   mesh formats "stl" / "ply" / "obj" -> label-<L>.<ext>, one watertight
//   mesh per filled label (LPS mm, from the label's combined field, so
//   neighbouring labels' meshes meet without overlap); a label with an empty
//   result writes no mesh;
//   write_seg -> seg.dcm: the filled label map as a multi-segment DICOM SEG
//   (core/dicom_out/label_segmentation.h) carrying the input's segment
//   labels, colours and codes (a label map: from label_names or its own
//   .seg.nrrd fields, else "Label N", a colour per label, generic codes);
//   segment n is the n-th label present, ascending;
//   write_rtstruct (default: on for RTSTRUCT input) -> rtstruct.dcm: the
//   filled labels as CLOSED_PLANAR contours per ROI and slice
//   (core/dicom_out/rtstruct.h; ROI numbers = labels, names and colours from
//   the input).
//   preview_formats "png" -> previews/*.png, "dicom" -> previews-dicom/ (a
//   Secondary Capture series): the reference's grey values on the output
//   grid's axial, coronal and sagittal planes with each filled label
//   outlined in its segment colour, the key slices (of every label) ticked,
//   and the labels' surfaces from the front (core/preview), as for
//   core/pipeline's JobSpec::preview_formats: a preview that cannot be made
//   or written is a note (FillJobReport::preview_notes), never a failure.
//   Both reference the reference series' images and frame of reference when
//   the output grid is the reference grid (factor 1). On a finer grid
//   (--factor/--spacing), or for a reference whose slices cannot be
//   referenced one image each (multi-frame, or without SOP Instance UIDs),
//   they reference a derived intensity series written beside them,
//   series-intensity/ (the reference resampled onto the output grid, as
//   `interslice run` writes it). UIDs are derived from the reference
//   series, the input labels and the fill parameters (dicom_writer.h
//   "Identity"): the same fill names its objects the same.
// An RTSTRUCT's key slices get the exact distance of its polygons
// (FillOptions::contours, polygon_distance.h). Its contours are placed on the
// reference's slices by position (segmentation_reader.h ReadRtStruct); when
// some of their image references (ContourImageSequence) name no image of the
// reference series, one warning says how many.
// The reference is read with DicomReadOptions::strict_frame_of_reference:
// slices whose FrameOfReferenceUIDs differ are INVALID_ARGUMENT (a DICOM
// segmentation is matched to the reference by its one Frame of Reference).
#ifndef INTERSLICE_CORE_LABELS_FILL_JOB_H_
#define INTERSLICE_CORE_LABELS_FILL_JOB_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/labels/label_fill.h"
#include "core/labels/segmentation_reader.h"

namespace interslice {

struct FillJobSpec {
  std::string segmentation;  // label map or DICOM SEG path
  // A label map's segment names, colours and codes: a colour table (.csv)
  // or JSON sidecar (segment_names.h); empty: a .seg.nrrd's own segment
  // fields, else "Label N". INVALID_ARGUMENT with SEG or RTSTRUCT input.
  std::string label_names;
  std::vector<std::string> reference;  // DICOM files and/or directories
  std::string series_instance_uid;     // when the reference holds several
  FillOptions fill;
  std::vector<std::string> volume_formats = {"nii"};
  std::vector<std::string> mesh_formats = {"stl"};
  double mesh_adaptivity = 0;  // OpenVDB adaptivity in [0, 1]
  bool write_seg = false;
  std::optional<bool> write_rtstruct;  // unset: on for RTSTRUCT input
  // The grey values of series-intensity/ (written on a finer grid): "morph"
  // (default) or "linear", as JobSpec::intensity_method (pipeline.h).
  std::string intensity_method = "morph";
  std::string uid_root;      // DicomWriteOptions::uid_root
  bool random_uids = false;  // DicomWriteOptions::random_uids
  // "png", "dicom" (above); empty = none.
  std::vector<std::string> preview_formats;
  std::string output_dir;
  int64_t max_input_voxels = int64_t{1} << 31;
};

struct FillArtifact {
  // "labels", "surface", "seg", "rtstruct", "series-intensity", "previews",
  // "previews-dicom"
  std::string kind;
  int label = 0;  // surfaces: the label; else 0
  std::string path;
  int64_t size_bytes = 0;
};

struct FillJobReport {
  double read_seconds = 0, fill_seconds = 0, mesh_seconds = 0,
         preview_seconds = 0, write_seconds = 0;
  Grid input_grid, output_grid;
  int factor = 1;
  std::string method;  // "auto", "linear", "cg", "direct"
  // "label-map", "seg-binary", "seg-fractional" or "rtstruct"; a SEG's
  // segments or an RTSTRUCT's ROIs.
  std::string input_kind;
  // A label map's index axes against the reference's (AxisMapping::
  // Describe, "(i, j, k)" when the same); empty for DICOM input.
  std::string input_layout;
  std::vector<LabelSegment> segments;
  // Key slices whose 2D distance came from the input's polygons (RTSTRUCT).
  int64_t polygon_key_slices = 0;
  std::vector<LabelFillInfo> per_label;  // fields dropped
  int64_t gap_voxels_closed = 0;
  int64_t key_voxels_restored = 0;
  // The input's (an RTSTRUCT's unresolved image references, above), then the
  // fill's (FillResult::warnings); they name no UID.
  std::vector<std::string> warnings;
  // With preview_formats: one sentence each (a preview skipped and why, an
  // empty label, ...).
  std::vector<std::string> preview_notes;
  std::vector<FillArtifact> artifacts;
};

// INVALID_ARGUMENT naming the field for a spec that cannot run.
absl::Status ValidateFillJobSpec(const FillJobSpec& spec);

// Runs the job. Errors from reading (the label map, the reference series),
// CheckSameGrid, FillBetweenSlices, meshing and writing, each naming the
// file or label. Progress: context.progress hears "read", "fill" (then the
// stages FillBetweenSlices reports), "mesh" (when meshes are asked for),
// "preview" (when previews are) and "write", each at fraction 0 when it
// begins.
absl::StatusOr<FillJobReport> RunFillJob(const FillJobSpec& spec,
                                         const ComputeContext& context);

// {"stages": {...} ("preview" with previews), "grid": {...}, "method",
// "labels": [{"label",
// "key_slices", "drawn_slices", "method", "voxels", "iterations",
// "relative_residual"}], "gap_voxels_closed", "key_voxels_restored",
// "warnings": [...], "previews": {"notes": [...]} (with previews),
// "artifacts": [...]}.
std::string FillJobReportToJson(const FillJobReport& report);

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_FILL_JOB_H_
