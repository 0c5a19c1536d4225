// A filled multi-label segmentation (`interslice fill`) written back to
// DICOM as a multi-segment binary Segmentation (DCMTK dcmseg), carrying what
// the input said about each structure (name, colour, codes).
//
// Referenced images: `referenced` describes the image series the label map
// lies on, one image per slice of its grid, in slice order:
// ReferencedImagesOfSource() for the reference series itself (output grid =
// reference grid), or PlanDerivedObjects(...).intensity for a derived
// intensity series on a finer grid (written with WriteIntensitySeries).
// Frame k of a segment references image k of it (DerivationImage), and the
// ReferencedSeriesSequence lists every image of it. Study and frame of
// reference are the source's (core/dicom_out/dicom_writer.h "Identity").
#ifndef INTERSLICE_CORE_DICOM_OUT_LABEL_SEGMENTATION_H_
#define INTERSLICE_CORE_DICOM_OUT_LABEL_SEGMENTATION_H_

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/geometry/volume.h"

namespace interslice {

// One structure of a label map: what a SEG segment or an RTSTRUCT ROI says
// about it. Read by core/labels/segmentation_reader.h, written here.
struct LabelSegment {
  int number = 0;     // the label value (SegmentNumber / ROINumber)
  std::string label;  // SegmentLabel / ROIName
  // RecommendedDisplayCIELabValue (DICOM scaling, 0..65535 each), if given.
  std::optional<std::array<uint16_t, 3>> cielab;
  // ROIDisplayColor (RGB 0..255), if given.
  std::optional<std::array<uint8_t, 3>> rgb;
  // SegmentedPropertyCategory/TypeCode (empty value: none given).
  CodedConcept category, type;
};

// Sensible descriptions for labels that come without any (a label map):
// "Label N", a distinct colour per label (hues spread by the golden angle),
// category and type SCT 85756007 "Tissue" (generic, DICOM CID 7150/7166).
LabelSegment DefaultLabelSegment(int label);

// `segment`'s colour as DICOM CIELab: its own, else converted from its RGB
// (DCMTK IODCIELabUtil, sRGB D65), else DefaultLabelSegment's.
std::array<uint16_t, 3> SegmentCieLab(const LabelSegment& segment);
// `segment`'s colour as RGB 0..255: its own, else converted from its CIELab,
// else DefaultLabelSegment's.
std::array<uint8_t, 3> SegmentRgb(const LabelSegment& segment);

// The reference series as the images a derived object lies on (one per
// slice, with the source's SOP Class and Instance UIDs and series UID).
// INVALID_ARGUMENT if a slice has no SOP Instance UID (an anonymised source
// cannot be referenced), two slices share one (frames of a multi-frame
// image), or an image does not lie on its slot of the source's regular grid
// (ImagePositionPatient more than 0.01 mm + 1% of the pixel spacing away:
// uneven gaps, gantry tilt); callers then derive an intensity series to
// reference instead.
absl::StatusOr<DerivedObjectIdentity> ReferencedImagesOfSource(
    const DicomSeries& source);

// Writes `labels` (0 = background; on the grid of `referenced`, see the
// geometry contract of dicom_writer.h) as one binary SEG, atomically, to
// `path`. Segments: one per label present in `labels`, numbered 1..N in
// ascending label order (DICOM wants segment numbers 1, 2, ...; a label map
// whose labels are 1..N keeps its numbers), described by the entry of
// `segments` with that label number, else DefaultLabelSegment (missing codes
// are filled with the default's). Frames: for each segment, one per slice
// where it has pixels (empty slices are left out, as DICOM allows), placed by
// PlanePositionPatient; dimensions: segment number, then position.
// SegmentAlgorithmType SEMIAUTOMATIC (drawn by a person, filled by
// interslice), algorithm "interslice fill". `identity` names the SEG
// (PlanDerivedObjects(...).segmentation). Errors: INVALID_ARGUMENT for a
// grid mismatch, a bad identity or more than 65535 segments; others as for
// WriteSegmentation.
absl::Status WriteLabelSegmentation(const DicomSeries& source,
                                    const Volume<uint16_t>& labels,
                                    const std::vector<LabelSegment>& segments,
                                    const DerivedObjectIdentity& identity,
                                    const DerivedObjectIdentity& referenced,
                                    const DicomWriteOptions& options,
                                    const std::string& path);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_LABEL_SEGMENTATION_H_
