// Closed planar contours of a label map, slice by slice, for writing the
// filled labels as an RTSTRUCT (core/dicom_out/rtstruct.h).
//
// Per label and slice: ITK's ContourExtractor2DImageFilter (marching
// squares) on the label's 0/1 mask at level 0.5, the mask padded by one
// background pixel so that every contour closes. Vertices lie halfway
// between a drawn and an undrawn pixel centre, in index coordinates (i, j)
// of the label map's grid, so rasterising the contours by the even-odd rule
// at pixel centres (as ReadRtStruct does) gives the mask back exactly.
// Holes are separate contours (even-odd makes them holes); diagonally
// touching pixels are joined into one contour (VertexConnectHighPixels).
#ifndef INTERSLICE_CORE_LABELS_LABEL_CONTOURS_H_
#define INTERSLICE_CORE_LABELS_LABEL_CONTOURS_H_

#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/labels/label_fill.h"
#include "core/labels/polygon_distance.h"

namespace interslice {

// Contours of `labels` (empty = every label present). Labels without pixels
// get no entry. CANCELLED / DEADLINE_EXCEEDED from context (polled per
// slice); INVALID_ARGUMENT for an invalid grid or data size.
absl::StatusOr<LabelContours> ExtractLabelContours(
    const LabelVolume& labels, const std::vector<int>& only,
    const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_LABEL_CONTOURS_H_
