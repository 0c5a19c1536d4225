// Names, colours and codes of a label map's labels (issue 24), so that the
// structures a person drew reach the DICOM SEG and RTSTRUCT outputs by name
// instead of as "Label N".
//
// Sources:
// - Slicer's segmentation file (.seg.nrrd): the header fields of segment n
//   (0-based), "Segment<n>_Name", "Segment<n>_LabelValue" (the voxel value;
//   without it n + 1, the order Slicer writes a label map in),
//   "Segment<n>_Color" ("r g b", 0..1) and "Segment<n>_Terminology"
//   ("context~category~type~...", each code "scheme^value^meaning", Slicer's
//   terminology string). Overlapping segments are stored by Slicer in
//   several layers ("Segment<n>_Layer" > 0) and are refused.
// - A colour table, CSV: one label a line, "label,name,R,G,B[,code]" (R, G,
//   B 0..255; code "scheme^value^meaning", e.g. "SCT^10200004^Liver", the
//   segmented property type); a first line that does not start with a number
//   is a header; empty lines and lines starting with '#' are skipped.
// - JSON: an array (or {"segments": [...]}) of objects {"label": 1,
//   "name": "Liver", "rgb": [r, g, b], "type": {"scheme", "value",
//   "meaning"}, "category": {...}}; only "label" is required.
// A label whose entry gives no code keeps DefaultLabelSegment's (category
// and type "Tissue"); one without colour keeps the default colour.
#ifndef INTERSLICE_CORE_LABELS_SEGMENT_NAMES_H_
#define INTERSLICE_CORE_LABELS_SEGMENT_NAMES_H_

#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "core/dicom_out/label_segmentation.h"

namespace interslice {

// The segments described by Slicer's header fields (VolumeFileHeader::
// key_values of a .seg.nrrd); empty when there are none. INVALID_ARGUMENT
// for segments in more than one layer (overlapping), a label value outside
// 1..65535, two segments with one label value, or a colour that is not
// three numbers in 0..1.
absl::StatusOr<std::vector<LabelSegment>> SegmentsFromSlicerFields(
    const std::vector<std::pair<std::string, std::string>>& key_values);

// Reads a colour table (.csv, .txt) or JSON (.json) sidecar.
// INVALID_ARGUMENT naming the file and line (CSV) or entry (JSON) for: an
// unreadable file, a label that is not an integer in 1..65535, a label
// listed twice, a colour component outside 0..255, a malformed code; an
// unknown extension.
absl::StatusOr<std::vector<LabelSegment>> ReadSegmentNames(
    const std::string& path);

// Checks `segments` against the labels present in a label map (sorted):
// INVALID_ARGUMENT when a segment names a label the map does not hold
// ("the label names name label 7, which the label map does not hold
// (labels: 1, 2, 3)"), with `what` naming the source.
absl::Status CheckSegmentsAgainstLabels(
    const std::vector<LabelSegment>& segments, const std::vector<int>& present,
    const std::string& what);

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_SEGMENT_NAMES_H_
