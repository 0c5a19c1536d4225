#include "core/dicom/dicom_header.h"

#include <cmath>
#include <filesystem>
#include <string>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdatset.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcitem.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcxfer.h"

namespace interslice {
namespace dicom_internal {
namespace {

enum class AttrState { kAbsent, kOk, kInvalid };

std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  if (item.findAndGetOFString(tag, value).bad()) return "";
  return std::string(absl::StripAsciiWhitespace(value.c_str()));
}

// Reads exactly `n` finite numbers of a DS/FD attribute. An empty element
// counts as absent (type 2 attributes may be present without a value).
AttrState GetDoubles(DcmItem& item, const DcmTagKey& tag, double* out, int n) {
  DcmElement* element = nullptr;
  if (item.findAndGetElement(tag, element).bad() || element == nullptr ||
      element->getLength() == 0) {
    return AttrState::kAbsent;
  }
  if (element->getVM() != static_cast<unsigned long>(n)) {
    return AttrState::kInvalid;
  }
  for (int i = 0; i < n; ++i) {
    Float64 value = 0;
    if (element->getFloat64(value, i).bad() || !std::isfinite(value)) {
      return AttrState::kInvalid;
    }
    out[i] = value;
  }
  return AttrState::kOk;
}

// Fills the image attributes of `h` from `ds`; returns the problem that makes
// the slice unusable, if any. Sets h.kind to kNotImage when the object is not
// a slice of a stack at all.
absl::Status ReadImageAttributes(DcmDataset& ds, const std::string& name,
                                 FileHeader& h) {
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  if (!ds.tagExists(DCM_PixelData) || rows == 0 || columns == 0) {
    h.kind = FileKind::kNotImage;
    return absl::OkStatus();
  }
  h.rows = rows;
  h.columns = columns;

  // Checked before the position: enhanced multi-frame objects keep their
  // positions in functional groups, and a user who passes one should learn
  // that multi-frame is unsupported rather than that no image was found.
  Sint32 frames = 1;
  if (ds.findAndGetSint32(DCM_NumberOfFrames, frames).good() && frames > 1) {
    return absl::UnimplementedError(absl::StrCat(
        name, ": multi-frame image (", frames,
        " frames) is not supported yet; only single-frame slices are"));
  }

  const AttrState position =
      GetDoubles(ds, DCM_ImagePositionPatient, h.position.data(), 3);
  const AttrState orientation =
      GetDoubles(ds, DCM_ImageOrientationPatient, h.orientation.data(), 6);
  if (position == AttrState::kAbsent || orientation == AttrState::kAbsent) {
    // Projection images, secondary captures, ...: not part of a stack.
    h.kind = FileKind::kNotImage;
    return absl::OkStatus();
  }
  if (position == AttrState::kInvalid) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid ImagePositionPatient"));
  }
  if (orientation == AttrState::kInvalid) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid ImageOrientationPatient"));
  }
  if (GetDoubles(ds, DCM_PixelSpacing, h.pixel_spacing.data(), 2) !=
          AttrState::kOk ||
      !(h.pixel_spacing[0] > 0) || !(h.pixel_spacing[1] > 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": missing or invalid PixelSpacing"));
  }
  if (GetDoubles(ds, DCM_RescaleSlope, &h.rescale_slope, 1) ==
      AttrState::kInvalid) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid RescaleSlope"));
  }
  if (GetDoubles(ds, DCM_RescaleIntercept, &h.rescale_intercept, 1) ==
      AttrState::kInvalid) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid RescaleIntercept"));
  }
  // Only used for a single slice; an invalid value falls back like a
  // missing one.
  if (GetDoubles(ds, DCM_SliceThickness, &h.slice_thickness, 1) !=
      AttrState::kOk) {
    h.slice_thickness = 0;
  }
  if (GetDoubles(ds, DCM_SpacingBetweenSlices, &h.spacing_between_slices, 1) !=
      AttrState::kOk) {
    h.spacing_between_slices = 0;
  }
  INTERSLICE_ASSIGN_OR_RETURN(h.layout, ReadPixelLayout(ds, name));

  // Native pixel data was not loaded (it is longer than the read limit), but
  // its length field is known: checking it here means that a header claiming
  // a huge image with little data is rejected before anything of the claimed
  // size is allocated. Encapsulated data is checked after decoding.
  if (!DcmXfer(ds.getOriginalXfer()).isEncapsulated()) {
    DcmElement* pixels = nullptr;
    ds.findAndGetElement(DCM_PixelData, pixels);
    const int64_t needed =
        int64_t{h.rows} * h.columns * (h.layout.bits_allocated / 8);
    const Uint32 length = pixels == nullptr ? 0 : pixels->getLengthField();
    if (length == DCM_UndefinedLength || int64_t{length} < needed) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s: pixel data is too short: %d bytes, but %d x %d pixels of %d "
          "bits need %d",
          name, length == DCM_UndefinedLength ? 0 : int64_t{length}, h.columns,
          h.rows, h.layout.bits_allocated, needed));
    }
  }
  return absl::OkStatus();
}

}  // namespace

std::string BaseName(const std::string& path) {
  return std::filesystem::path(path).filename().string();
}

FileHeader ScanFile(const std::string& path) {
  FileHeader h;
  h.path = path;
  const std::string name = BaseName(path);

  DcmFileFormat file;
  const OFCondition loaded =
      file.loadFile(OFFilename(path.c_str()), EXS_Unknown, EGL_noChange,
                    kHeaderMaxReadLength, ERM_autoDetect);
  DcmDataset& ds = *file.getDataset();
  DcmMetaInfo& meta = *file.getMetaInfo();

  if (GetString(meta, DCM_MediaStorageSOPClassUID) ==
          UID_MediaStorageDirectoryStorage ||
      ds.tagExists(DCM_DirectoryRecordSequence)) {
    h.kind = FileKind::kDicomDir;
    return h;
  }

  h.series_uid = GetString(ds, DCM_SeriesInstanceUID);
  h.study_uid = GetString(ds, DCM_StudyInstanceUID);
  h.frame_of_reference_uid = GetString(ds, DCM_FrameOfReferenceUID);
  h.modality = GetString(ds, DCM_Modality);
  h.sop_class_uid = GetString(ds, DCM_SOPClassUID);
  h.sop_instance_uid = GetString(ds, DCM_SOPInstanceUID);

  if (loaded.bad()) {
    // DCMTK keeps what it parsed before the error. A file that got as far as
    // a SeriesInstanceUID is a broken member of that series (typically a
    // truncated copy); dropping it silently could leave a gap at the end of
    // the stack that no spacing check would notice.
    if (h.series_uid.empty()) {
      h.kind = FileKind::kNotDicom;
    } else {
      h.kind = FileKind::kImage;
      h.problem = absl::InvalidArgumentError(absl::StrCat(
          name, ": truncated or unreadable DICOM file (", loaded.text(), ")"));
    }
    return h;
  }
  if (h.series_uid.empty()) {
    // Without a series it cannot be grouped; real images always have one.
    h.kind = FileKind::kNotImage;
    return h;
  }
  h.kind = FileKind::kImage;
  h.problem = ReadImageAttributes(ds, name, h);
  return h;
}

absl::StatusOr<PixelLayout> ReadPixelLayout(DcmItem& item,
                                            const std::string& name) {
  Uint16 samples = 1;
  if (item.findAndGetUint16(DCM_SamplesPerPixel, samples).good() &&
      samples != 1) {
    return absl::UnimplementedError(absl::StrCat(
        name, ": SamplesPerPixel is ", samples,
        " (colour); only greyscale images (SamplesPerPixel 1) are supported"));
  }
  const std::string photometric =
      GetString(item, DCM_PhotometricInterpretation);
  if (!photometric.empty() && photometric != "MONOCHROME1" &&
      photometric != "MONOCHROME2") {
    return absl::UnimplementedError(absl::StrCat(
        name, ": PhotometricInterpretation ", photometric,
        " is not supported; only MONOCHROME1 and MONOCHROME2 are"));
  }

  PixelLayout layout;
  Uint16 bits_allocated = 0;
  if (item.findAndGetUint16(DCM_BitsAllocated, bits_allocated).bad()) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": BitsAllocated is missing"));
  }
  if (bits_allocated != 8 && bits_allocated != 16 && bits_allocated != 32) {
    return absl::UnimplementedError(
        absl::StrCat(name, ": BitsAllocated ", bits_allocated,
                     " is not supported; only 8, 16 and 32 are"));
  }
  layout.bits_allocated = bits_allocated;
  Uint16 bits_stored = bits_allocated;
  item.findAndGetUint16(DCM_BitsStored, bits_stored);
  Uint16 high_bit = bits_stored - 1;
  item.findAndGetUint16(DCM_HighBit, high_bit);
  Uint16 representation = 0;
  item.findAndGetUint16(DCM_PixelRepresentation, representation);
  if (bits_stored < 1 || bits_stored > bits_allocated ||
      high_bit >= bits_allocated || high_bit + 1 < bits_stored) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": inconsistent BitsAllocated ", bits_allocated,
                     ", BitsStored ", bits_stored, ", HighBit ", high_bit));
  }
  if (representation > 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid PixelRepresentation ", representation));
  }
  layout.bits_stored = bits_stored;
  layout.high_bit = high_bit;
  layout.is_signed = representation == 1;
  return layout;
}

}  // namespace dicom_internal
}  // namespace interslice
