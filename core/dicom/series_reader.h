// Reading one DICOM image series into a volume (DCMTK).
//
// Input: files and/or directories (directories are searched recursively).
// Files that are not DICOM, DICOMDIR files and DICOM objects that are not
// single-frame images with a position and orientation (reports, presentation
// states, ...) are skipped and counted, never fatal on their own.
//
// The image stack:
// - Grouped by SeriesInstanceUID. When several image series are present and
//   options.series_instance_uid is empty, the call fails with
//   FAILED_PRECONDITION naming each series (UID, modality, image count) so the
//   user can choose one.
// - Sorted along the slice normal n = row x column (ImageOrientationPatient);
//   the position of a slice is ImagePositionPatient . n.
// - Voxel values are modality values (HU for CT): stored value * RescaleSlope
//   + RescaleIntercept, per slice.
// - Grid: size = (Columns, Rows, slices); spacing = (PixelSpacing[1] (between
//   columns), PixelSpacing[0] (between rows), slice spacing from positions);
//   origin = ImagePositionPatient of the first sorted slice; direction columns
//   = (row direction, column direction, n). All in LPS mm.
//
// Errors (INVALID_ARGUMENT unless noted; messages name the problem and the
// file's base name, never patient data):
// - NOT_FOUND: no readable DICOM image in the input.
// - FAILED_PRECONDITION: several series and none chosen; chosen UID absent.
// - Inconsistent Rows/Columns, PixelSpacing or ImageOrientationPatient
//   between slices; two slices at the same position; fewer than 1 slice.
// - Non-uniform slice spacing (more than 1% or 0.01 mm off the median) and
//   gantry tilt (slice positions not along n): UNIMPLEMENTED for now.
// - Multi-frame images: UNIMPLEMENTED for now.
// - Undecodable pixel data (unsupported transfer syntax named), truncated or
//   short pixel data, SamplesPerPixel != 1, BitsAllocated not 8/16/32:
//   INVALID_ARGUMENT / UNIMPLEMENTED. Sizes are checked against
//   options.max_voxels before anything of that size is allocated.
#ifndef INTERSLICE_CORE_DICOM_SERIES_READER_H_
#define INTERSLICE_CORE_DICOM_SERIES_READER_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

struct DicomReadOptions {
  // SeriesInstanceUID to read; empty means "the only image series present".
  std::string series_instance_uid;
  // Upper bound on Columns * Rows * slices, checked before allocation.
  int64_t max_voxels = int64_t{1} << 31;
};

// One original slice of the series, in volume order (k).
struct DicomSliceInfo {
  std::string path;
  std::string sop_instance_uid;
  Vec3 image_position = {0, 0, 0};   // ImagePositionPatient, mm
  double position_along_normal = 0;  // mm
  double rescale_slope = 1, rescale_intercept = 0;
};

// One series found in the input (for listings and error messages).
struct DicomSeriesSummary {
  std::string series_instance_uid;
  std::string modality;
  int64_t image_count = 0;
};

struct DicomSeries {
  Volume<float> image;                 // modality values, e.g. HU
  std::vector<DicomSliceInfo> slices;  // size() == image.grid.size[2]
  std::string series_instance_uid;
  std::string study_instance_uid;
  std::string frame_of_reference_uid;
  std::string modality;
  std::string sop_class_uid;
  int64_t skipped_files = 0;  // non-DICOM, DICOMDIR, non-image, other series
};

// Reads the series. `paths` are files or directories.
absl::StatusOr<DicomSeries> ReadDicomSeries(
    const std::vector<std::string>& paths, const DicomReadOptions& options,
    const ComputeContext& context);

// Lists the image series found in `paths` (headers only).
absl::StatusOr<std::vector<DicomSeriesSummary>> ListDicomSeries(
    const std::vector<std::string>& paths);

// Turns DCMTK's own logger (which prints a line to stderr for every file it
// cannot parse) down to fatal messages. Programs call it once at start-up;
// the library never changes that process-wide setting by itself.
void QuietDicomToolkitLogging();

// Registers DCMTK's JPEG, JPEG-LS and RLE decoders; idempotent and
// thread-safe (ReadDicomSeries calls it).
void RegisterDicomDecoders();

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_SERIES_READER_H_
