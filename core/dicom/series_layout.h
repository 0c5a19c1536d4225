// Part of the DICOM series reader (series_reader.h): from the scanned headers
// of one series to the geometry of its image stack, without reading pixel
// data (no I/O at all: only the FileHeaders are read), and the gantry-tilt
// correction of the decoded stack.
//
// LayOutDicomStack, in this order of checks:
// 1. The first member (in index order) whose header has a problem fails the
//    layout with that problem (a broken or unreadable file of the series).
// 2. Slices: a single-frame file is one slice; an enhanced multi-frame file
//    gives one slice per frame, with the frame's position, orientation,
//    pixel spacing and rescale (FileHeader::frames). Frames belong to
//    volumes (FrameGeometry::volume: stack, temporal position, frame type);
//    one volume is laid out at a time: the only one, or `volume`.
//    FAILED_PRECONDITION, listing each volume with its slice count, when
//    there are several and `volume` is empty, or `volume` is not one of them.
// 3. Attributes a stack must not change: Modality, BitsAllocated,
//    BitsStored, PixelRepresentation, and with strict_frame_of_reference
//    FrameOfReferenceUID (never shown). INVALID_ARGUMENT naming the first
//    slice (index order) that differs from the value most slices have, and
//    one slice that has it; when no value is shared by two slices, that each
//    slice has its own (naming two), and when there are more than two
//    values, how many.
//    Without strict_frame_of_reference, FrameOfReferenceUIDs that differ
//    (several UIDs, or some slices without one) are accepted when the
//    geometry checks below (4. to 7.) pass: some anonymisers give every file
//    its own Frame of Reference although the slices are one acquisition, and
//    what makes slices one stack is their geometry, which is checked. The
//    counts are in DicomStackLayout; a failure of the geometry checks then
//    says that the UIDs differ too.
// 4. Rows/Columns, ImageOrientationPatient (each component within 1e-4) and
//    PixelSpacing (relative 1e-4) equal to the first slice's;
//    ImageOrientationPatient two orthogonal unit vectors (to 1e-3; then
//    orthonormalised by Gram-Schmidt). INVALID_ARGUMENT naming the slice.
// 5. Sorted along the normal n = row x column by ImagePositionPatient . n
//    (ties: path, then frame). Two slices closer than 1e-3 mm along n:
//    INVALID_ARGUMENT naming both.
// 6. Gantry tilt: when some step between neighbouring slices moves within
//    the image plane by more than 0.01 mm per mm along n, every slice's
//    in-plane offset from the first slice (in pixels along i and j) is
//    recorded for CorrectGantryTilt, and the tilt angle is that of the whole
//    stack's first-to-last step against n. An offset of a whole image or
//    more: INVALID_ARGUMENT (the slices do not overlap).
// 7. Grid (all LPS mm): size (Columns, Rows, slices); spacing
//    (PixelSpacing[1], PixelSpacing[0], median gap along n; one slice:
//    SliceThickness, else SpacingBetweenSlices, else 1); origin = position of
//    the first sorted slice; direction columns (row, column, n); then
//    Grid::Validate (INVALID_ARGUMENT, e.g. for a PixelSpacing of 0). Gaps
//    within max(0.01 mm, 1% of the median) of the median count as uniform.
// Messages name slices by file base name ("I10.dcm", "enh.dcm frame 3"),
// never patient data or UIDs.
#ifndef INTERSLICE_CORE_DICOM_SERIES_LAYOUT_H_
#define INTERSLICE_CORE_DICOM_SERIES_LAYOUT_H_

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/dicom/dicom_header.h"
#include "core/geometry/volume.h"

namespace interslice {

// One original slice: a single-frame file, or one frame of an enhanced
// multi-frame file. Values are those of the frame (functional groups) for
// multi-frame files, of the file otherwise.
struct DicomSliceRef {
  size_t header = 0;  // index into the headers given to LayOutDicomStack
  int frame = 0;      // 0-based frame number in the file (0: single frame)
  Vec3 position = {0, 0, 0};  // ImagePositionPatient, mm
  std::array<double, 6> orientation = {1, 0, 0, 0, 1, 0};
  std::array<double, 2> pixel_spacing = {1, 1};  // [between rows, columns]
  double rescale_slope = 1, rescale_intercept = 0;
  std::string volume;  // FrameGeometry::volume; empty for single frames
};

// The geometry of the stack and the order of its slices.
struct DicomStackLayout {
  std::vector<DicomSliceRef> order;  // sorted along the normal
  std::vector<double> positions;     // along the normal, mm, in `order`
  Grid grid;
  // Gaps between consecutive positions, mm (0 for one slice), and whether
  // all are uniform (see 7. above).
  bool uniform = true;
  double min_gap = 0, max_gap = 0;
  // Gantry tilt: the in-plane offset of each slice (in `order`) from the
  // first, in pixels along (i, j); empty when the stack is not tilted.
  std::vector<std::array<double, 2>> tilt_shift;
  double tilt_degrees = 0;  // 0 when not tilted
  // Step 3: whether the slices' FrameOfReferenceUIDs differ (several UIDs,
  // or some slices with one and some without; accepted only without
  // strict_frame_of_reference), the distinct non-empty UIDs among them and
  // the slices without one.
  bool frames_of_reference_differ = false;
  int64_t frame_of_reference_uids = 0;
  int64_t slices_without_frame_of_reference = 0;
};

// Lays out the stack of `members` (indices into `headers`, the files of one
// series, e.g. DicomSeriesGroup::members) as described above. `volume`
// chooses among the volumes of multi-frame files; empty means "the only
// one". strict_frame_of_reference: refuse slices whose FrameOfReferenceUIDs
// differ even when their geometry is one stack (step 3). `members` must be
// valid indices of FileKind::kImage headers; INVALID_ARGUMENT when it is
// empty.
absl::StatusOr<DicomStackLayout> LayOutDicomStack(
    const std::vector<dicom_internal::FileHeader>& headers,
    const std::vector<size_t>& members, const std::string& volume,
    bool strict_frame_of_reference = false);

// Gantry tilt correction (dcm2niix's approach): slice k of `image` (laid out
// as `layout`, decoded) is resampled bilinearly at (i - shift_i, j - shift_j)
// so that it lies on the in-plane grid of the first slice; samples from
// outside the acquired slice are the minimum of the whole volume (the
// darkest value keeps the padding outside any object defined by a lower
// threshold: air for CT). Exact for any in-plane offsets, not only a tilt
// about one axis. Does nothing when layout.tilt_shift is empty;
// INVALID_ARGUMENT (and `image` untouched) when `image` does not hold one
// slice per shift. Threading: context.threads workers; the result does not
// depend on their number. Not cancellable (one pass over the volume).
absl::Status CorrectGantryTilt(const DicomStackLayout& layout,
                               Volume<float>& image,
                               const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_SERIES_LAYOUT_H_
