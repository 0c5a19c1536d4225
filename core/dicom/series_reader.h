// Reading one DICOM image series into a volume (DCMTK; GDCM for JPEG 2000).
//
// ReadDicomSeries runs three parts, each with its own header and usable on
// its own: series_index.h (paths -> scanned headers -> image series, and the
// listings used in messages), series_layout.h (one series' headers -> the
// sorted stack's geometry, multi-frame volumes, gantry tilt) and
// pixel_decode.h (a file's frames -> modality values). This header includes
// the index and decode headers, which declare DicomSeriesSummary,
// CollectInputFiles, TransferSyntaxInfo, DecodableTransferSyntaxes and
// RegisterDicomDecoders.
//
// Input: files and/or directories (directories are searched recursively).
// Files that are not DICOM, DICOMDIR files, DICOM objects that are not
// images with a position and orientation (reports, presentation states,
// secondary captures without geometry) and secondary captures that share a
// series with acquired images are skipped and counted, never fatal on their
// own. Files whose sequences nest more than 128 levels deep are refused
// (skipped, and named in the NOT_FOUND message if nothing else is left)
// before DCMTK parses them, because DCMTK's parser recurses once per level
// and would overflow the stack.
//
// Anonymised exports: no UID is required. SOPClassUID missing or empty: the
// file meta header's MediaStorageSOPClassUID is used (as dcm2niix and GDCM
// do); absent there too, the file is still read as a slice by its geometry
// (as dcm2niix does). SeriesInstanceUID missing or empty: the series is
// inferred from what a series keeps constant and is still present:
// FrameOfReferenceUID, Modality and SeriesNumber (each when present),
// ImageOrientationPatient, Rows/Columns and PixelSpacing (orientation and
// spacing compared to 1e-4). Such a series is named "no-uid-1", "no-uid-2",
// ... (in a stable order) in listings and messages, and that name selects it
// like a UID. The slices are sorted by geometry as always. What was inferred
// is listed in DicomSeries::notes.
//
// Transfer syntaxes: implicit/explicit little endian, explicit big endian,
// deflated, JPEG (baseline, extended, lossless), JPEG-LS and RLE through
// DCMTK; JPEG 2000 (1.2.840.10008.1.2.4.90/.91) through GDCM, used only when
// DCMTK cannot decode. Anything else: UNIMPLEMENTED naming the syntax.
//
// Slices: single-frame images, and the frames of enhanced multi-frame
// images, whose position, orientation, pixel spacing and rescale come from
// the functional groups (per-frame item first, then the shared one). Frames
// are grouped into volumes by StackID, TemporalPositionIndex and FrameType
// (with ComplexImageComponent). Several volumes in the chosen series (e.g. a
// Philips B0 map stored as magnitude and field-map frames at the same 32
// positions, or Siemens XA temporal positions in separate files) are
// FAILED_PRECONDITION naming each one, unless options.volume picks one.
//
// The image stack:
// - Grouped by SeriesInstanceUID (or, without one, as above). When several
//   image series are present and options.series_instance_uid is empty, the
//   call fails with FAILED_PRECONDITION naming each series (UID or name,
//   modality, image count) so the user can choose one.
// - Sorted along the slice normal n = row x column (ImageOrientationPatient);
//   the position of a slice is ImagePositionPatient . n.
// - Voxel values are modality values (HU for CT): stored value * RescaleSlope
//   + RescaleIntercept, per slice (per frame).
// - Grid: size = (Columns, Rows, slices); spacing = (PixelSpacing[1] (between
//   columns), PixelSpacing[0] (between rows), median gap between slice
//   positions); origin = ImagePositionPatient of the first sorted slice;
//   direction columns = (row direction, column direction, n). All in LPS mm.
// - Non-uniform spacing and missing slices are accepted: the grid's z spacing
//   is then only the median gap, and slices[k].position_along_normal is the
//   truth (uniform_spacing, min_gap_mm and max_gap_mm say how far off).
//   Slice k lies at origin + n * (position_along_normal[k] - [0]).
// - Gantry tilt (positions that move within the image plane from slice to
//   slice): every slice is resampled onto the in-plane grid of the first
//   slice, i.e. shifted by its in-plane offset from the first slice
//   (bilinear; padding with the volume's minimum value), as dcm2niix does.
//   The result is an orthogonal grid along n whose voxels are at their true
//   patient positions; gantry_tilt_degrees reports the angle between the
//   slice-to-slice direction and n. Exact for any in-plane offsets, not just
//   a tilt about one axis; offsets larger than the image are an error.
//
// Errors (INVALID_ARGUMENT unless noted; messages name the problem and the
// file's base name (and frame), never patient data or UIDs of the files):
// - NOT_FOUND: no readable DICOM image in the input.
// - FAILED_PRECONDITION: several series and none chosen; chosen UID absent;
//   several volumes and none chosen; chosen volume absent.
// - Inconsistent Rows/Columns, PixelSpacing or ImageOrientationPatient
//   between slices; two slices at the same position.
// - Modality, BitsAllocated, BitsStored or PixelRepresentation not the same
//   on every slice, and FrameOfReferenceUID (its value never shown) with
//   options.strict_frame_of_reference: the message names the first slice
//   that differs from most and says what differs (or that each slice has
//   its own, see series_layout.h).
//
// Frames of reference: slices whose FrameOfReferenceUIDs differ (several
// UIDs, e.g. an anonymiser that gave every file its own, or some slices
// without one) are read when their geometry is one stack, i.e. passes every
// geometry check above (same Rows/Columns, orientation and pixel spacing,
// distinct positions along one normal, overlapping slices), unless
// options.strict_frame_of_reference. The series then takes the first
// slice's UID (k = 0, as for the study; core/dicom_out gives the outputs
// that one, or one named from the source when it is empty), and a sentence
// in DicomSeries::notes and DicomSeries::warnings says how many UIDs there
// were, that the geometry was checked and which one the outputs use. When
// the geometry is not one stack, the geometry error says that the UIDs
// differ as well.
// - RescaleSlope or RescaleIntercept present but empty, not one finite
//   number, or a RescaleSlope of 0 (checked while scanning headers, before
//   any pixel data is decoded).
// - Undecodable pixel data (UNIMPLEMENTED, transfer syntax named), truncated
//   or short pixel data, fewer encapsulated fragments than frames,
//   SamplesPerPixel != 1, BitsAllocated not 8/16/32 (UNIMPLEMENTED).
//   Native pixel data is checked against Rows x Columns x frames from its
//   length field before it is loaded, and the volume size (and each file's
//   decoded size, all frames) against options.max_voxels before it is
//   allocated.
// - JPEG 2000: GDCM decodes one frame's codestream at a time and never sees
//   the file; the codestream must be a bare J2K codestream (no JP2 wrapper)
//   of one component with exactly Columns x Rows samples, a precision that
//   fits BitsAllocated and at most 4096 tiles, or the file is refused before
//   decoding. Several frames need one fragment per frame.
#ifndef INTERSLICE_CORE_DICOM_SERIES_READER_H_
#define INTERSLICE_CORE_DICOM_SERIES_READER_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/dicom/pixel_decode.h"  // DecodableTransferSyntaxes, ...
#include "core/dicom/series_index.h"  // DicomSeriesSummary, CollectInputFiles
#include "core/geometry/volume.h"

namespace interslice {

struct DicomReadOptions {
  // SeriesInstanceUID to read (or the name of a series without one, see
  // above); empty means "the only image series present".
  std::string series_instance_uid;
  // Upper bound on Columns * Rows * slices, checked before allocation.
  int64_t max_voxels = int64_t{1} << 31;
  // Volume of multi-frame images to read when the series holds several, as
  // named in the FAILED_PRECONDITION message (e.g. "stack 1, temporal
  // position 2, frame type ORIGINAL\PRIMARY\M\NONE"); empty means "the
  // only one".
  std::string volume;
  // Refuse slices whose FrameOfReferenceUIDs differ (INVALID_ARGUMENT) even
  // when their geometry is one stack; default false: read them, with a note
  // (see "Frames of reference" above).
  bool strict_frame_of_reference = false;
};

// One original slice of the series, in volume order (k).
struct DicomSliceInfo {
  std::string path;
  int frame = 0;  // 0-based frame number within the file (multi-frame)
  std::string sop_instance_uid;
  // ImagePositionPatient as stored (before any tilt resampling), mm.
  Vec3 image_position = {0, 0, 0};
  double position_along_normal = 0;  // mm
  double rescale_slope = 1, rescale_intercept = 0;
};

struct DicomSeries {
  Volume<float> image;                 // modality values, e.g. HU
  std::vector<DicomSliceInfo> slices;  // size() == image.grid.size[2]
  std::string series_instance_uid;
  std::string study_instance_uid;
  std::string frame_of_reference_uid;
  std::string modality;
  std::string sop_class_uid;
  std::string volume;  // the multi-frame volume read; empty for single frames
  // SHA-256 (hex) of image.data as read (the modality values, after any
  // gantry tilt correction), only when some slice has no SOP Instance UID
  // (an anonymised source); else empty. What identifies such a source.
  std::string pixel_digest;
  // Gaps between consecutive slice positions, mm (0 for one slice), and
  // whether all are within 1% (or 0.01 mm) of the median.
  bool uniform_spacing = true;
  double min_gap_mm = 0, max_gap_mm = 0;
  // Non-zero when the slices were resampled for gantry tilt (degrees).
  double gantry_tilt_degrees = 0;
  // SliceThickness of the first slice (functional groups for multi-frame
  // objects), mm; 0 when absent.
  double slice_thickness_mm = 0;
  // Files not used: non-DICOM, DICOMDIR, non-image, other series or volumes.
  int64_t skipped_files = 0;
  // What the reader inferred or found missing in the series' files, one
  // sentence each, e.g. "SeriesInstanceUID missing on 4 files: series
  // grouped by modality, orientation, size and pixel spacing" or
  // "SOPClassUID missing on 4 files: taken from the file meta header
  // (MediaStorageSOPClassUID)". Empty for complete files. Never UIDs or
  // patient data: fit for reports and logs.
  std::vector<std::string> notes;
  // The notes (each also in `notes`) a person should see although the read
  // succeeded, i.e. where the reader accepted what a stricter reading
  // refuses: so far the sentence on differing FrameOfReferenceUIDs.
  std::vector<std::string> warnings;
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

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_SERIES_READER_H_
