// WriteSegmentation: a binary DICOM SEG of the mask (DCMTK dcmseg).
#include <array>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/label_segmentation.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmfg/fgderimg.h"
#include "dcmtk/dcmfg/fgfracon.h"
#include "dcmtk/dcmfg/fgpixmsr.h"
#include "dcmtk/dcmfg/fgplanor.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmiod/iodmacro.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"

namespace interslice {
namespace {

using dicom_out_internal::AddReferencedImageSeries;
using dicom_out_internal::AddSegmentationFrame;
using dicom_out_internal::CheckReferencedSeries;
using dicom_out_internal::CopyPatientStudyFrameOfReference;
using dicom_out_internal::CreateBinarySegmentation;
using dicom_out_internal::CurrentDate;
using dicom_out_internal::CurrentTime;
using dicom_out_internal::FormatDecimalString;
using dicom_out_internal::LoadSourceHeader;
using dicom_out_internal::ReferenceSliceImage;
using dicom_out_internal::RgbToDicomCieLab;
using dicom_out_internal::SaveFileAtomically;
using dicom_out_internal::SaveSegmentation;
using dicom_out_internal::SliceImageReference;
using dicom_out_internal::ValidateOutputGrid;

absl::Status Check(const OFCondition& cond, const char* what) {
  if (cond.good()) return absl::OkStatus();
  return absl::InternalError(
      absl::StrCat("DICOM SEG: cannot ", what, ": ", cond.text()));
}

absl::Status ValidateCode(const CodedConcept& code, const char* what) {
  if (code.value.empty() || code.scheme.empty() || code.meaning.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "segment ", what, " code needs a value, a scheme and a meaning"));
  }
  return absl::OkStatus();
}

// DICOM PS3.5 6.2: the default character repertoire minus backslash (the
// value delimiter) and control characters.
bool IsPlainText(std::string_view text) {
  for (const char c : text) {
    const auto u = static_cast<unsigned char>(c);
    if (c == '\\' || u < 0x20 || u == 0x7f) return false;
  }
  return true;
}

// CS: upper-case letters, digits, space and underscore (PS3.5 table 6.2-1).
bool IsCodeString(std::string_view text) {
  for (const char c : text) {
    if (!(absl::ascii_isupper(c) || absl::ascii_isdigit(c) || c == ' ' ||
          c == '_')) {
      return false;
    }
  }
  return true;
}

// The source's units for a label: HU for CT, else what its first file
// says its modality values are, whole (RescaleType is an LO of up to 64
// characters, e.g. "SIGNAL INTENSITY (UNITLESS)"; PET's Units a CS), else
// "units".
absl::StatusOr<std::string> SourceUnits(const DicomSeries& source) {
  if (source.modality == "CT") return std::string("HU");
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> file,
                              LoadSourceHeader(source));
  DcmDataset& header = *file->getDataset();
  for (const DcmTagKey& tag : {DCM_RescaleType, DCM_Units}) {
    OFString value;
    if (header.findAndGetOFString(tag, value).good()) {
      std::string units(absl::StripAsciiWhitespace(value.c_str()));
      // "US" is RescaleType's "unspecified" (PS3.3 C.11.1.1.2).
      // No length limit of its own: the label that holds it has one, which
      // DescribeThresholdSegment checks (a limit here replaced long units
      // with "units" without a word).
      if (!units.empty() && units != "US" && IsPlainText(units)) {
        return units;
      }
    }
  }
  return std::string("units");
}

bool IsBone(const CodedConcept& type) {
  return type.scheme == "SCT" && type.value == kBoneCodeValue;
}

// A segment that is not bone is shown as a fill shows its first label.
std::array<uint8_t, 3> RegionRgb() { return *DefaultLabelSegment(1).rgb; }

// SegmentLabel is an LO (PS3.5 table 6.2-1).
constexpr size_t kMaxSegmentLabelLength = 64;

std::string FormatThreshold(double value) {
  return absl::StrFormat("%g", value);
}

}  // namespace

absl::StatusOr<CodedConcept> ParseCodedConcept(std::string_view text) {
  const std::vector<std::string> parts = absl::StrSplit(
      absl::string_view(text.data(), text.size()), absl::MaxSplits(':', 2));
  if (parts.size() != 3) {
    return absl::InvalidArgumentError(
        "expected scheme:value:meaning, e.g. SCT:272673000:Bone");
  }
  CodedConcept code{parts[1], parts[0], parts[2]};
  if (code.scheme.empty() || code.scheme.size() > 16 ||
      !IsCodeString(code.scheme)) {
    return absl::InvalidArgumentError(
        "the coding scheme must be 1-16 upper-case letters, digits, spaces "
        "or underscores (e.g. SCT, DCM, FMA)");
  }
  if (code.value.empty() || code.value.size() > 16 ||
      !IsPlainText(code.value)) {
    return absl::InvalidArgumentError(
        "the code value must be 1-16 characters without backslash or "
        "control characters");
  }
  if (code.meaning.empty() || code.meaning.size() > 64 ||
      !IsPlainText(code.meaning)) {
    return absl::InvalidArgumentError(
        "the code meaning must be 1-64 characters without backslash or "
        "control characters");
  }
  return code;
}

absl::Status ValidateSegmentLabel(std::string_view label) {
  if (label.empty() || label.size() > kMaxSegmentLabelLength ||
      !IsPlainText(label)) {
    return absl::InvalidArgumentError(
        "the segment label must be 1-64 characters without backslash or "
        "control characters");
  }
  return absl::OkStatus();
}

absl::StatusOr<SegmentDescription> DescribeThresholdSegment(
    const DicomSeries& source, double lower, std::optional<double> upper,
    std::string_view label, const std::optional<CodedConcept>& code) {
  if (!label.empty()) INTERSLICE_RETURN_IF_ERROR(ValidateSegmentLabel(label));
  const CodedConcept tissue = {kTissueCodeValue, "SCT", "Tissue"};
  const CodedConcept bone = {kBoneCodeValue, "SCT", "Bone"};
  const CodedConcept anatomical = {kAnatomicalStructureCodeValue, "SCT",
                                   "Anatomical Structure"};
  SegmentDescription segment;
  if (code.has_value()) {
    segment.type = *code;
    const bool is_tissue =
        code->scheme == "SCT" &&
        (code->value == kBoneCodeValue || code->value == kTissueCodeValue);
    segment.category = is_tissue ? tissue : anatomical;
    segment.label = label.empty() ? code->meaning : std::string(label);
    if (!IsBone(segment.type)) segment.rgb = RegionRgb();
    return segment;
  }
  if (source.modality == "CT" && lower >= kBoneThresholdHu) {
    segment.category = tissue;
    segment.type = bone;
    segment.label = "Bone";
  } else {
    INTERSLICE_ASSIGN_OR_RETURN(const std::string units, SourceUnits(source));
    segment.category = anatomical;
    segment.type = anatomical;
    segment.rgb = RegionRgb();
    segment.label =
        upper.has_value()
            ? absl::StrCat("Region ", FormatThreshold(lower), " to ",
                           FormatThreshold(*upper), " ", units)
            : absl::StrCat("Region above ", FormatThreshold(lower), " ", units);
    // The units are never cut or replaced: a label they make too long for
    // a SegmentLabel fails, saying how to name the segment instead.
    if (label.empty() && !ValidateSegmentLabel(segment.label).ok()) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "the segment label would be %d characters with the source's units "
          "(%d characters), more than the %d a SegmentLabel holds: name the "
          "segment (--segment-label; rules: segment_label; gRPC: "
          "segmentation.segment_label)",
          segment.label.size(), units.size(), kMaxSegmentLabelLength));
    }
  }
  if (!label.empty()) segment.label = std::string(label);
  return segment;
}

namespace dicom_out_internal {

absl::StatusOr<std::unique_ptr<DcmSegmentation>> CreateBinarySegmentation(
    const DicomSeries& source, const Grid& grid,
    const DerivedObjectIdentity& identity, const DicomWriteOptions& options) {
  const std::string& series_uid = identity.series_instance_uid;
  const std::string& sop_uid = identity.sop_instance_uids.front();
  const std::string& dimension_uid = identity.dimension_organization_uid;
  // The segmentation's creator is interslice (Enhanced General Equipment
  // needs all four values; a software tool has no serial number).
  const IODGeneralEquipmentModule::EquipmentInfo equipment(
      "interslice", "interslice", "0", options.software_version.c_str());
  const std::string description = identity.series_description.substr(0, 64);
  ContentIdentificationMacro content("1", "INTERSLICE",
                                     description.substr(0, 64).c_str(), "");
  DcmSegmentation* raw = nullptr;
  INTERSLICE_RETURN_IF_ERROR(
      Check(DcmSegmentation::createBinarySegmentation(
                raw, static_cast<Uint16>(grid.size[1]),
                static_cast<Uint16>(grid.size[0]), equipment, content),
            "create the segmentation"));
  std::unique_ptr<DcmSegmentation> seg(raw);

  // Identity. Patient/study data are copied into the written dataset by
  // SaveSegmentation;
  // the type 1 UIDs are set here because dcmseg checks them while writing.
  INTERSLICE_RETURN_IF_ERROR(Check(
      seg->getStudy().setStudyInstanceUID((identity.study_instance_uid.empty()
                                               ? source.study_instance_uid
                                               : identity.study_instance_uid)
                                              .c_str()),
      "set StudyInstanceUID"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(seg->getFrameOfReference().setFrameOfReferenceUID(
                (identity.frame_of_reference_uid.empty()
                     ? source.frame_of_reference_uid
                     : identity.frame_of_reference_uid)
                    .c_str()),
            "set FrameOfReferenceUID"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(seg->getSeries().setSeriesInstanceUID(series_uid.c_str()),
            "set SeriesInstanceUID"));
  // SeriesNumber is type 1 in the Segmentation Series module.
  seg->getSeries().setSeriesNumber(
      std::to_string(identity.series_number).c_str());
  seg->getSeries().setSeriesDescription(description.c_str());
  seg->getSeries().setSeriesDate(CurrentDate().c_str());
  seg->getSeries().setSeriesTime(CurrentTime().c_str());
  INTERSLICE_RETURN_IF_ERROR(
      Check(seg->getSOPCommon().setSOPInstanceUID(sop_uid.c_str()),
            "set SOPInstanceUID"));

  // Geometry shared by all frames.
  FGPixelMeasures measures;
  measures.setPixelSpacing(absl::StrCat(FormatDecimalString(grid.spacing[1]),
                                        "\\",
                                        FormatDecimalString(grid.spacing[0]))
                               .c_str());
  measures.setSliceThickness(FormatDecimalString(grid.spacing[2]).c_str());
  measures.setSpacingBetweenSlices(
      FormatDecimalString(grid.spacing[2]).c_str());
  INTERSLICE_RETURN_IF_ERROR(
      Check(seg->addForAllFrames(measures), "add pixel measures"));
  const Vec3 row = grid.Axis(0), col = grid.Axis(1);
  std::unique_ptr<FGPlaneOrientationPatient> orientation(
      FGPlaneOrientationPatient::createMinimal(
          FormatDecimalString(row[0]).c_str(),
          FormatDecimalString(row[1]).c_str(),
          FormatDecimalString(row[2]).c_str(),
          FormatDecimalString(col[0]).c_str(),
          FormatDecimalString(col[1]).c_str(),
          FormatDecimalString(col[2]).c_str()));
  if (orientation == nullptr) {
    return absl::InternalError("DICOM SEG: cannot create plane orientation");
  }
  INTERSLICE_RETURN_IF_ERROR(
      Check(seg->addForAllFrames(*orientation), "add plane orientation"));

  // Dimensions: which segment, then where along the normal (the index of
  // ImagePositionPatient), as DICOM PS3.3 C.8.20.2.3 recommends for SEG.
  IODMultiframeDimensionModule& dims = seg->getDimensions();
  INTERSLICE_RETURN_IF_ERROR(Check(
      dims.addDimensionIndex(DCM_ReferencedSegmentNumber, dimension_uid.c_str(),
                             DCM_SegmentIdentificationSequence,
                             "ReferencedSegmentNumber"),
      "add the segment dimension"));
  INTERSLICE_RETURN_IF_ERROR(Check(
      dims.addDimensionIndex(DCM_ImagePositionPatient, dimension_uid.c_str(),
                             DCM_PlanePositionSequence, "ImagePositionPatient"),
      "add the position dimension"));

  return seg;
}

absl::Status AddSegmentationFrame(DcmSegmentation& seg, const Grid& grid,
                                  int64_t k, uint16_t segment_number,
                                  const DerivedObjectIdentity& referenced,
                                  const std::string& derivation_description,
                                  const uint8_t* frame) {
  const Vec3 p = grid.IndexToPhysical({0, 0, static_cast<double>(k)});
  std::unique_ptr<FGPlanePosPatient> position(FGPlanePosPatient::createMinimal(
      FormatDecimalString(p[0]).c_str(), FormatDecimalString(p[1]).c_str(),
      FormatDecimalString(p[2]).c_str()));
  if (position == nullptr) {
    return absl::InternalError("DICOM SEG: cannot create plane position");
  }
  FGFrameContent frame_content;
  frame_content.setDimensionIndexValues(segment_number, 0);
  frame_content.setDimensionIndexValues(static_cast<Uint32>(k + 1), 1);

  // Frame k lies on image k of the referenced series: that image is what it
  // was derived from and what a viewer overlays it on.
  // (of the enhanced layout's one instance: frame k + 1 of it).
  const SliceImageReference image = ReferenceSliceImage(referenced, k);
  OFVector<ImageSOPInstanceReferenceMacro> references(1);
  references[0].setReferencedSOPClassUID(referenced.sop_class_uid.c_str());
  references[0].setReferencedSOPInstanceUID(image.sop_instance_uid.c_str());
  if (image.frame_number > 0) {
    INTERSLICE_RETURN_IF_ERROR(
        Check(references[0].addReferencedFrameNumber(
                  static_cast<Uint16>(image.frame_number)),
              "reference the frame of the enhanced intensity image"));
  }
  std::unique_ptr<FGDerivationImage> derivation(
      DcmSegmentation::createDerivationImageFG(
          references, derivation_description.substr(0, 1024).c_str()));
  if (derivation == nullptr) {
    return absl::InternalError("DICOM SEG: cannot create derivation image");
  }

  OFVector<FGBase*> per_frame;
  per_frame.push_back(position.get());
  per_frame.push_back(&frame_content);
  per_frame.push_back(derivation.get());
  // addFrame packs the bytes into its own bit-packed copy; it takes a
  // non-const pointer only by its signature.
  return Check(
      seg.addFrame(const_cast<Uint8*>(frame), segment_number, per_frame),
      absl::StrCat("add the frame of segment ", segment_number, " on slice ", k)
          .c_str());
}

absl::Status SaveSegmentation(DcmSegmentation& seg, DcmItem& source_header,
                              const DerivedObjectIdentity& identity,
                              const DerivedObjectIdentity& referenced,
                              const std::string& path) {
  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  INTERSLICE_RETURN_IF_ERROR(Check(seg.writeDataset(ds), "encode"));
  CopyPatientStudyFrameOfReference(source_header, identity, ds);
  AddReferencedImageSeries(referenced, ds);
  return SaveFileAtomically(file, path);
}

}  // namespace dicom_out_internal

absl::Status WriteSegmentation(const DicomSeries& source,
                               const Volume<uint8_t>& mask,
                               const DerivedObjectIdentity& identity,
                               const DerivedObjectIdentity& referenced,
                               const SegmentDescription& segment,
                               const DicomWriteOptions& options,
                               const std::string& path) {
  const Grid& grid = mask.grid;
  INTERSLICE_RETURN_IF_ERROR(
      ValidateOutputGrid(source, grid, mask.data.size(), "segmentation mask"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckReferencedSeries(identity, referenced, grid, "segmentation"));
  if (segment.label.empty()) {
    return absl::InvalidArgumentError("segment label is empty");
  }
  INTERSLICE_RETURN_IF_ERROR(ValidateCode(segment.category, "category"));
  INTERSLICE_RETURN_IF_ERROR(ValidateCode(segment.type, "type"));
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& src = *source_file->getDataset();

  INTERSLICE_ASSIGN_OR_RETURN(
      std::unique_ptr<DcmSegmentation> seg,
      CreateBinarySegmentation(source, grid, identity, options));

  // The one segment.
  DcmSegment* raw_segment = nullptr;
  INTERSLICE_RETURN_IF_ERROR(Check(
      DcmSegment::create(raw_segment, segment.label.c_str(),
                         CodeSequenceMacro(segment.category.value.c_str(),
                                           segment.category.scheme.c_str(),
                                           segment.category.meaning.c_str()),
                         CodeSequenceMacro(segment.type.value.c_str(),
                                           segment.type.scheme.c_str(),
                                           segment.type.meaning.c_str()),
                         DcmSegTypes::SAT_AUTOMATIC,
                         segment.algorithm_name.c_str()),
      "create the segment"));
  // The colour a viewer shows it in; OHIF warns without one.
  const std::array<uint16_t, 3> lab = RgbToDicomCieLab(segment.rgb);
  if (const OFCondition cond =
          raw_segment->setRecommendedDisplayCIELabValue(lab[0], lab[1], lab[2]);
      cond.bad()) {
    delete raw_segment;  // not the segmentation's yet
    return Check(cond, "set the segment's colour");
  }
  Uint16 segment_number = 0;
  {
    const OFCondition cond = seg->addSegment(raw_segment, segment_number);
    if (cond.bad()) delete raw_segment;  // ownership passes only on success
    INTERSLICE_RETURN_IF_ERROR(Check(cond, "add the segment"));
  }

  const int64_t nx = grid.size[0], ny = grid.size[1], nz = grid.size[2];
  std::vector<Uint8> frame(static_cast<size_t>(nx * ny));
  for (int64_t k = 0; k < nz; ++k) {
    const uint8_t* slice = &mask.data[static_cast<size_t>(nx * ny * k)];
    for (size_t i = 0; i < frame.size(); ++i) frame[i] = slice[i] != 0;
    INTERSLICE_RETURN_IF_ERROR(
        AddSegmentationFrame(*seg, grid, k, segment_number, referenced,
                             options.derivation_description, frame.data()));
  }
  return SaveSegmentation(*seg, src, identity, referenced, path);
}

}  // namespace interslice
