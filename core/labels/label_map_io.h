// Label map files (NIfTI, NRRD) on a reference series' voxels in any index
// layout, read exactly and written back in the input's own layout and header
// (issue 24). Segmentation tools write the reference's voxels in their own
// order (nibabel and dcm2niix RAS with rows flipped, model exports with axes
// permuted): the file's index axes are matched to the reference's by a
// signed permutation (core/volume_io/layout.h), never resampled.
#ifndef INTERSLICE_CORE_LABELS_LABEL_MAP_IO_H_
#define INTERSLICE_CORE_LABELS_LABEL_MAP_IO_H_

#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/labels/label_fill.h"
#include "core/volume_io/layout.h"
#include "core/volume_io/volume_io.h"

namespace interslice {

// The input file's layout and header, to write results like it.
struct LabelMapFile {
  VolumeFileHeader header;
  AxisMapping mapping;  // file index axes -> reference index axes
};

struct LabelMapOnReference {
  LabelVolume labels;  // on the reference grid, the reference's layout
  LabelMapFile file;
};

// Reads `path` onto `reference`. Errors (INVALID_ARGUMENT, each one line
// naming the file): unreadable or not a 3D scalar volume; scaled voxel
// values (NIfTI scl_slope other than 0 or 1, or scl_inter other than 0);
// a grid whose voxels are not the reference's (MatchGridToReference: tilted
// axes, voxel counts, spacing, voxel centres off by how many mm along which
// axis); a voxel that is not a label (LabelVolumeFromFloat: negative, not an
// integer, above 65535).
absl::StatusOr<LabelMapOnReference> ReadLabelMapOnReference(
    const std::string& path, const Grid& reference);

// Writes `labels` (on the reference grid or a finer one with the same axes
// and extent, the fill's output) to `path` (.nii.gz, .nii or .nrrd) in the
// layout of `file`: its axis order, directions and first voxel
// (ToFileLayout), its NIfTI qform/sform codes, its NRRD key/value fields
// (Slicer's segment metadata; the per-segment "_Extent" fields, which the
// result would contradict, are left out), and its voxel type when that is
// unsigned char or short and holds every label (else unsigned short).
// Errors as WriteVolume.
absl::Status WriteLabelMapLike(const LabelVolume& labels,
                               const LabelMapFile& file,
                               const std::string& path,
                               const ComputeContext& context = {});

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_LABEL_MAP_IO_H_
