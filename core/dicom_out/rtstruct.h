// A filled multi-label segmentation written as an RT Structure Set
// (RTSTRUCT, DCMTK dcmrt): per ROI, its CLOSED_PLANAR contours slice by
// slice, in patient coordinates (LPS, mm).
//
// The contours come in index coordinates (i, j) of `grid` on its slices k
// (core/labels/label_contours.h makes them from the label map); each point
// is written as grid.IndexToPhysical(i, j, k). Each contour references the
// image it lies on (ContourImageSequence: image k of `referenced`, the
// reference series itself (ReferencedImagesOfSource) or a derived intensity
// series on the same grid); the Referenced Frame of Reference Sequence lists
// the study, series and every image of `referenced`. ROIs keep their numbers,
// names (ROIName; "Label N" if empty) and colours (ROIDisplayColor: the RGB
// given, else converted from the CIELab, else a default colour); they are
// marked ROIGenerationAlgorithm SEMIAUTOMATIC; RTROIInterpretedType is left
// empty (type 2: not known to interslice). Patient and study are copied from
// the source (dicom_writer.h "Identity"); identity.sop_instance_uids holds the
// one instance UID; series number and description come from `identity`. Errors:
// INVALID_ARGUMENT for a grid mismatch, a bad identity, an ROI number
// outside 1..65535 or twice, a polygon with fewer than 3 points or a slice
// outside the grid; FAILED_PRECONDITION when the source cannot be read again;
// INTERNAL naming `path` when it cannot be written.
#ifndef INTERSLICE_CORE_DICOM_OUT_RTSTRUCT_H_
#define INTERSLICE_CORE_DICOM_OUT_RTSTRUCT_H_

#include <array>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/label_segmentation.h"
#include "core/geometry/volume.h"

namespace interslice {

struct RoiContours {
  LabelSegment roi;  // roi.number = ROINumber
  // Slice k -> closed polygons (vertices (i, j), the closing edge implied).
  std::map<int64_t, std::vector<std::vector<std::array<double, 2>>>> slices;
};

absl::Status WriteRtStructureSet(const DicomSeries& source, const Grid& grid,
                                 const std::vector<RoiContours>& rois,
                                 const DerivedObjectIdentity& identity,
                                 const DerivedObjectIdentity& referenced,
                                 const DicomWriteOptions& options,
                                 const std::string& path);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_RTSTRUCT_H_
