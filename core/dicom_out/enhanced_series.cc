// WriteEnhancedIntensity: the intensity volume as one Enhanced CT Image
// instance (DCMTK dcmect + dcmfg).
#include "core/dicom_out/enhanced_series.h"

#include <algorithm>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/ascii.h"
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
#include "dcmtk/dcmect/enhanced_ct.h"
#include "dcmtk/dcmfg/fgctimageframetype.h"
#include "dcmtk/dcmfg/fgderimg.h"
#include "dcmtk/dcmfg/fgfracon.h"
#include "dcmtk/dcmfg/fgframeanatomy.h"
#include "dcmtk/dcmfg/fgframevoilut.h"
#include "dcmtk/dcmfg/fgirradiationeventid.h"
#include "dcmtk/dcmfg/fgpixeltransform.h"
#include "dcmtk/dcmfg/fgpixmsr.h"
#include "dcmtk/dcmfg/fgplanor.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmiod/iodmacro.h"

namespace interslice {
namespace {

using dicom_out_internal::AddReferencedSeries;
using dicom_out_internal::ChooseEncoding;
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
using dicom_out_internal::SaveFileAtomically;
using dicom_out_internal::SlicePositionAlongNormal;
using dicom_out_internal::SourceWindows;
using dicom_out_internal::StoredPaddingValue;
using dicom_out_internal::ValidateOutputGrid;
using dicom_out_internal::Window;

absl::Status Check(const OFCondition& cond, const std::string& what) {
  if (cond.good()) return absl::OkStatus();
  return absl::InternalError(
      absl::StrCat("Enhanced CT: cannot ", what, ": ", cond.text()));
}

// Body Part Examined -> the SNOMED CT anatomic region of PS3.16 Annex L
// (CID 4031), for the Frame Anatomy functional group, whose Anatomic Region
// Sequence is type 1. Only the common CT terms; others fall back to
// "Entire body" (PS3.16 Annex L lists it for WHOLEBODY), which is true of
// every region.
struct AnatomicRegion {
  const char* body_part;
  const char* code;
  const char* meaning;
};
constexpr AnatomicRegion kAnatomicRegions[] = {
    {"HEAD", "69536005", "Head"},
    {"BRAIN", "12738006", "Brain"},
    {"SKULL", "89546000", "Skull"},
    {"HEADNECK", "774007", "Head and Neck"},
    {"NECK", "45048000", "Neck"},
    {"CHEST", "51185008", "Thorax"},
    {"THORAX", "51185008", "Thorax"},
    {"ABDOMEN", "818981001", "Abdomen"},
    {"PELVIS", "816092008", "Pelvis"},
    {"CHESTABDOMEN", "416550000", "Chest and Abdomen"},
    {"ABDOMENPELVIS", "818982008", "Abdomen and Pelvis"},
    {"SPINE", "421060004", "Spine"},
    {"CSPINE", "122494005", "Cervical spine"},
    {"TSPINE", "122495006", "Thoracic spine"},
    {"LSPINE", "122496007", "Lumbar spine"},
    {"HEART", "80891009", "Heart"},
    {"KNEE", "72696002", "Knee"},
    {"ANKLE", "344001", "Ankle"},
    {"FOOT", "56459004", "Foot"},
    {"HAND", "85562004", "Hand"},
    {"WRIST", "74670003", "Wrist joint"},
    {"ELBOW", "127949000", "Elbow"},
    {"SHOULDER", "16982005", "Shoulder"},
    {"HIP", "29836001", "Hip"},
    {"WHOLEBODY", "38266002", "Entire body"},
};

AnatomicRegion RegionOf(DcmItem& source_header) {
  OFString body_part;
  source_header.findAndGetOFString(DCM_BodyPartExamined, body_part);
  std::string key = absl::AsciiStrToUpper(body_part.c_str());
  key.erase(std::remove(key.begin(), key.end(), ' '), key.end());
  for (const AnatomicRegion& region : kAnatomicRegions) {
    if (key == region.body_part) return region;
  }
  return kAnatomicRegions[std::size(kAnatomicRegions) - 1];
}

// The window strings (multi-valued DS / LO) of the source's windows.
struct WindowText {
  std::string centers, widths, explanations;
  bool any_explanation = false;
};

WindowText FormatWindows(const std::vector<Window>& windows) {
  WindowText text;
  for (size_t w = 0; w < windows.size(); ++w) {
    const char* separator = w == 0 ? "" : "\\";
    absl::StrAppend(&text.centers, separator,
                    FormatDecimalString(windows[w].center));
    absl::StrAppend(&text.widths, separator,
                    FormatDecimalString(windows[w].width));
    absl::StrAppend(&text.explanations, separator, windows[w].explanation);
    text.any_explanation |= !windows[w].explanation.empty();
  }
  return text;
}

// Source Image Evidence Sequence (Enhanced CT Image module, type 1C: the
// frames' Derivation Image items reference source images): the source
// instances, as a Hierarchical SOP Instance Reference (study, series,
// instances). Absent when the source cannot be referenced (anonymised).
void AddSourceImageEvidence(const DicomSeries& source, DcmItem& to) {
  if (source.series_instance_uid.empty() || source.sop_class_uid.empty() ||
      source.study_instance_uid.empty()) {
    return;
  }
  DcmItem* study = nullptr;
  DcmItem* series = nullptr;
  for (const DicomSliceInfo& slice : source.slices) {
    if (slice.sop_instance_uid.empty()) continue;
    if (study == nullptr) {
      to.findOrCreateSequenceItem(DCM_SourceImageEvidenceSequence, study, 0);
      study->putAndInsertString(DCM_StudyInstanceUID,
                                source.study_instance_uid.c_str());
      study->findOrCreateSequenceItem(DCM_ReferencedSeriesSequence, series, 0);
      series->putAndInsertString(DCM_SeriesInstanceUID,
                                 source.series_instance_uid.c_str());
    }
    DcmItem* instance = nullptr;
    series->findOrCreateSequenceItem(DCM_ReferencedSOPSequence, instance,
                                     -2 /* append */);
    instance->putAndInsertString(DCM_ReferencedSOPClassUID,
                                 source.sop_class_uid.c_str());
    instance->putAndInsertString(DCM_ReferencedSOPInstanceUID,
                                 slice.sop_instance_uid.c_str());
  }
}

// The per-frame groups of output slice k.
struct FrameGroups {
  std::unique_ptr<FGPlanePosPatient> position;
  FGFrameContent content;
  FGDerivationImage derivation;
};

absl::StatusOr<std::unique_ptr<FrameGroups>> MakeFrameGroups(
    const DicomSeries& source, const Grid& grid, int64_t k,
    const DicomWriteOptions& options, const std::string& derivation_text) {
  auto groups = std::make_unique<FrameGroups>();
  const Vec3 p = grid.IndexToPhysical({0, 0, static_cast<double>(k)});
  groups->position.reset(FGPlanePosPatient::createMinimal(
      FormatDecimalString(p[0]).c_str(), FormatDecimalString(p[1]).c_str(),
      FormatDecimalString(p[2]).c_str()));
  if (groups->position == nullptr) {
    return absl::InternalError("Enhanced CT: cannot create a plane position");
  }
  // One stack, frames in order along the normal (PS3.3 C.7.6.16.2.2.4).
  INTERSLICE_RETURN_IF_ERROR(
      Check(groups->content.setStackID("1"), "set the stack ID"));
  INTERSLICE_RETURN_IF_ERROR(Check(
      groups->content.setInStackPositionNumber(static_cast<Uint32>(k + 1)),
      "set the in-stack position"));
  INTERSLICE_RETURN_IF_ERROR(Check(
      groups->content.setDimensionIndexValues(static_cast<Uint32>(k + 1), 0),
      "set the dimension index"));

  // Derivation: the source slices this frame's values come from, as the
  // classic layout's SourceImageSequence (the morph's value tangents also
  // use the outer neighbours).
  const double position = SlicePositionAlongNormal(grid, k);
  std::vector<int64_t> slices = NearestSourceSlices(source, position);
  if (slices.size() == 2 &&
      options.intensity_interpolation ==
          DicomWriteOptions::IntensityInterpolation::kMorph) {
    if (slices[0] > 0) slices.push_back(slices[0] - 1);
    if (slices[1] + 1 < static_cast<int64_t>(source.slices.size()))
      slices.push_back(slices[1] + 1);
  }
  std::vector<int64_t> referable;
  for (int64_t s : slices) {
    // An anonymised source slice without a SOP Instance UID cannot be
    // referenced.
    if (!source.slices[s].sop_instance_uid.empty() &&
        !source.sop_class_uid.empty()) {
      referable.push_back(s);
    }
  }
  if (!referable.empty()) {
    DerivationImageItem* item = nullptr;
    INTERSLICE_RETURN_IF_ERROR(
        Check(groups->derivation.addDerivationImageItem(
                  CodeSequenceMacro("113085", "DCM", "Spatial resampling"),
                  derivation_text.c_str(), item),
              "add the derivation image"));
    for (int64_t s : referable) {
      SourceImageItem* source_item = new SourceImageItem();
      source_item->getPurposeOfReferenceCode().set(
          kSourceImagePurposeCode, "DCM", kSourceImagePurposeMeaning);
      INTERSLICE_RETURN_IF_ERROR(Check(
          source_item->getImageSOPInstanceReference().setReferencedSOPClassUID(
              source.sop_class_uid.c_str()),
          "reference a source image"));
      INTERSLICE_RETURN_IF_ERROR(
          Check(source_item->getImageSOPInstanceReference()
                    .setReferencedSOPInstanceUID(
                        source.slices[s].sop_instance_uid.c_str()),
                "reference a source image"));
      item->getSourceImageItems().push_back(source_item);
    }
  }
  return groups;
}

}  // namespace

absl::StatusOr<DerivedObjectIdentity> PlanEnhancedIntensity(
    const DicomSeries& source, const DerivedObjectIdentity& classic,
    const DicomWriteOptions& options) {
  if (source.modality != "CT") {
    return absl::FailedPreconditionError(absl::StrCat(
        "the enhanced DICOM layout is written for CT sources only (Enhanced "
        "CT Image); this series' modality is '",
        source.modality,
        "': use the classic layout (Enhanced MR is not implemented)"));
  }
  if (classic.series_instance_uid.empty()) {
    return absl::InvalidArgumentError(
        "enhanced intensity: the classic intensity identity has no series "
        "UID");
  }
  DerivedObjectIdentity enhanced = classic;
  const std::string base =
      absl::StrCat("enhanced-intensity/", classic.series_instance_uid);
  INTERSLICE_ASSIGN_OR_RETURN(
      enhanced.series_instance_uid,
      DeriveDicomUid(options.uid_root, absl::StrCat(base, "/series")));
  INTERSLICE_ASSIGN_OR_RETURN(
      std::string instance,
      DeriveDicomUid(options.uid_root, absl::StrCat(base, "/instance")));
  enhanced.sop_instance_uids = {std::move(instance)};
  INTERSLICE_ASSIGN_OR_RETURN(
      enhanced.dimension_organization_uid,
      DeriveDicomUid(options.uid_root, absl::StrCat(base, "/dimensions")));
  enhanced.sop_class_uid = UID_EnhancedCTImageStorage;
  return enhanced;
}

absl::Status WriteEnhancedIntensity(const DicomSeries& source,
                                    const Volume<float>& values,
                                    const DerivedObjectIdentity& identity,
                                    const DicomWriteOptions& options,
                                    const std::string& path) {
  const Grid& grid = values.grid;
  INTERSLICE_RETURN_IF_ERROR(ValidateOutputGrid(
      source, grid, values.data.size(), "enhanced intensity"));
  if (identity.sop_class_uid != UID_EnhancedCTImageStorage ||
      identity.sop_instance_uids.size() != 1 ||
      identity.sop_instance_uids.front().empty() ||
      identity.series_instance_uid.empty() ||
      identity.dimension_organization_uid.empty()) {
    return absl::InvalidArgumentError(
        "enhanced intensity: the identity must name one Enhanced CT instance "
        "with series and dimension organization UIDs "
        "(PlanEnhancedIntensity)");
  }
  const int64_t nx = grid.size[0], ny = grid.size[1], nz = grid.size[2];
  // Pixel Data is one element: its length must fit 32 bits (even, below the
  // undefined-length marker).
  const uint64_t pixel_bytes = static_cast<uint64_t>(nx) *
                               static_cast<uint64_t>(ny) *
                               static_cast<uint64_t>(nz) * 2;
  if (pixel_bytes >= 0xFFFFFFFEull) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "enhanced intensity: %d frames of %d x %d pixels hold %d bytes, more "
        "than one DICOM Pixel Data element can (4 GiB); use the classic "
        "layout",
        nz, nx, ny, pixel_bytes));
  }
  if (nz > std::numeric_limits<Uint16>::max()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "enhanced intensity: %d frames; a frame reference (US) can name at "
        "most 65535: use the classic layout",
        nz));
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
  const WindowText window_text = FormatWindows(windows);
  INTERSLICE_ASSIGN_OR_RETURN(const std::optional<float> padding,
                              SourcePixelPadding(source));
  const std::optional<double> stored_padding =
      StoredPaddingValue(encoding, padding);
  std::string derivation = options.derivation_description;
  if (!derivation.empty()) derivation += "; ";
  derivation += encoding.description;
  if (derivation.size() > 1024) derivation.resize(1024);  // ST limit

  // The Enhanced CT Image module: a derived volume of axial-stack frames,
  // resampled (PS3.3 C.8.15.2.1.1: value 4 RESAMPLED), monochrome, not a
  // projection (VolumeBasedCalculationTechnique NONE). Its creator is
  // interslice (Enhanced General Equipment needs all four values; software
  // has no serial number).
  const IODEnhGeneralEquipmentModule::EquipmentInfo equipment(
      "interslice", "interslice", "0", options.software_version.c_str());
  EctEnhancedCT* raw = nullptr;
  INTERSLICE_RETURN_IF_ERROR(Check(
      EctEnhancedCT::create(
          raw, static_cast<Uint16>(ny), static_cast<Uint16>(nx),
          encoding.is_signed ? OFTrue : OFFalse, EctTypes::E_ImageType1_Derived,
          EctTypes::DT_ImageType3_Volume, EctTypes::DT_ImageType4_Resampled,
          "1", EctTypes::E_ContQuali_Research, EctTypes::E_PixelPres_Monochrome,
          EctTypes::E_VolProps_Volume, EctTypes::DT_VolBasedCalcTechnique_None,
          equipment),
      "create the object"));
  std::unique_ptr<EctEnhancedCT> ct(raw);

  // Identity; patient and study are copied from the source after encoding.
  const std::string date = CurrentDate();
  const std::string time = CurrentTime();
  INTERSLICE_RETURN_IF_ERROR(Check(
      ct->getStudy().setStudyInstanceUID((identity.study_instance_uid.empty()
                                              ? source.study_instance_uid
                                              : identity.study_instance_uid)
                                             .c_str()),
      "set StudyInstanceUID"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->getFrameOfReference().setFrameOfReferenceUID(
                (identity.frame_of_reference_uid.empty()
                     ? source.frame_of_reference_uid
                     : identity.frame_of_reference_uid)
                    .c_str()),
            "set FrameOfReferenceUID"));
  INTERSLICE_RETURN_IF_ERROR(Check(ct->getSeries().setSeriesInstanceUID(
                                       identity.series_instance_uid.c_str()),
                                   "set SeriesInstanceUID"));
  ct->getSeries().setSeriesNumber(
      std::to_string(identity.series_number).c_str());
  ct->getSeries().setSeriesDescription(
      identity.series_description.substr(0, 64).c_str());
  ct->getSeries().setSeriesDate(date.c_str());
  ct->getSeries().setSeriesTime(time.c_str());
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->getSOPCommon().setSOPInstanceUID(
                identity.sop_instance_uids.front().c_str()),
            "set SOPInstanceUID"));
  ct->getIODMultiFrameFGModule().setContentDate(date.c_str());
  ct->getIODMultiFrameFGModule().setContentTime(time.c_str());

  // Shared functional groups.
  FGPixelMeasures measures;
  INTERSLICE_RETURN_IF_ERROR(
      Check(measures.setPixelSpacing(
                absl::StrCat(FormatDecimalString(grid.spacing[1]), "\\",
                             FormatDecimalString(grid.spacing[0]))
                    .c_str()),
            "set the pixel spacing"));
  const std::string slice_spacing = FormatDecimalString(grid.spacing[2]);
  measures.setSliceThickness(slice_spacing.c_str());
  measures.setSpacingBetweenSlices(slice_spacing.c_str());
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->addForAllFrames(measures), "add pixel measures"));
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
    return absl::InternalError("Enhanced CT: cannot create plane orientation");
  }
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->addForAllFrames(*orientation), "add plane orientation"));

  FGCTImageFrameType frame_type;
  INTERSLICE_RETURN_IF_ERROR(
      Check(frame_type.setFrameType("DERIVED\\PRIMARY\\VOLUME\\RESAMPLED"),
            "set the frame type"));
  frame_type.setPixelPresentation(FGCTImageFrameType::E_PixelPres_Monochrome);
  frame_type.setVolumetricProperties(FGCTImageFrameType::E_VolProp_Volume);
  frame_type.setVolumeBasedCalculationTechnique(
      FGCTImageFrameType::DT_VolBasedCalcTechnique_None);
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->addForAllFrames(frame_type), "add the CT image frame type"));

  FGPixelValueTransformation transformation;
  transformation.setFGType(FGPixelValueTransformation::E_PixelValTrans_CT);
  INTERSLICE_RETURN_IF_ERROR(
      Check(transformation.setRescaleIntercept(
                FormatDecimalString(encoding.intercept).c_str()),
            "set the rescale intercept"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(transformation.setRescaleSlope(
                FormatDecimalString(encoding.slope).c_str()),
            "set the rescale slope"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(transformation.setRescaleType("HU"), "set the rescale type"));
  INTERSLICE_RETURN_IF_ERROR(Check(ct->addForAllFrames(transformation),
                                   "add the pixel value transformation"));

  FGFrameVOILUT voi;
  INTERSLICE_RETURN_IF_ERROR(
      Check(voi.setWindowCenter(window_text.centers.c_str()),
            "set the window centre"));
  INTERSLICE_RETURN_IF_ERROR(Check(
      voi.setWindowWidth(window_text.widths.c_str()), "set the window width"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->addForAllFrames(voi), "add the frame VOI LUT"));

  const AnatomicRegion region = RegionOf(src);
  FGFrameAnatomy anatomy;
  // Unpaired: the region is named as a whole, neither side (the source's
  // laterality, if any, is of the study, not of these frames).
  anatomy.setLaterality(FGFrameAnatomy::LATERALITY_UNPAIRED);
  INTERSLICE_RETURN_IF_ERROR(Check(anatomy.getAnatomy().getAnatomicRegion().set(
                                       region.code, "SCT", region.meaning),
                                   "set the anatomic region"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->addForAllFrames(anatomy), "add the frame anatomy"));

  // The irradiation event: the source's (the frames show what it
  // irradiated), else one derived for this object.
  OFString irradiation_event;
  if (src.findAndGetOFString(DCM_IrradiationEventUID, irradiation_event)
          .bad() ||
      irradiation_event.empty()) {
    INTERSLICE_ASSIGN_OR_RETURN(
        const std::string uid,
        DeriveDicomUid(
            options.uid_root,
            absl::StrCat("enhanced-intensity/", identity.series_instance_uid,
                         "/irradiation-event")));
    irradiation_event = uid.c_str();
  }
  FGIrradiationEventIdentification irradiation;
  INTERSLICE_RETURN_IF_ERROR(
      Check(irradiation.setIrradiationEventUID(irradiation_event),
            "set the irradiation event UID"));
  INTERSLICE_RETURN_IF_ERROR(
      Check(ct->addForAllFrames(irradiation), "add the irradiation event"));

  // One dimension: the position along the normal.
  IODMultiframeDimensionModule& dimensions = ct->getDimensions();
  INTERSLICE_RETURN_IF_ERROR(Check(
      dimensions.addDimensionIndex(
          DCM_ImagePositionPatient, identity.dimension_organization_uid.c_str(),
          DCM_PlanePositionSequence, "ImagePositionPatient"),
      "add the position dimension"));
  dimensions.setDimensionOrganizationType("3D");

  // The frames: the classic layout's stored values, slice by slice.
  std::vector<Uint16> stored(static_cast<size_t>(nx * ny));
  EctEnhancedCT::FramesType frames = ct->getFrames();
  for (int64_t k = 0; k < nz; ++k) {
    INTERSLICE_ASSIGN_OR_RETURN(
        std::unique_ptr<FrameGroups> groups,
        MakeFrameGroups(source, grid, k, options, derivation));
    OFVector<FGBase*> per_frame;
    per_frame.push_back(groups->position.get());
    per_frame.push_back(&groups->content);
    if (!groups->derivation.getDerivationImageItems().empty()) {
      per_frame.push_back(&groups->derivation);
    }
    EncodeSlice(values, k, encoding, stored.data());
    OFCondition added;
    if (encoding.is_signed) {
      auto* typed = OFget<EctEnhancedCT::Frames<Sint16>>(&frames);
      if (typed == nullptr) {
        return absl::InternalError("Enhanced CT: no signed frame store");
      }
      added = typed->addFrame(reinterpret_cast<Sint16*>(stored.data()),
                              stored.size(), per_frame);
    } else {
      auto* typed = OFget<EctEnhancedCT::Frames<Uint16>>(&frames);
      if (typed == nullptr) {
        return absl::InternalError("Enhanced CT: no unsigned frame store");
      }
      added = typed->addFrame(stored.data(), stored.size(), per_frame);
    }
    INTERSLICE_RETURN_IF_ERROR(Check(added, absl::StrCat("add frame ", k + 1)));
  }
  if (static_cast<int64_t>(ct->getNumberOfFrames()) != nz) {
    return absl::InternalError(
        absl::StrFormat("Enhanced CT: %d of %d frames were added",
                        ct->getNumberOfFrames(), nz));
  }

  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  INTERSLICE_RETURN_IF_ERROR(Check(ct->writeDataset(ds), "encode"));
  CopyPatientStudyFrameOfReference(src, identity, ds);
  for (const DcmTagKey& tag : {DCM_PatientPosition, DCM_BodyPartExamined}) {
    DcmElement* element = nullptr;
    if (src.findAndGetElement(tag, element, OFFalse, OFTrue).good() &&
        element != nullptr) {
      if (element->getLength() > 0) {
        ds.insert(element, OFTrue);
      } else {
        delete element;
      }
    }
  }
  ds.putAndInsertString(DCM_InstanceCreationDate, date.c_str());
  ds.putAndInsertString(DCM_InstanceCreationTime, time.c_str());
  AddReferencedSeries(source, ds);
  AddSourceImageEvidence(source, ds);
  if (window_text.any_explanation) {
    DcmItem* shared = nullptr;
    DcmItem* voi_item = nullptr;
    if (ds.findAndGetSequenceItem(DCM_SharedFunctionalGroupsSequence, shared, 0)
            .good() &&
        shared->findAndGetSequenceItem(DCM_FrameVOILUTSequence, voi_item, 0)
            .good()) {
      voi_item->putAndInsertString(DCM_WindowCenterWidthExplanation,
                                   window_text.explanations.c_str());
    }
  }
  if (stored_padding.has_value()) {
    // The dictionary's VR is US or SS ("xs"): say which, as
    // PixelRepresentation does.
    if (encoding.is_signed) {
      auto* element = new DcmSignedShort(DcmTag(DCM_PixelPaddingValue, EVR_SS));
      element->putSint16(static_cast<Sint16>(*stored_padding));
      ds.insert(element, OFTrue);
    } else {
      auto* element =
          new DcmUnsignedShort(DcmTag(DCM_PixelPaddingValue, EVR_US));
      element->putUint16(static_cast<Uint16>(*stored_padding));
      ds.insert(element, OFTrue);
    }
  }
  return SaveFileAtomically(
      file, path,
      options.intensity_encoding ==
              DicomWriteOptions::PixelEncoding::kRleLossless
          ? EXS_RLELossless
          : EXS_LittleEndianExplicit);
}

}  // namespace interslice
