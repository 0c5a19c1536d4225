// Writing interslice results back to DICOM (DCMTK): an isotropic derived
// image series (mask, signed distance or resampled intensity), a binary DICOM
// Segmentation of the mask, resampling of the source image onto the output
// grid (ITK), and the coordinate convention of mesh files.
//
// Geometry contract (shared by every writer here):
// - `source` is what ReadDicomSeries returned; its files (slices[k].path) must
//   still be readable, because the Patient and Study modules are copied from
//   the first one (never invented, never logged).
// - The output grid is any grid (see core/geometry/volume.h) whose direction
//   equals the source grid's direction (to 1e-4): same row and column
//   directions, slices stacked along the source's normal n = row x column.
//   Its origin, size and spacing are free (an isotropic refinement of the
//   source, or a crop of it). Otherwise INVALID_ARGUMENT.
// - Slice k of the output is written at ImagePositionPatient = grid origin +
//   k * spacing[2] * n, with InstanceNumber k + 1, so instance numbers grow
//   along n (the order our reader sorts in). ImageOrientationPatient is the
//   first two direction columns; PixelSpacing = (spacing[1], spacing[0]) (row
//   spacing first, as DICOM wants); SliceThickness = SpacingBetweenSlices =
//   spacing[2]. Reading the series back with ReadDicomSeries reproduces the
//   grid.
//
// Identity:
// - New SeriesInstanceUID and SOPInstanceUIDs under options.uid_root; by
//   default "2.25." followed by a random (version 4) UUID as one decimal
//   number (ITU-T X.667 / DICOM PS3.5 B.2). Every call makes a new series.
// - StudyInstanceUID, FrameOfReferenceUID and the Patient, General Study and
//   Patient Study modules (and SpecificCharacterSet) are copied from the first
//   source file; type 2 attributes absent there are written empty.
// - Equipment (Manufacturer etc.) describes interslice, the creator of the
//   derived objects, not the scanner.
//
// Errors: INVALID_ARGUMENT for bad inputs (grid mismatch, wrong voxel count,
// non-finite values, values that cannot be encoded, a malformed UID root);
// FAILED_PRECONDITION when a source file cannot be read again; INTERNAL (with
// the output path and the system's reason) when the output folder or a file
// cannot be created or written. Messages never contain patient data.
#ifndef INTERSLICE_CORE_DICOM_OUT_DICOM_WRITER_H_
#define INTERSLICE_CORE_DICOM_OUT_DICOM_WRITER_H_

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/dicom/series_reader.h"
#include "core/geometry/volume.h"

namespace interslice {

struct DicomWriteOptions {
  // Root for the new UIDs (digits and dots, no leading zeros in a component,
  // at most 40 characters so that 24 random digits fit into the 64-character
  // limit). Empty means "2.25." + UUID.
  std::string uid_root;
  // SeriesDescription; empty means a default naming the content ("interslice
  // mask", "interslice signed distance (mm)", ...).
  std::string series_description;
  // SeriesNumber; <= 0 leaves it empty in derived series (type 2 there)
  // and uses 9001 for a SEG (type 1 there).
  int series_number = 0;
  // Start of DerivationDescription; the writer appends what the content is
  // (and, for intensity, the interpolator). Keep it free of patient data.
  std::string derivation_description =
      "interslice shape-based interpolation (Csebfalvi et al. 2001)";
  // SoftwareVersions of the creating equipment.
  std::string software_version = "interslice";
};

enum class DerivedContent {
  // 0/1 object mask; stored as uint16 0/1, RescaleSlope 1, Intercept 0;
  // window centre 0.5, width 1. A voxel is 1 where its value is nonzero.
  kMask,
  // Signed distance in mm (positive inside). Stored as int16 with
  // RescaleIntercept 0 and the smallest RescaleSlope of 0.01, 0.02, 0.05,
  // 0.1, 0.2, 0.5, 1, 2, ... mm for which max |distance| fits in 32767 steps
  // (so 0.01 mm up to +-327 mm); values are rounded to the nearest step.
  // Window centre 0 mm, width 2 * max|d| clamped to [1, 20] mm (the region
  // around the surface, where the sign change is).
  kDistance,
  // Source modality values (e.g. HU) resampled onto the output grid (see
  // ResampleToGrid), stored with the first source slice's RescaleSlope and
  // RescaleIntercept (rounded to the nearest stored value; uint16 if every
  // stored value is >= 0, else int16). If a value does not fit, the slope is
  // raised along 1-2-5 steps. Window: the source's first WindowCenter/Width,
  // else the data range.
  kIntensity,
};

// "mask", "distance" or "intensity".
std::string_view DerivedContentName(DerivedContent content);

// Writes `values` (on the output grid, see the contract above) as a derived
// single-frame image series into `output_dir` (created if missing), one file
// per slice named IM00001.dcm, IM00002.dcm, ... in InstanceNumber order, each
// written to a temporary name and renamed into place. Files of the same names
// are replaced; other files are left alone, so use a folder per series.
// Returns the paths written, in slice order.
//
// IOD: CT Image Storage when the source is CT Image Storage, MR Image Storage
// when it is MR Image Storage (their type 1/2 acquisition attributes, e.g.
// KVP or ScanningSequence, are copied from the source), otherwise Secondary
// Capture Image Storage with the Image Plane module added (a standard
// extended SOP class; our reader needs the plane). ImageType is
// DERIVED\SECONDARY\AXIAL (CT), DERIVED\SECONDARY\OTHER (MR) or
// DERIVED\SECONDARY (SC): the defined terms have no value for a mask or a
// distance map, so SeriesDescription and DerivationDescription say what the
// series holds. Mask and distance carry RescaleType "US" (unspecified; the
// unit, mm, is in DerivationDescription), intensity "HU" for CT. MR images
// get RescaleSlope/Intercept only when not the identity (standard extended:
// the MR IOD has no Modality LUT). SourceImageSequence (per slice: the one or
// two source slices nearest along n, purpose DCM 121322) and
// ReferencedSeriesSequence (every source instance) point back to the source.
// Little Endian Explicit, uncompressed.
absl::StatusOr<std::vector<std::string>> WriteDerivedSeries(
    const DicomSeries& source, const Volume<float>& values,
    DerivedContent content, const DicomWriteOptions& options,
    const std::string& output_dir);

// A coded concept (CodeValue, CodingSchemeDesignator, CodeMeaning).
struct CodedConcept {
  std::string value;
  std::string scheme;
  std::string meaning;
};

struct SegmentDescription {
  std::string label = "Bone";
  // CID 7150 "Segmentation Property Categories" and CID 7166 "Common Tissue
  // Segmentation Types" (DICOM PS3.16).
  CodedConcept category = {"85756007", "SCT", "Tissue"};
  CodedConcept type = {"272673000", "SCT", "Bone"};
  std::string algorithm_name = "interslice";
};

// Writes `mask` (nonzero = inside; on the output grid, see the contract
// above) as a binary DICOM Segmentation with one segment (SegmentAlgorithmType
// AUTOMATIC), atomically, to `path` (its folder must exist).
// - One frame per output slice, in slice order, empty slices included, so
//   that the frames tile the whole output grid and a reader needs nothing but
//   the SEG to rebuild it. Shared functional groups: PixelMeasures (as in the
//   derived series), PlaneOrientationPatient; per frame: PlanePositionPatient,
//   FrameContent (dimension indices: segment number, then slice k + 1 along
//   ImagePositionPatient) and DerivationImage (the one or two source slices
//   nearest along n, purpose "Source image for image processing operation").
// - ReferencedSeriesSequence lists every source instance.
absl::Status WriteSegmentation(const DicomSeries& source,
                               const Volume<uint8_t>& mask,
                               const SegmentDescription& segment,
                               const DicomWriteOptions& options,
                               const std::string& path);

// The source image (modality values) trilinearly interpolated at the voxel
// centres of `target` (itk::ResampleImageFilter with
// itk::LinearInterpolateImageFunction, identity transform, both in LPS mm).
// Linear because it never overshoots the neighbouring values (no ringing at
// bone/air edges, unlike B-splines or windowed sinc, which matters across
// 5 mm slices) and is exact on the source slices; the intensity series is
// context under the overlay, not a measurement. Points up to half a voxel
// outside the source are clamped to the edge; points farther outside get the
// source's minimum value (air). `target` may have any valid geometry.
// Threads: context.threads (0 = all); the result does not depend on it.
absl::StatusOr<Volume<float>> ResampleToGrid(const Volume<float>& image,
                                             const Grid& target,
                                             const ComputeContext& context);

// A few lines of text to write beside mesh files (e.g. surface.txt): vertices
// are DICOM patient coordinates (LPS, mm) of the source's Frame of Reference
// (its UID is included), triangles are counter-clockwise seen from outside,
// and how to convert to RAS. Contains UIDs but no patient data.
std::string MeshConventionNote(const DicomSeries& source);

// A new UID under `root` (empty: "2.25." + UUID); INVALID_ARGUMENT if `root`
// is malformed or too long. Exposed for callers that name other objects of
// the same job.
absl::StatusOr<std::string> GenerateDicomUid(const std::string& root);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_DICOM_WRITER_H_
