// WriteDistanceMap: the signed distance field as a DICOM Parametric Map
// (PS3.3 A.75) with 32-bit float pixels (DCMTK dcmpmap).
//
// Why a Parametric Map: it is the IOD made for real-valued maps on an image
// grid. Float Pixel Data stores each distance exactly (no rescale
// quantisation, unlike an integer image series), and the Real World Value
// Mapping says what the numbers are (a signed distance) and in which unit
// (UCUM "mm"), which an image series can only put into free text.
//
// Organisation (as for the SEG, see segmentation.cc): one frame per output
// slice in slice order; shared functional groups for what every frame has in
// common, per-frame ones for position, frame content and derivation; one
// dimension (ImagePositionPatient), so frame k + 1 is slice k and lies on
// image k of the intensity series, which it references.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
#include "core/dicom_out/dicom_writer.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcvrcs.h"
#include "dcmtk/dcmfg/fgderimg.h"
#include "dcmtk/dcmfg/fgfracon.h"
#include "dcmtk/dcmfg/fgframeanatomy.h"
#include "dcmtk/dcmfg/fgframevoilut.h"
#include "dcmtk/dcmfg/fgparametricmapframetype.h"
#include "dcmtk/dcmfg/fgpixeltransform.h"
#include "dcmtk/dcmfg/fgpixmsr.h"
#include "dcmtk/dcmfg/fgplanor.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmfg/fgrealworldvaluemapping.h"
#include "dcmtk/dcmiod/iodcontentitemmacro.h"
#include "dcmtk/dcmiod/iodmacro.h"
#include "dcmtk/dcmpmap/dpmparametricmapiod.h"

namespace interslice {
namespace {

using dicom_out_internal::AddReferencedImageSeries;
using dicom_out_internal::CheckReferencedSeries;
using dicom_out_internal::CopyPatientStudyFrameOfReference;
using dicom_out_internal::CurrentDate;
using dicom_out_internal::CurrentTime;
using dicom_out_internal::FormatDecimalString;
using dicom_out_internal::kSourceImagePurposeCode;
using dicom_out_internal::kSourceImagePurposeMeaning;
using dicom_out_internal::LoadSourceHeader;
using dicom_out_internal::SaveFileAtomically;
using dicom_out_internal::ValidateOutputGrid;

// ImageType values 3 and 4 (Image Flavor and Derived Pixel Contrast, in the
// Parametric Map Image module), also the Parametric Map Frame Type of every
// frame. VOLUME: the frames sample a volume; DISTANCE: the pixels are
// distances, not a contrast of the source (Derived Pixel Contrast has
// Defined Terms, which may be extended; none of them fits, so dciodvfy warns
// that DISTANCE is not among them).
constexpr char kImageFlavor[] = "VOLUME";
constexpr char kDerivedPixelContrast[] = "DISTANCE";

// Content Label (CS: upper case, digits, space, underscore; at most 16).
constexpr char kContentLabel[] = "SIGNED_DISTANCE";

// Real World Value Mapping (C.7.6.16.2.11): LUT Label (SH, at most 16
// characters) and LUT Explanation (LO, at most 64).
constexpr char kLutLabel[] = "signed distance";
constexpr char kLutExplanation[] =
    "Signed distance to the surface in mm, positive inside";

// Window for display: centred on the surface (0 mm) and as wide as the
// values present, but at most 20 mm, so that the few millimetres around the
// surface keep their contrast in a large map, and at least 1 mm (a nearly
// flat map).
constexpr double kMinWindowWidthMm = 1.0;
constexpr double kMaxWindowWidthMm = 20.0;

// DCMTK 3.6.7 keeps the number of frames in 16 bits when it reads a
// Parametric Map (and writes at most 65535 into NumberOfFrames).
constexpr int64_t kMaxFrames = 65535;
// Float Pixel Data (OF) has a 32-bit length field, 0xFFFFFFFF reserved.
constexpr uint64_t kMaxPixelDataBytes = 0xFFFFFFFEull;

absl::Status CheckParametricMap(const OFCondition& cond,
                                absl::string_view what) {
  return dicom_out_internal::CheckDcmtk(cond, "DICOM Parametric Map", what);
}

// Beyond CheckReferencedSeries: the SOP class, if given, is the Parametric
// Map's, and every referenced image has a UID (frame k names image k).
absl::Status ValidateIdentities(const DerivedObjectIdentity& identity,
                                const DerivedObjectIdentity& referenced) {
  if (!identity.sop_class_uid.empty() &&
      identity.sop_class_uid != UID_ParametricMapStorage) {
    return absl::InvalidArgumentError(absl::StrCat(
        "distance map SOP class must be Parametric Map Storage (",
        UID_ParametricMapStorage, "), not ", identity.sop_class_uid));
  }
  if (std::any_of(referenced.sop_instance_uids.begin(),
                  referenced.sop_instance_uids.end(),
                  [](const std::string& uid) { return uid.empty(); })) {
    return absl::InvalidArgumentError(
        "distance map: the referenced image series has an image without a "
        "SOP instance UID");
  }
  return absl::OkStatus();
}

struct ValueRange {
  float min = 0, max = 0;
};

// INVALID_ARGUMENT for NaN or infinity (the message names the voxel index,
// which is no patient data); otherwise the range of the values.
absl::StatusOr<ValueRange> FiniteRange(const Volume<float>& distance) {
  ValueRange range{std::numeric_limits<float>::max(),
                   std::numeric_limits<float>::lowest()};
  for (size_t i = 0; i < distance.data.size(); ++i) {
    const float v = distance.data[i];
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(
          absl::StrCat("distance map value ", i, " is not finite (", v, ")"));
    }
    range.min = std::min(range.min, v);
    range.max = std::max(range.max, v);
  }
  return range;
}

// Modality of the Parametric Map Series module: the source's, so that
// the map files under the same modality as the images it overlays; "OT" if
// the source has none (or a malformed one).
std::string MapModality(const DicomSeries& source) {
  if (!source.modality.empty() &&
      DcmCodeString::checkStringValue(source.modality.c_str(), "1").good()) {
    return source.modality;
  }
  return "OT";
}

std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  if (item.findAndGetOFString(tag, value).bad()) return "";
  return std::string(value.c_str());
}

// Frame Anatomy (C.7.6.16.2.8) is mandatory for a Parametric Map (Table
// A.75-2), but interslice knows no more about anatomy than the source says:
// the source's Anatomic Region Sequence if it has one, else its Body Part
// Examined mapped to SNOMED CT as in PS3.16 Annex L (for the common unpaired
// regions), else the region that contains every frame, "Entire body".
// Laterality: the source's, else U (unpaired).
absl::Status FillFrameAnatomy(DcmItem& src, FGFrameAnatomy& anatomy) {
  struct Region {
    const char* body_part;
    const char* code;
    const char* meaning;
  };
  static constexpr Region kRegions[] = {
      {"BRAIN", "12738006", "Brain"},
      {"HEAD", "69536005", "Head"},
      {"SKULL", "89546000", "Skull"},
      {"NECK", "45048000", "Neck"},
      {"CHEST", "51185008", "Chest"},
      {"HEART", "80891009", "Heart"},
      {"LIVER", "10200004", "Liver"},
      {"ABDOMEN", "818981001", "Abdomen"},
      {"PELVIS", "816092008", "Pelvis"},
      {"SPINE", "421060004", "Spine"},
      {"CSPINE", "122494005", "Cervical spine"},
      {"TSPINE", "122495006", "Thoracic spine"},
      {"LSPINE", "122496007", "Lumbar spine"},
      {"WHOLEBODY", "38266002", "Entire body"},
  };
  std::string code = "38266002", scheme = "SCT", meaning = "Entire body";
  DcmItem* region = nullptr;
  if (src.findAndGetSequenceItem(DCM_AnatomicRegionSequence, region, 0)
          .good() &&
      region != nullptr && !GetString(*region, DCM_CodeValue).empty() &&
      !GetString(*region, DCM_CodingSchemeDesignator).empty() &&
      !GetString(*region, DCM_CodeMeaning).empty()) {
    code = GetString(*region, DCM_CodeValue);
    scheme = GetString(*region, DCM_CodingSchemeDesignator);
    meaning = GetString(*region, DCM_CodeMeaning);
  } else {
    const std::string body_part = absl::AsciiStrToUpper(
        absl::StripAsciiWhitespace(GetString(src, DCM_BodyPartExamined)));
    for (const Region& r : kRegions) {
      if (body_part == r.body_part) {
        code = r.code;
        meaning = r.meaning;
        break;
      }
    }
  }
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      anatomy.getAnatomy().getAnatomicRegion().set(
          code.c_str(), scheme.c_str(), meaning.substr(0, 64).c_str()),
      "set the anatomic region"));

  FGFrameAnatomy::LATERALITY laterality = FGFrameAnatomy::LATERALITY_UNPAIRED;
  for (const DcmTagKey& tag :
       {DCM_FrameLaterality, DCM_ImageLaterality, DCM_Laterality}) {
    const std::string text(absl::StripAsciiWhitespace(GetString(src, tag)));
    const FGFrameAnatomy::LATERALITY value =
        FGFrameAnatomy::str2Laterality(text.c_str());
    if (FGFrameAnatomy::isLateralityValid(value)) {
      laterality = value;
      break;
    }
  }
  return CheckParametricMap(anatomy.setLaterality(laterality),
                            "set the laterality");
}

// Real World Value Mapping (C.7.6.16.2.11): stored value = distance in mm.
// For Float Pixel Data the mapped range is given as doubles (Double Float
// Real World Value First/Last Value Mapped): the US/SS Real World Value
// First/Last Value Mapped may only be used for float pixels when an integer
// of their size can define the range (C.7.6.16.2.11.1), which it cannot for
// fractional millimetres. Slope and intercept are required for float pixels.
absl::Status FillRealWorldValueMapping(const ValueRange& range,
                                       FGRealWorldValueMapping& rwvm) {
  auto owned = std::make_unique<FGRealWorldValueMapping::RWVMItem>();
  FGRealWorldValueMapping::RWVMItem& item = *owned;
  rwvm.getRealWorldValueMapping().push_back(owned.release());  // rwvm owns it
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      item.setDoubleFloatRealWorldValueFirstValueMapped(range.min),
      "set the first value mapped"));
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      item.setDoubleFloatRealWorldValueLastValueMapped(range.max),
      "set the last value mapped"));
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      item.setRealWorldValueIntercept(0.0), "set the intercept"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(item.setRealWorldValueSlope(1.0), "set the slope"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(item.setLUTLabel(kLutLabel), "set the LUT label"));
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      item.setLUTExplanation(kLutExplanation), "set the explanation"));
  // Units from CID 7181 (UCUM), as Table A.75-2 asks.
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      item.getMeasurementUnitsCode().set("mm", "UCUM", "millimeter"),
      "set the units"));
  // What the quantity is (Quantity Definition Sequence, CID 9000 / 7180):
  // (Quantity) = (Distance), so that a reader need not parse the label.
  auto quantity = std::make_unique<ContentItemMacro>();
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(quantity->setValueType(ContentItemMacro::VT_CODE),
                         "set the quantity value type"));
  quantity->getEntireConceptNameCodeSequence().push_back(
      new CodeSequenceMacro("246205007", "SCT", "Quantity"));
  quantity->getEntireConceptCodeSequence().push_back(
      new CodeSequenceMacro("121206", "DCM", "Distance"));
  item.getEntireQuantityDefinitionSequence().push_back(quantity.release());
  return absl::OkStatus();
}

}  // namespace

absl::Status WriteDistanceMap(const DicomSeries& source,
                              const Volume<float>& distance,
                              const DerivedObjectIdentity& identity,
                              const DerivedObjectIdentity& referenced,
                              const DicomWriteOptions& options,
                              const std::string& path) {
  const Grid& grid = distance.grid;
  INTERSLICE_RETURN_IF_ERROR(
      ValidateOutputGrid(source, grid, distance.data.size(), "distance map"));
  const int64_t nx = grid.size[0], ny = grid.size[1], nz = grid.size[2];
  if (nz > kMaxFrames) {
    return absl::InvalidArgumentError(
        absl::StrCat("distance map has ", nz, " slices; DCMTK reads at most ",
                     kMaxFrames, " frames of a Parametric Map"));
  }
  if (static_cast<uint64_t>(grid.VoxelCount()) * sizeof(Float32) >
      kMaxPixelDataBytes) {
    return absl::InvalidArgumentError(absl::StrCat(
        "distance map has ", grid.VoxelCount(),
        " voxels; Float Pixel Data holds less than 4 GiB (crop or coarsen)"));
  }
  // Series Number is type 1 in the Parametric Map Series module;
  // CheckReferencedSeries insists on it.
  INTERSLICE_RETURN_IF_ERROR(
      CheckReferencedSeries(identity, referenced, grid, "distance map"));
  INTERSLICE_RETURN_IF_ERROR(ValidateIdentities(identity, referenced));
  INTERSLICE_ASSIGN_OR_RETURN(const ValueRange range, FiniteRange(distance));
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& src = *source_file->getDataset();

  // The map's creator is interslice (Enhanced General Equipment needs all
  // four values; a software tool has no serial number).
  const IODEnhGeneralEquipmentModule::EquipmentInfo equipment(
      "interslice", "interslice", "0",
      options.software_version.empty() ? "interslice"
                                       : options.software_version.c_str());
  const ContentIdentificationMacro content(
      "1", kContentLabel, identity.series_description.substr(0, 64).c_str(),
      "");
  // Content Qualification RESEARCH: interslice is not a cleared medical
  // product.
  OFvariant<OFCondition, DPMParametricMapIOD> created =
      DPMParametricMapIOD::create<IODFloatingPointImagePixelModule>(
          MapModality(source).c_str(),
          std::to_string(identity.series_number).c_str(), "1",
          static_cast<Uint16>(ny), static_cast<Uint16>(nx), equipment, content,
          kImageFlavor, kDerivedPixelContrast, DPMTypes::CQ_RESEARCH);
  if (const OFCondition* cond = OFget<OFCondition>(&created)) {
    return CheckParametricMap(*cond, "create the map");
  }
  DPMParametricMapIOD& map = *OFget<DPMParametricMapIOD>(&created);
  // DCMTK's default is YES, which is right: the surface a distance map
  // describes can be rendered into a recognisable face.
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.setRecognizableVisualFeatures(DPMTypes::RVF_YES),
                         "set RecognizableVisualFeatures"));

  // Identity. Patient/study data are copied into the written dataset below;
  // the type 1 UIDs are set here too so that DCMTK does not invent them.
  const std::string& study = identity.study_instance_uid.empty()
                                 ? source.study_instance_uid
                                 : identity.study_instance_uid;
  const std::string& frame_of_reference =
      identity.frame_of_reference_uid.empty() ? source.frame_of_reference_uid
                                              : identity.frame_of_reference_uid;
  if (!study.empty()) {
    INTERSLICE_RETURN_IF_ERROR(
        CheckParametricMap(map.getStudy().setStudyInstanceUID(study.c_str()),
                           "set StudyInstanceUID"));
  }
  if (!frame_of_reference.empty()) {
    INTERSLICE_RETURN_IF_ERROR(
        CheckParametricMap(map.getFrameOfReference().setFrameOfReferenceUID(
                               frame_of_reference.c_str()),
                           "set FrameOfReferenceUID"));
  }
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.getSeries().setSeriesInstanceUID(
                             identity.series_instance_uid.c_str()),
                         "set SeriesInstanceUID"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.getSeries().setSeriesDescription(
                             identity.series_description.substr(0, 64).c_str()),
                         "set SeriesDescription"));
  map.getSeries().setSeriesDate(CurrentDate().c_str());
  map.getSeries().setSeriesTime(CurrentTime().c_str());
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.getSOPCommon().setSOPInstanceUID(
                             identity.sop_instance_uids[0].c_str()),
                         "set SOPInstanceUID"));

  // Shared functional groups (Table A.75-2).
  FGPixelMeasures measures;
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      measures.setPixelSpacing(
          absl::StrCat(FormatDecimalString(grid.spacing[1]), "\\",
                       FormatDecimalString(grid.spacing[0]))
              .c_str()),
      "set PixelSpacing"));
  measures.setSliceThickness(FormatDecimalString(grid.spacing[2]).c_str());
  measures.setSpacingBetweenSlices(
      FormatDecimalString(grid.spacing[2]).c_str());
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.addForAllFrames(measures), "add pixel measures"));

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
    return absl::InternalError(
        "DICOM Parametric Map: cannot create plane orientation");
  }
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      map.addForAllFrames(*orientation), "add plane orientation"));

  FGFrameAnatomy anatomy;
  INTERSLICE_RETURN_IF_ERROR(FillFrameAnatomy(src, anatomy));
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.addForAllFrames(anatomy), "add frame anatomy"));

  // Float pixels are the values themselves: the Identity Pixel Value
  // Transformation (slope 1, intercept 0) is mandatory (Table A.75-2); the
  // meaning and unit are in the Real World Value Mapping.
  FGPixelValueTransformation identity_transform;
  identity_transform.setUseAsIdentityPixelValueTransformation();
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.addForAllFrames(identity_transform),
                         "add the identity transformation"));

  FGRealWorldValueMapping rwvm;
  INTERSLICE_RETURN_IF_ERROR(FillRealWorldValueMapping(range, rwvm));
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      map.addForAllFrames(rwvm), "add real world value mapping"));

  const double max_abs = std::max(std::abs(static_cast<double>(range.min)),
                                  std::abs(static_cast<double>(range.max)));
  FGFrameVOILUT voi;
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      voi.setCenterWidthExplanation(
          0.0, std::clamp(2 * max_abs, kMinWindowWidthMm, kMaxWindowWidthMm),
          "SURFACE"),
      "set the window"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.addForAllFrames(voi), "add the window"));

  FGParametricMapFrameType frame_type;
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      frame_type.setFrameType(absl::StrCat("DERIVED\\PRIMARY\\", kImageFlavor,
                                           "\\", kDerivedPixelContrast)
                                  .c_str()),
      "set the frame type"));
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(map.addForAllFrames(frame_type),
                                                "add the frame type"));

  // One dimension: where along the normal (the index of
  // ImagePositionPatient), so frame k + 1 has index k + 1 (C.7.6.17).
  INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
      map.getIODMultiframeDimensionModule().addDimensionIndex(
          DCM_ImagePositionPatient, identity.dimension_organization_uid.c_str(),
          DCM_PlanePositionSequence, "ImagePositionPatient"),
      "add the position dimension"));

  DPMParametricMapIOD::FramesType frames_variant = map.getFrames();
  auto* frames = OFget<DPMParametricMapIOD::Frames<Float32>>(&frames_variant);
  if (frames == nullptr) {
    return absl::InternalError(
        "DICOM Parametric Map: no 32-bit float frame access");
  }
  const CodeSequenceMacro derivation_code("113076", "DCM", "Segmentation");
  const CodeSequenceMacro purpose(kSourceImagePurposeCode, "DCM",
                                  kSourceImagePurposeMeaning);
  const std::string derivation_description =
      absl::StrCat(options.derivation_description,
                   "; signed distance to the surface (mm, positive inside)")
          .substr(0, 1024);
  const size_t frame_pixels = static_cast<size_t>(nx * ny);
  std::vector<Float32> frame(frame_pixels);
  for (int64_t k = 0; k < nz; ++k) {
    // addFrame copies from a non-const pointer; the copy keeps the input
    // const.
    const float* slice = &distance.data[frame_pixels * static_cast<size_t>(k)];
    std::copy(slice, slice + frame_pixels, frame.begin());

    const Vec3 p = grid.IndexToPhysical({0, 0, static_cast<double>(k)});
    std::unique_ptr<FGPlanePosPatient> position(
        FGPlanePosPatient::createMinimal(FormatDecimalString(p[0]).c_str(),
                                         FormatDecimalString(p[1]).c_str(),
                                         FormatDecimalString(p[2]).c_str()));
    if (position == nullptr) {
      return absl::InternalError(
          "DICOM Parametric Map: cannot create plane position");
    }
    FGFrameContent frame_content;
    INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
        frame_content.setDimensionIndexValues(static_cast<Uint32>(k + 1), 0),
        "set the dimension index"));

    ImageSOPInstanceReferenceMacro reference;
    INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
        reference.setReferencedSOPClassUID(referenced.sop_class_uid.c_str()),
        "set the referenced SOP class"));
    // Image k of a classic series, or frame k + 1 of the enhanced instance.
    const dicom_out_internal::SliceImageReference image =
        dicom_out_internal::ReferenceSliceImage(referenced, k);
    INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
        reference.setReferencedSOPInstanceUID(image.sop_instance_uid.c_str()),
        "set the referenced SOP instance"));
    if (image.frame_number > 0) {
      INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
          reference.addReferencedFrameNumber(
              static_cast<Uint16>(image.frame_number)),
          "reference the frame of the enhanced intensity image"));
    }
    OFVector<ImageSOPInstanceReferenceMacro> references;
    references.push_back(reference);
    std::unique_ptr<FGDerivationImage> derivation(
        FGDerivationImage::createMinimal(references,
                                         derivation_description.c_str(),
                                         derivation_code, purpose));
    if (derivation == nullptr) {
      return absl::InternalError(
          "DICOM Parametric Map: cannot create derivation image");
    }

    OFVector<FGBase*> per_frame;
    per_frame.push_back(position.get());
    per_frame.push_back(&frame_content);
    per_frame.push_back(derivation.get());
    INTERSLICE_RETURN_IF_ERROR(CheckParametricMap(
        frames->addFrame(frame.data(), frame_pixels, per_frame),
        "add a frame"));
  }
  // addFrame does nothing (and reports success) for an empty frame or group
  // list; make sure every slice became a frame.
  if (map.getNumberOfFrames() != static_cast<size_t>(nz)) {
    return absl::InternalError(
        absl::StrCat("DICOM Parametric Map: ", map.getNumberOfFrames(),
                     " frames for ", nz, " slices"));
  }

  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  INTERSLICE_RETURN_IF_ERROR(
      CheckParametricMap(map.writeDataset(ds), "encode"));
  // writeDataset copied every frame into the dataset's Float Pixel Data; the
  // map's own frames (one output volume) are not needed for saving, which
  // with the fsync is the longest part. Destroying the map here keeps one
  // copy, not two, alive while the file is written. `map` and `frames` refer
  // into `created` and are not used after this.
  created = OFCondition(EC_Normal);
  CopyPatientStudyFrameOfReference(src, identity, ds);
  // Common Instance Reference module (C.12.2): every image of the intensity
  // series the frames derive from.
  AddReferencedImageSeries(referenced, ds);
  return SaveFileAtomically(file, path);
}

}  // namespace interslice
