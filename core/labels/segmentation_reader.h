// Segmentations in from DICOM: a DICOM Segmentation (SEG, DCMTK dcmseg) as a
// label map on the grid of the series it was drawn on.
//
// - Binary and fractional SEGs, one or many segments, frames for any subset
//   of the reference's slices (slices without a frame are not drawn).
// - Label = SegmentNumber. A fractional frame sets a pixel when its value is
//   at least half of MaximumFractionalValue (the 0.5 iso-level of the
//   fraction).
// - Each frame is placed by its ImagePositionPatient (per-frame or shared
//   Plane Position) on the reference slice it lies on.
//
// Errors (INVALID_ARGUMENT, naming the file and, where it applies, the frame
// (1-based, as in DICOM) and segment): not a readable SEG; a
// FrameOfReferenceUID other than the reference's; a referenced series
// (ReferencedSeriesSequence) other than the reference series; Rows/Columns
// or ImageOrientationPatient not the reference's; a frame off the
// reference's slice planes (more than 1% of a slice gap) or shifted in plane
// (more than 1% of a pixel); a frame without segment number or position;
// two segments set on the same pixel ("segments 1 and 2 overlap on slice
// 12"); more than 65535 segments.
#ifndef INTERSLICE_CORE_LABELS_SEGMENTATION_READER_H_
#define INTERSLICE_CORE_LABELS_SEGMENTATION_READER_H_

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/dicom_out/label_segmentation.h"
#include "core/geometry/volume.h"
#include "core/labels/label_fill.h"
#include "core/labels/polygon_distance.h"

namespace interslice {

// A segment's or ROI's description is a LabelSegment
// (core/dicom_out/label_segmentation.h: number, label, colour, codes), so
// that the fill's DICOM outputs carry it over.
struct SegmentationInput {
  LabelVolume labels;  // on the reference grid
  std::vector<LabelSegment> segments;
  // RTSTRUCT only: the CLOSED_PLANAR contours of each ROI read, per slice,
  // in index coordinates of the reference grid (FillOptions::contours).
  LabelContours contours;
  bool fractional = false;
  bool rtstruct = false;
  int64_t frames = 0;
  // RTSTRUCT only, when ReferenceSeries::image_sop_instance_uids is given:
  // the contour image references of the CLOSED_PLANAR contours read
  // (ContourImageSequence > ReferencedSOPInstanceUID), and how many of them
  // name no image of the reference series. Contours are placed on slices by
  // their points' positions whatever they reference; a caller says so when
  // the references could not have confirmed it (fill_job.h).
  int64_t image_references = 0;
  int64_t unresolved_image_references = 0;
};

// The reference series, as core/dicom read it.
struct ReferenceSeries {
  Grid grid;
  std::string series_instance_uid;
  std::string frame_of_reference_uid;
  // The SOP Instance UIDs of its images (an anonymised series may have
  // none), for counting an RTSTRUCT's unresolved image references
  // (SegmentationInput); nullopt: not counted.
  std::optional<std::vector<std::string>> image_sop_instance_uids;
};

// True if `path` is a DICOM file (the "DICM" magic at byte 128).
bool LooksLikeDicomFile(const std::string& path);

// `only`: segment numbers to read (empty = all); frames of other segments
// are skipped, so that overlaps with them are no error.
absl::StatusOr<SegmentationInput> ReadDicomSegmentation(
    const std::string& path, const ReferenceSeries& reference,
    const std::vector<int>& only = {});

// An RTSTRUCT (DCMTK dcmrt) as a label map on the reference grid: label =
// ROINumber (1..65535), segments[].label = ROIName, segments[].rgb =
// ROIDisplayColor (if given), no codes; `contours` holds the polygons. Each
// CLOSED_PLANAR contour must lie on one slice plane of the reference (all
// points within 5% of a slice gap of it); the pixels whose centres are
// inside the contours of an ROI on that slice by the even-odd rule are set
// (several polygons and holes drawn as inner contours included). Other
// geometric types (POINT, OPEN_*) are skipped. The contours' image
// references are counted (SegmentationInput::image_references), not used:
// placement is by position. Errors as for a SEG (file,
// ROI name and number, contour, slice), plus: a contour off the slice
// planes, fewer than 3 points, an ROI number outside 1..65535, an ROI whose
// ReferencedFrameOfReferenceUID is not the reference's.
absl::StatusOr<SegmentationInput> ReadRtStruct(
    const std::string& path, const ReferenceSeries& reference,
    const std::vector<int>& only = {});

// Either of the above, by the file's SOPClassUID; INVALID_ARGUMENT for a
// DICOM object that is neither.
absl::StatusOr<SegmentationInput> ReadDicomLabels(
    const std::string& path, const ReferenceSeries& reference,
    const std::vector<int>& only = {});

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_SEGMENTATION_READER_H_
