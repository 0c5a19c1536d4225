// WriteIntensitySeries: one single-frame DICOM image per output slice.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <system_error>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
#include "core/dicom_out/dicom_writer.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcitem.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcvrss.h"
#include "dcmtk/dcmdata/dcvrus.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using dicom_out_internal::Encoding;

// The 1-2-5 ladder times `base`: base, 2 base, 5 base, 10 base, ...
double LadderStep(double base, int step) {
  static constexpr double kMantissa[] = {1, 2, 5};
  return base * kMantissa[step % 3] * std::pow(10.0, step / 3);
}

struct Range {
  double min = 0, max = 0;
};

absl::StatusOr<Range> FiniteRange(const std::vector<float>& data) {
  Range range{std::numeric_limits<double>::infinity(),
              -std::numeric_limits<double>::infinity()};
  for (float v : data) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(
          "values contain NaN or infinity; cannot encode them in DICOM");
    }
    range.min = std::min(range.min, static_cast<double>(v));
    range.max = std::max(range.max, static_cast<double>(v));
  }
  return range;
}

// Chooses slope (from the ladder starting at `base`) and signedness so that
// every value of `range` rounds to a 16-bit stored value.
absl::Status FitSlope(const Range& range, double base, double intercept,
                      Encoding& encoding) {
  for (int step = 0; step < 60; ++step) {
    const double slope = LadderStep(base, step);
    const double lo = std::round((range.min - intercept) / slope);
    const double hi = std::round((range.max - intercept) / slope);
    if (lo >= 0 && hi <= 65535) {
      encoding.slope = slope;
      encoding.is_signed = false;
      return absl::OkStatus();
    }
    if (lo >= -32768 && hi <= 32767) {
      encoding.slope = slope;
      encoding.is_signed = true;
      return absl::OkStatus();
    }
  }
  return absl::InvalidArgumentError(
      absl::StrFormat("values from %g to %g cannot be encoded in 16 bits",
                      range.min, range.max));
}

}  // namespace

namespace dicom_out_internal {

std::vector<Window> SourceWindows(DcmItem& source_header) {
  std::vector<Window> windows;
  for (unsigned long i = 0;; ++i) {
    Float64 center = 0, width = 0;
    if (source_header.findAndGetFloat64(DCM_WindowCenter, center, i).bad() ||
        source_header.findAndGetFloat64(DCM_WindowWidth, width, i).bad()) {
      break;
    }
    if (!std::isfinite(center) || !std::isfinite(width) || width < 1) {
      return {};
    }
    Window window{center, width, ""};
    OFString explanation;
    if (source_header
            .findAndGetOFString(DCM_WindowCenterWidthExplanation, explanation,
                                i)
            .good()) {
      window.explanation = explanation.c_str();
    }
    windows.push_back(window);
  }
  return windows;
}

absl::StatusOr<Encoding> ChooseEncoding(const DicomSeries& source,
                                        const Volume<float>& values,
                                        const DicomWriteOptions& options) {
  INTERSLICE_ASSIGN_OR_RETURN(const Range range, FiniteRange(values.data));
  Encoding e;
  const DicomSliceInfo& first = source.slices.front();
  const double base = first.rescale_slope > 0 ? first.rescale_slope : 1;
  e.intercept = first.rescale_intercept;
  INTERSLICE_RETURN_IF_ERROR(FitSlope(range, base, e.intercept, e));
  e.window_center = 0.5 * (range.min + range.max);
  e.window_width = std::max(1.0, range.max - range.min);
  e.rescale_type = source.modality == "CT" ? "HU" : "US";
  e.description =
      options.intensity_interpolation ==
              DicomWriteOptions::IntensityInterpolation::kMorph
          ? "source modality values at the output slice positions, carried "
            "along the motion registered between the two nearest source "
            "slices (registration-based interpolation, Penney et al. 2004), "
            "linearly interpolated where the registration is unreliable"
          : "source modality values at the output slice positions, linearly "
            "interpolated between the two nearest source slices at their true "
            "positions";
  return e;
}

std::optional<double> StoredPaddingValue(const Encoding& encoding,
                                         std::optional<float> padding) {
  if (!padding.has_value()) return std::nullopt;
  const double stored =
      std::round((*padding - encoding.intercept) / encoding.slope);
  if (encoding.is_signed ? (stored >= -32768 && stored <= 32767)
                         : (stored >= 0 && stored <= 65535)) {
    return stored;
  }
  return std::nullopt;
}

void EncodeSlice(const Volume<float>& values, int64_t k,
                 const Encoding& encoding, uint16_t* stored) {
  const size_t pixels =
      static_cast<size_t>(values.grid.size[0] * values.grid.size[1]);
  const float* slice = &values.data[pixels * static_cast<size_t>(k)];
  for (size_t i = 0; i < pixels; ++i) {
    const double value =
        std::round((slice[i] - encoding.intercept) / encoding.slope);
    stored[i] = encoding.is_signed
                    ? static_cast<Uint16>(static_cast<int16_t>(value))
                    : static_cast<Uint16>(value);
  }
}

}  // namespace dicom_out_internal

namespace {

namespace fs = std::filesystem;
using dicom_out_internal::AddReferencedSeries;
using dicom_out_internal::ChooseEncoding;
using dicom_out_internal::CommitFile;
using dicom_out_internal::CopyAnatomy;
using dicom_out_internal::CopyPatientStudyFrameOfReference;
using dicom_out_internal::CurrentDate;
using dicom_out_internal::CurrentTime;
using dicom_out_internal::EncodeSlice;
using dicom_out_internal::Encoding;
using dicom_out_internal::FormatDecimalString;
using dicom_out_internal::kSourceImagePurposeCode;
using dicom_out_internal::kSourceImagePurposeMeaning;
using dicom_out_internal::LoadSourceHeader;
using dicom_out_internal::NearestSourceSlices;
using dicom_out_internal::SaveFileUnsynced;
using dicom_out_internal::SlicePositionAlongNormal;
using dicom_out_internal::SourceWindows;
using dicom_out_internal::StoredPaddingValue;
using dicom_out_internal::SyncDirectory;
using dicom_out_internal::ValidateOutputGrid;
using dicom_out_internal::Window;

enum class Iod { kCt, kMr, kSecondaryCapture };

Iod ChooseIod(const std::string& sop_class_uid) {
  if (sop_class_uid == UID_CTImageStorage) return Iod::kCt;
  if (sop_class_uid == UID_MRImageStorage) return Iod::kMr;
  return Iod::kSecondaryCapture;
}

void CopyIfPresent(DcmItem& from, DcmItem& to, const DcmTagKey& tag,
                   const char* fallback /* nullptr: empty */) {
  DcmElement* element = nullptr;
  if (from.findAndGetElement(tag, element, OFFalse, OFTrue).good() &&
      element != nullptr && element->getLength() > 0) {
    to.insert(element, OFTrue);
    return;
  }
  delete element;
  if (fallback != nullptr) {
    to.putAndInsertString(tag, fallback);
  } else {
    to.insertEmptyElement(tag);
  }
}

// Copies `tag` when the source has a value for it: an empty value of an
// optional or conditional attribute would be an error of ours.
void CopyIfNotEmpty(DcmItem& from, DcmItem& to, const DcmTagKey& tag) {
  DcmElement* element = nullptr;
  if (from.findAndGetElement(tag, element, OFFalse, OFTrue).good() &&
      element != nullptr) {
    if (element->getLength() > 0) {
      to.insert(element, OFTrue);
      return;
    }
    delete element;
  }
}

// Acquisition attributes the CT/MR Image modules require (type 1 and 2),
// copied from the source; they describe how the underlying data were
// acquired.
void CopyAcquisitionAttributes(Iod iod, DcmItem& from, DcmItem& to) {
  if (iod == Iod::kCt) {
    CopyIfPresent(from, to, DCM_KVP, nullptr);
    CopyIfPresent(from, to, DCM_AcquisitionNumber, nullptr);
  } else if (iod == Iod::kMr) {
    // Type 1: "RM" (research mode) and "NONE" are the neutral values when the
    // source lacks them.
    CopyIfPresent(from, to, DCM_ScanningSequence, "RM");
    CopyIfPresent(from, to, DCM_SequenceVariant, "NONE");
    for (const DcmTagKey& tag :
         {DCM_ScanOptions, DCM_MRAcquisitionType, DCM_RepetitionTime,
          DCM_EchoTime, DCM_EchoTrainLength}) {
      CopyIfPresent(from, to, tag, nullptr);
    }
    for (const DcmTagKey& tag :
         {DCM_InversionTime, DCM_SequenceName, DCM_AngioFlag,
          DCM_MagneticFieldStrength, DCM_ImagedNucleus, DCM_FlipAngle}) {
      CopyIfNotEmpty(from, to, tag);
    }
  }
  CopyIfNotEmpty(from, to, DCM_PatientPosition);
  // BodyPartExamined and the Laterality it may require.
  CopyAnatomy(from, to);
  // Patient Position is type 2C for CT and MR images (required unless a
  // Patient Orientation Code Sequence is present, which we never write).
  if (iod != Iod::kSecondaryCapture && !to.tagExists(DCM_PatientPosition)) {
    to.insertEmptyElement(DCM_PatientPosition);
  }
}

// Patient orientation letters (L/R, P/A, H/F) of an LPS direction, strongest
// component first, for the PatientOrientation attribute.
std::string OrientationLetters(const Vec3& v) {
  static constexpr char kPositive[] = {'L', 'P', 'H'};
  static constexpr char kNegative[] = {'R', 'A', 'F'};
  int order[3] = {0, 1, 2};
  std::sort(order, order + 3,
            [&v](int a, int b) { return std::abs(v[a]) > std::abs(v[b]); });
  std::string letters;
  for (int axis : order) {
    if (std::abs(v[axis]) < 1e-4) break;
    letters.push_back(v[axis] > 0 ? kPositive[axis] : kNegative[axis]);
  }
  return letters;
}

absl::Status CreateFolder(const std::string& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) {
    return absl::InternalError(absl::StrCat("cannot create the output folder ",
                                            dir, ": ", ec.message()));
  }
  if (!fs::is_directory(dir, ec)) {
    return absl::InternalError(
        absl::StrCat("the output path ", dir, " is not a folder"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::vector<std::string>> WriteIntensitySeries(
    const DicomSeries& source, const Volume<float>& values,
    const DerivedObjectIdentity& identity, const DicomWriteOptions& options,
    const std::string& output_dir) {
  const Grid& grid = values.grid;
  INTERSLICE_RETURN_IF_ERROR(
      ValidateOutputGrid(source, grid, values.data.size(), "intensity series"));
  if (static_cast<int64_t>(identity.sop_instance_uids.size()) != grid.size[2]) {
    return absl::InvalidArgumentError(
        absl::StrFormat("intensity series: %d SOP instance UIDs for %d slices",
                        identity.sop_instance_uids.size(), grid.size[2]));
  }
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& src = *source_file->getDataset();
  INTERSLICE_ASSIGN_OR_RETURN(const Encoding encoding,
                              ChooseEncoding(source, values, options));
  std::vector<Window> windows = SourceWindows(src);
  if (windows.empty()) {
    windows.push_back({encoding.window_center, encoding.window_width, ""});
  }
  // The source's padding value, in our stored units (the same as the
  // source's whenever the slope was not raised, which linear blending of its
  // values never needs).
  INTERSLICE_ASSIGN_OR_RETURN(const std::optional<float> padding,
                              SourcePixelPadding(source));
  const std::optional<double> stored_padding =
      StoredPaddingValue(encoding, padding);
  INTERSLICE_RETURN_IF_ERROR(CreateFolder(output_dir));

  const Iod iod = ChooseIod(identity.sop_class_uid);
  const char* sop_class = identity.sop_class_uid.c_str();
  // MR images have no Modality LUT module: write the rescale only when it is
  // not the identity (a standard extended attribute then).
  const bool write_rescale =
      iod != Iod::kMr || encoding.slope != 1 || encoding.intercept != 0;
  const std::string date = CurrentDate();
  const std::string time = CurrentTime();
  const std::string description =
      identity.series_description.substr(0, 64);  // LO
  std::string derivation = options.derivation_description;
  if (!derivation.empty()) derivation += "; ";
  derivation += encoding.description;
  if (derivation.size() > 1024) derivation.resize(1024);  // ST limit
  std::string window_centers, window_widths, window_explanations;
  bool any_explanation = false;
  for (size_t w = 0; w < windows.size(); ++w) {
    const char* separator = w == 0 ? "" : "\\";
    absl::StrAppend(&window_centers, separator,
                    FormatDecimalString(windows[w].center));
    absl::StrAppend(&window_widths, separator,
                    FormatDecimalString(windows[w].width));
    absl::StrAppend(&window_explanations, separator, windows[w].explanation);
    any_explanation |= !windows[w].explanation.empty();
  }
  const Vec3 row = grid.Axis(0), col = grid.Axis(1);
  const std::string orientation = absl::StrCat(
      FormatDecimalString(row[0]), "\\", FormatDecimalString(row[1]), "\\",
      FormatDecimalString(row[2]), "\\", FormatDecimalString(col[0]), "\\",
      FormatDecimalString(col[1]), "\\", FormatDecimalString(col[2]));
  const std::string pixel_spacing =
      absl::StrCat(FormatDecimalString(grid.spacing[1]), "\\",
                   FormatDecimalString(grid.spacing[0]));
  const std::string slice_spacing = FormatDecimalString(grid.spacing[2]);
  // No content-specific value 4: the CT/MR defined terms have none for a
  // mask or a distance map (SeriesDescription and DerivationDescription say
  // what the series holds).
  // MR requires a value 3; "OTHER" is the neutral choice.
  const std::string image_type = iod == Iod::kCt   ? "DERIVED\\SECONDARY\\AXIAL"
                                 : iod == Iod::kMr ? "DERIVED\\SECONDARY\\OTHER"
                                                   : "DERIVED\\SECONDARY";

  const int64_t nx = grid.size[0], ny = grid.size[1], nz = grid.size[2];
  std::vector<std::string> paths(static_cast<size_t>(nz));
  // Written but not yet committed (see the end).
  std::vector<std::string> temps(static_cast<size_t>(nz));
  // One instance: slice k, from this worker's copy of the source header
  // `header` (DCMTK loads its large values lazily from the file, so a header is
  // never shared between threads) and its pixel buffer.
  auto write_instance = [&](DcmDataset& header, std::vector<Uint16>& pixels,
                            int64_t k) -> absl::Status {
    DcmFileFormat file;
    DcmDataset& ds = *file.getDataset();
    CopyPatientStudyFrameOfReference(header, identity, ds);

    // SOP Common, General Series, General Equipment.
    const std::string& sop_uid =
        identity.sop_instance_uids[static_cast<size_t>(k)];
    ds.putAndInsertString(DCM_SOPClassUID, sop_class);
    ds.putAndInsertString(DCM_SOPInstanceUID, sop_uid.c_str());
    ds.putAndInsertString(DCM_InstanceCreationDate, date.c_str());
    ds.putAndInsertString(DCM_InstanceCreationTime, time.c_str());
    ds.putAndInsertString(DCM_Modality, iod == Iod::kSecondaryCapture
                                            ? source.modality.c_str()
                                            : (iod == Iod::kCt ? "CT" : "MR"));
    if (iod == Iod::kSecondaryCapture) {
      // SC Equipment module: the conversion type of derived data.
      ds.putAndInsertString(DCM_ConversionType, "WSD");
    }
    ds.putAndInsertString(DCM_SeriesInstanceUID,
                          identity.series_instance_uid.c_str());
    ds.putAndInsertString(DCM_SeriesNumber,
                          std::to_string(identity.series_number).c_str());
    ds.putAndInsertString(DCM_SeriesDate, date.c_str());
    ds.putAndInsertString(DCM_SeriesTime, time.c_str());
    ds.putAndInsertString(DCM_SeriesDescription, description.c_str());
    ds.putAndInsertString(DCM_Manufacturer, "interslice");
    ds.putAndInsertString(DCM_ManufacturerModelName, "interslice");
    ds.putAndInsertString(DCM_SoftwareVersions,
                          options.software_version.c_str());
    CopyAcquisitionAttributes(iod, header, ds);

    // General Image.
    ds.putAndInsertString(DCM_InstanceNumber, std::to_string(k + 1).c_str());
    ds.putAndInsertString(DCM_ContentDate, date.c_str());
    ds.putAndInsertString(DCM_ContentTime, time.c_str());
    ds.putAndInsertString(DCM_ImageType, image_type.c_str());
    if (iod == Iod::kSecondaryCapture) {
      // Type 2C in SC images, whose IOD has no Image Plane module.
      ds.putAndInsertString(
          DCM_PatientOrientation,
          absl::StrCat(OrientationLetters(row), "\\", OrientationLetters(col))
              .c_str());
    }
    ds.putAndInsertString(DCM_DerivationDescription, derivation.c_str());
    const double position = SlicePositionAlongNormal(grid, k);
    std::vector<int64_t> references = NearestSourceSlices(source, position);
    if (references.size() == 2 &&
        options.intensity_interpolation ==
            DicomWriteOptions::IntensityInterpolation::kMorph) {
      // The morph's value tangents come from the outer neighbours too.
      if (references[0] > 0) references.push_back(references[0] - 1);
      if (references[1] + 1 < static_cast<int64_t>(source.slices.size()))
        references.push_back(references[1] + 1);
    }
    for (int64_t s : references) {
      // An anonymised source slice without a SOP Instance UID cannot be
      // referenced.
      if (source.slices[s].sop_instance_uid.empty() ||
          source.sop_class_uid.empty()) {
        continue;
      }
      DcmItem* item = nullptr;
      ds.findOrCreateSequenceItem(DCM_SourceImageSequence, item, -2);
      item->putAndInsertString(DCM_ReferencedSOPClassUID,
                               source.sop_class_uid.c_str());
      item->putAndInsertString(DCM_ReferencedSOPInstanceUID,
                               source.slices[s].sop_instance_uid.c_str());
      DcmItem* purpose = nullptr;
      item->findOrCreateSequenceItem(DCM_PurposeOfReferenceCodeSequence,
                                     purpose, 0);
      purpose->putAndInsertString(DCM_CodeValue, kSourceImagePurposeCode);
      purpose->putAndInsertString(DCM_CodingSchemeDesignator, "DCM");
      purpose->putAndInsertString(DCM_CodeMeaning, kSourceImagePurposeMeaning);
    }
    AddReferencedSeries(source, ds);

    // Image Plane.
    const Vec3 origin = grid.IndexToPhysical({0, 0, static_cast<double>(k)});
    ds.putAndInsertString(DCM_ImagePositionPatient,
                          absl::StrCat(FormatDecimalString(origin[0]), "\\",
                                       FormatDecimalString(origin[1]), "\\",
                                       FormatDecimalString(origin[2]))
                              .c_str());
    ds.putAndInsertString(DCM_ImageOrientationPatient, orientation.c_str());
    ds.putAndInsertString(DCM_PixelSpacing, pixel_spacing.c_str());
    ds.putAndInsertString(DCM_SliceThickness, slice_spacing.c_str());
    ds.putAndInsertString(DCM_SpacingBetweenSlices, slice_spacing.c_str());
    ds.putAndInsertString(DCM_SliceLocation,
                          FormatDecimalString(position).c_str());

    // Image Pixel and Modality LUT / VOI LUT.
    ds.putAndInsertUint16(DCM_SamplesPerPixel, 1);
    ds.putAndInsertString(DCM_PhotometricInterpretation, "MONOCHROME2");
    ds.putAndInsertUint16(DCM_Rows, static_cast<Uint16>(ny));
    ds.putAndInsertUint16(DCM_Columns, static_cast<Uint16>(nx));
    ds.putAndInsertUint16(DCM_BitsAllocated, 16);
    ds.putAndInsertUint16(DCM_BitsStored, 16);
    ds.putAndInsertUint16(DCM_HighBit, 15);
    ds.putAndInsertUint16(DCM_PixelRepresentation, encoding.is_signed ? 1 : 0);
    if (write_rescale) {
      ds.putAndInsertString(DCM_RescaleIntercept,
                            FormatDecimalString(encoding.intercept).c_str());
      ds.putAndInsertString(DCM_RescaleSlope,
                            FormatDecimalString(encoding.slope).c_str());
      ds.putAndInsertString(DCM_RescaleType, encoding.rescale_type.c_str());
    }
    ds.putAndInsertString(DCM_WindowCenter, window_centers.c_str());
    ds.putAndInsertString(DCM_WindowWidth, window_widths.c_str());
    if (any_explanation) {
      ds.putAndInsertString(DCM_WindowCenterWidthExplanation,
                            window_explanations.c_str());
    }
    if (stored_padding.has_value()) {
      // The dictionary's VR is US or SS ("xs"): say which, as
      // PixelRepresentation does.
      if (encoding.is_signed) {
        auto* element =
            new DcmSignedShort(DcmTag(DCM_PixelPaddingValue, EVR_SS));
        element->putSint16(static_cast<Sint16>(*stored_padding));
        ds.insert(element, OFTrue);
      } else {
        auto* element =
            new DcmUnsignedShort(DcmTag(DCM_PixelPaddingValue, EVR_US));
        element->putUint16(static_cast<Uint16>(*stored_padding));
        ds.insert(element, OFTrue);
      }
    }

    EncodeSlice(values, k, encoding, pixels.data());
    ds.putAndInsertUint16Array(DCM_PixelData, pixels.data(),
                               static_cast<unsigned long>(pixels.size()));

    // The file meta header names the same SOP instance.
    const std::string path =
        (fs::path(output_dir) / absl::StrFormat("IM%05d.dcm", k + 1)).string();
    INTERSLICE_ASSIGN_OR_RETURN(
        temps[static_cast<size_t>(k)],
        SaveFileUnsynced(file, path,
                         options.intensity_encoding ==
                                 DicomWriteOptions::PixelEncoding::kRleLossless
                             ? EXS_RLELossless
                             : EXS_LittleEndianExplicit));
    paths[static_cast<size_t>(k)] = path;
    return absl::OkStatus();
  };
  // Instances are independent files: they are written in parallel, in
  // contiguous runs of slices, on the calling task arena's threads (RunJob
  // calls writers inside its arena of ComputeContext::threads). Each file's
  // writeback starts as it is saved; the fsyncs come after all are written.
  const int64_t runs = std::min<int64_t>(
      nz, 4 * static_cast<int64_t>(tbb::this_task_arena::max_concurrency()));
  std::vector<absl::Status> run_status(static_cast<size_t>(runs));
  tbb::parallel_for(int64_t{0}, runs, [&](int64_t r) {
    absl::StatusOr<std::unique_ptr<DcmFileFormat>> run_header =
        r == 0 ? std::move(source_file) : LoadSourceHeader(source);
    if (!run_header.ok()) {
      run_status[static_cast<size_t>(r)] = run_header.status();
      return;
    }
    std::vector<Uint16> pixels(static_cast<size_t>(nx * ny));
    for (int64_t k = r * nz / runs; k < (r + 1) * nz / runs; ++k) {
      absl::Status status =
          write_instance(*(*run_header)->getDataset(), pixels, k);
      if (!status.ok()) {
        run_status[static_cast<size_t>(r)] = std::move(status);
        return;
      }
    }
  });
  absl::Status failed;
  for (absl::Status& status : run_status) failed.Update(status);
  if (!failed.ok()) {
    for (const std::string& temp : temps) {
      if (!temp.empty()) std::remove(temp.c_str());
    }
    return failed;
  }
  // Every instance is written: make each durable under its name (CommitFile
  // removes its temporary when it fails), in parallel, then the folder once.
  std::vector<absl::Status> commit_status(static_cast<size_t>(nz));
  tbb::parallel_for(int64_t{0}, nz, [&](int64_t k) {
    commit_status[static_cast<size_t>(k)] = CommitFile(
        temps[static_cast<size_t>(k)], paths[static_cast<size_t>(k)]);
  });
  for (absl::Status& status : commit_status) failed.Update(status);
  if (failed.ok()) failed = SyncDirectory(output_dir);
  if (!failed.ok()) return failed;
  return paths;
}

}  // namespace interslice
