// Private to core/dicom_out: helpers shared by the derived-series and SEG
// writers (validation, copying patient/study data, references, atomic save).
#ifndef INTERSLICE_CORE_DICOM_OUT_DICOM_OUT_INTERNAL_H_
#define INTERSLICE_CORE_DICOM_OUT_DICOM_OUT_INTERNAL_H_

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/geometry/volume.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcxfer.h"

class DcmFileFormat;
class OFCondition;
class DcmItem;
class DcmSegmentation;

namespace interslice::dicom_out_internal {

// OK when `condition` is good, else INTERNAL "<object>: cannot <what>: <DCMTK's
// text>" (`object` names the object being written, e.g. "RTSTRUCT").
absl::Status CheckDcmtk(const OFCondition& condition, absl::string_view object,
                        absl::string_view what);

// Purpose of reference for source images (DICOM CID 7202).
inline constexpr char kSourceImagePurposeCode[] = "121322";
inline constexpr char kSourceImagePurposeMeaning[] =
    "Source image for image processing operation";

// INVALID_ARGUMENT unless `grid` is valid, holds `voxel_count` voxels, fits
// DICOM's 16-bit Rows/Columns and shares the source grid's direction. `what`
// names the volume in messages.
absl::Status ValidateOutputGrid(const DicomSeries& source, const Grid& grid,
                                size_t voxel_count, const char* what);

// Position of slice k of `grid` along its third axis (the source normal), mm.
double SlicePositionAlongNormal(const Grid& grid, int64_t k);

// Indices of the source slices an output slice at `position` (mm along the
// normal) was computed from: the slice it lies on (within 1e-3 mm), else the
// two that bracket it, else the nearest one.
std::vector<int64_t> NearestSourceSlices(const DicomSeries& source,
                                         double position);

// How the intensity series stores modality values (derived_series.cc; the
// classic and the enhanced layout share it, so both hold the same stored
// values): value = stored * slope + intercept.
struct Encoding {
  double slope = 1;
  double intercept = 0;
  bool is_signed = false;
  double window_center = 0;
  double window_width = 1;
  std::string rescale_type;  // "US" (unspecified) or "HU"
  std::string description;   // appended to DerivationDescription
};

// A pair of window values and its explanation (VOI LUT module).
struct Window {
  double center = 0;
  double width = 1;
  std::string explanation;
};

// Every WindowCenter/WindowWidth pair of the source (with its explanation),
// or none when they are absent, unpaired or unusable.
std::vector<Window> SourceWindows(DcmItem& source_header);

// The encoding of `values` (WriteIntensitySeries' contract: the first source
// slice's rescale, the slope raised along 1-2-5 steps only if a value does
// not fit 16 bits). INVALID_ARGUMENT for non-finite or unencodable values.
absl::StatusOr<Encoding> ChooseEncoding(const DicomSeries& source,
                                        const Volume<float>& values,
                                        const DicomWriteOptions& options);

// The source's padding (modality units) as a stored value of `encoding`, if
// it is representable.
std::optional<double> StoredPaddingValue(const Encoding& encoding,
                                         std::optional<float> padding);

// Stores slice k of `values` into `stored` (nx * ny values; signed values
// as their two's complement bits).
void EncodeSlice(const Volume<float>& values, int64_t k,
                 const Encoding& encoding, uint16_t* stored);

// Loads the first source file without its pixel data. FAILED_PRECONDITION
// (naming the file's base name) if it cannot be read.
absl::StatusOr<std::unique_ptr<DcmFileFormat>> LoadSourceHeader(
    const DicomSeries& source);

// Copies SpecificCharacterSet and the Patient, Clinical Trial Subject,
// General Study, Patient Study, Clinical Trial Study and Frame of Reference
// attributes present in `from`, except empty ones (an empty conditional
// attribute is an error of the source that must not pass into ours; empty
// items of copied sequences are dropped likewise); writes absent type 2
// attributes empty.
// StudyInstanceUID and FrameOfReferenceUID are then set from `identity`
// (the source's, or the job's own for a source without them).
void CopyPatientStudyFrameOfReference(DcmItem& from,
                                      const DerivedObjectIdentity& identity,
                                      DcmItem& to);

// The anatomy of an image series that shows the source (General Series
// BodyPartExamined and Laterality, General Image ImageLaterality): the
// source's values when valid (BodyPartExamined a CS; Laterality R or L;
// ImageLaterality R, L, U or B), dropped otherwise. Laterality is type 2C,
// required unless the body part is unpaired or ImageLaterality is sent
// (PS3.3 C.7.3.1): with neither in the source and a body part that is absent
// or not known to be unpaired (DICOM PS3.16 Annex L; the terms dciodvfy
// knows as unpaired), it is written empty, meaning unknown.
void CopyAnatomy(DcmItem& from, DcmItem& to);

// Adds ReferencedSeriesSequence (Common Instance Reference module) listing
// every source instance that has a SOP Instance UID (none when the source
// has no SeriesInstanceUID: an anonymised source cannot be referenced).
void AddReferencedSeries(const DicomSeries& source, DcmItem& to);

// Adds ReferencedSeriesSequence listing every instance of `series` (a derived
// image series this object lies on), replacing any there.
void AddReferencedImageSeries(const DerivedObjectIdentity& series, DcmItem& to);

// True for the SOP classes of the enhanced layout's intensity object
// (Enhanced CT Image, Enhanced MR Image): one multi-frame instance whose
// frame k + 1 is output slice k (core/dicom_out/enhanced_series.h).
bool IsEnhancedImageSopClass(const std::string& sop_class_uid);

// The image slice k of `referenced` (an intensity object on the same grid)
// is: image k of a classic series (frame_number 0: the whole single-frame
// instance), or frame k + 1 of the one enhanced instance.
struct SliceImageReference {
  std::string sop_instance_uid;
  int64_t frame_number = 0;
};
SliceImageReference ReferenceSliceImage(const DerivedObjectIdentity& referenced,
                                        int64_t k);

// INVALID_ARGUMENT unless `identity` names one instance (with a series and a
// dimension organization UID) and `referenced` names one image per slice of
// `grid` (or is one enhanced multi-frame instance, a frame per slice). `what`
// names the object in messages.
absl::Status CheckReferencedSeries(const DerivedObjectIdentity& identity,
                                   const DerivedObjectIdentity& referenced,
                                   const Grid& grid, const char* what);

// DS text for `value` (at most 16 characters, as many digits as fit).
std::string FormatDecimalString(double value);

// DCMTK's current date (YYYYMMDD) and time (HHMMSS).
std::string CurrentDate();
std::string CurrentTime();

// Saves `file` in `xfer` (default Little Endian Explicit; an encapsulated
// syntax such as EXS_RLELossless first encodes the pixel data with DCMTK's
// codec, registered here once) to "<path>.tmp-<random>", syncs it and
// renames it to `path`. INTERNAL naming `path` on failure; the temporary
// file never survives a failure.
absl::Status SaveFileAtomically(
    DcmFileFormat& file, const std::string& path,
    E_TransferSyntax xfer = EXS_LittleEndianExplicit);

// SaveFileAtomically in two steps, for the many files of an image series:
// one fsync per file as it is written cost ~30% of the DICOM write stage on
// the phantom (docs/speed/whole-job-notes.md). SaveFileUnsynced encodes and
// saves to a temporary beside `path` and asks the kernel to start writing it
// back (sync_file_range, not waiting); it returns the temporary's name.
// CommitFile fsyncs the temporary (by then mostly written) and renames it to
// `path`; on failure it removes the temporary. The caller removes the
// temporaries it does not commit. SyncDirectory fsyncs a folder once, so the
// renames in it are durable too.
absl::StatusOr<std::string> SaveFileUnsynced(
    DcmFileFormat& file, const std::string& path,
    E_TransferSyntax xfer = EXS_LittleEndianExplicit);
absl::Status CommitFile(const std::string& temp, const std::string& path);
absl::Status SyncDirectory(const std::string& dir);

// The set-up both SEG writers (segmentation.cc: run's binary SEG;
// label_segmentation.cc: fill's multi-segment SEG) share. A binary
// DcmSegmentation of `grid`'s rows and columns with interslice as its
// equipment; the identity's study, frame of reference (each falling back to
// the source's when empty), series and SOP instance UIDs, series number,
// description (<= 64 characters), date and time; the geometry all frames
// share (Pixel Measures, Plane Orientation) and the two dimensions: segment,
// then ImagePositionPatient (DICOM PS3.3 C.8.20.2.3). INTERNAL naming the
// step DCMTK refused.
absl::StatusOr<std::unique_ptr<DcmSegmentation>> CreateBinarySegmentation(
    const DicomSeries& source, const Grid& grid,
    const DerivedObjectIdentity& identity, const DicomWriteOptions& options);

// `rgb` (sRGB, 0..255 each) as a DICOM CIELab colour (PS3.3 C.10.7.1.1:
// CIELab D65 scaled to 0..65535 each), for RecommendedDisplayCIELabValue:
// DCMTK's IODCIELabUtil does the conversion. Both SEG writers colour their
// segments with it, so that a colour means the same in either.
std::array<uint16_t, 3> RgbToDicomCieLab(const std::array<uint8_t, 3>& rgb);

// Adds `frame` (nx*ny bytes, each 0 or 1) as the frame of segment
// `segment_number` on slice k of `grid`: its plane position, its dimension
// index values (segment, k + 1) and a derivation naming image k of
// `referenced`, the image a viewer overlays it on.
absl::Status AddSegmentationFrame(DcmSegmentation& seg, const Grid& grid,
                                  int64_t k, uint16_t segment_number,
                                  const DerivedObjectIdentity& referenced,
                                  const std::string& derivation_description,
                                  const uint8_t* frame);

// Encodes `seg`, copies patient and study data from `source_header`, lists
// `referenced` as the referenced series and saves the file atomically.
absl::Status SaveSegmentation(DcmSegmentation& seg, DcmItem& source_header,
                              const DerivedObjectIdentity& identity,
                              const DerivedObjectIdentity& referenced,
                              const std::string& path);

}  // namespace interslice::dicom_out_internal

#endif  // INTERSLICE_CORE_DICOM_OUT_DICOM_OUT_INTERNAL_H_
