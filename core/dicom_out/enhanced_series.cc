// WriteEnhancedIntensity: the intensity volume as one Enhanced CT Image or
// Enhanced MR Image instance (DCMTK dcmect + dcmfg).
//
// Both IODs have the same modules but their modality-specific image module
// and series module (PS3.3 A.38.1 and A.36.2), and the same functional
// groups but the image frame type (CT Image Frame Type, C.8.15.3.1; MR Image
// Frame Type, C.8.13.5.1) and, for CT, Irradiation Event Identification.
// DCMTK 3.6.7 has a class for Enhanced CT (EctEnhancedCT) but none for
// Enhanced MR, so both are built with EctEnhancedCT as the container of the
// shared dcmiod modules, the dcmfg functional groups and the frames; for MR
// the encoded dataset then gets the SOP class, the Enhanced MR Image
// module's attributes and the shared MR Image Frame Type group written here
// (ConvertToEnhancedMr), and never the CT-only groups.
#include "core/dicom_out/enhanced_series.h"

#include <algorithm>
#include <cstdint>
#include <initializer_list>
#include <limits>
#include <memory>
#include <optional>
#include <set>
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

// The enhanced IOD written for a source, by its modality.
enum class EnhancedIod { kCt, kMr };

const char* IodName(EnhancedIod iod) {
  return iod == EnhancedIod::kCt ? "Enhanced CT" : "Enhanced MR";
}

// kCt for "CT", kMr for "MR"; nullopt for every other modality.
std::optional<EnhancedIod> IodForModality(const std::string& modality) {
  if (modality == "CT") return EnhancedIod::kCt;
  if (modality == "MR") return EnhancedIod::kMr;
  return std::nullopt;
}

const char* SopClassOf(EnhancedIod iod) {
  return iod == EnhancedIod::kCt ? UID_EnhancedCTImageStorage
                                 : UID_EnhancedMRImageStorage;
}

absl::Status CheckEnhanced(const OFCondition& cond, absl::string_view what) {
  return dicom_out_internal::CheckDcmtk(cond, "enhanced intensity", what);
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
// instances), each instance once (the frames of a multi-frame source are
// slices of one instance). Absent when the source cannot be referenced
// (anonymised).
void AddSourceImageEvidence(const DicomSeries& source, DcmItem& to) {
  if (source.series_instance_uid.empty() || source.sop_class_uid.empty() ||
      source.study_instance_uid.empty()) {
    return;
  }
  DcmItem* study = nullptr;
  DcmItem* series = nullptr;
  std::set<std::string> listed;
  for (const DicomSliceInfo& slice : source.slices) {
    if (slice.sop_instance_uid.empty() ||
        !listed.insert(slice.sop_instance_uid).second) {
      continue;
    }
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

// True when source slice s is one frame of a multi-frame instance (not its
// only frame, or an instance other slices are frames of too), which a
// reference then names by frame number.
bool IsFrameOfMultiFrameInstance(const DicomSeries& source, int64_t s) {
  const DicomSliceInfo& slice = source.slices[static_cast<size_t>(s)];
  if (slice.frame > 0) return true;
  return std::count_if(source.slices.begin(), source.slices.end(),
                       [&slice](const DicomSliceInfo& other) {
                         return other.sop_instance_uid ==
                                slice.sop_instance_uid;
                       }) > 1;
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
    return absl::InternalError(
        "enhanced intensity: cannot create a plane position");
  }
  // One stack, frames in order along the normal (PS3.3 C.7.6.16.2.2.4).
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(groups->content.setStackID("1"), "set the stack ID"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      groups->content.setInStackPositionNumber(static_cast<Uint32>(k + 1)),
      "set the in-stack position"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
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
    INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
        groups->derivation.addDerivationImageItem(
            CodeSequenceMacro("113085", "DCM", "Spatial resampling"),
            derivation_text.c_str(), item),
        "add the derivation image"));
    for (int64_t s : referable) {
      SourceImageItem* source_item = new SourceImageItem();
      source_item->getPurposeOfReferenceCode().set(
          kSourceImagePurposeCode, "DCM", kSourceImagePurposeMeaning);
      INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
          source_item->getImageSOPInstanceReference().setReferencedSOPClassUID(
              source.sop_class_uid.c_str()),
          "reference a source image"));
      INTERSLICE_RETURN_IF_ERROR(
          CheckEnhanced(source_item->getImageSOPInstanceReference()
                            .setReferencedSOPInstanceUID(
                                source.slices[s].sop_instance_uid.c_str()),
                        "reference a source image"));
      if (IsFrameOfMultiFrameInstance(source, s)) {
        // A multi-frame source (an enhanced CT/MR): slice s is one frame of
        // its instance.
        INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
            source_item->getImageSOPInstanceReference()
                .addReferencedFrameNumber(
                    static_cast<Uint16>(source.slices[s].frame + 1)),
            "reference a source frame"));
      }
      item->getSourceImageItems().push_back(source_item);
    }
  }
  return groups;
}

// Image Type / Frame Type of every frame (PS3.3 C.8.16.1): derived, primary
// (it shows the anatomy, not a measure of it), a volume, resampled.
constexpr char kDerivedFrameType[] = "DERIVED\\PRIMARY\\VOLUME\\RESAMPLED";

// The MR Image Description macro (PS3.3 C.8.13.3) of the source: what its
// values are (ComplexImageComponent) and weighted by (AcquisitionContrast).
struct MrImageDescription {
  std::string complex_image_component;
  std::string acquisition_contrast;
  // MR Image and Spectroscopy Instance macro (C.8.13.2), type 1C; the
  // dciodvfy of Debian bookworm (2022) requires it of our DERIVED frames.
  std::string applicable_safety_standard_agency;
};

// The value of `tag` in the MR Image Frame Type of the source's frame
// `frame` (per frame, then shared), else at the top level of `src`; empty
// when absent or not one of `allowed` (the defined terms).
std::string SourceMrValue(DcmItem& src, int frame, const DcmTagKey& tag,
                          std::initializer_list<const char*> allowed) {
  std::vector<DcmItem*> places;
  DcmItem* group = nullptr;
  DcmItem* type = nullptr;
  if (src.findAndGetSequenceItem(DCM_PerFrameFunctionalGroupsSequence, group,
                                 frame)
          .good() &&
      group->findAndGetSequenceItem(DCM_MRImageFrameTypeSequence, type, 0)
          .good()) {
    places.push_back(type);
  }
  if (src.findAndGetSequenceItem(DCM_SharedFunctionalGroupsSequence, group, 0)
          .good() &&
      group->findAndGetSequenceItem(DCM_MRImageFrameTypeSequence, type, 0)
          .good()) {
    places.push_back(type);
  }
  places.push_back(&src);
  for (DcmItem* place : places) {
    OFString value;
    if (place->findAndGetOFString(tag, value).bad() || value.empty()) continue;
    for (const char* term : allowed) {
      if (value == term) return term;
    }
  }
  return "";
}

// The source's description, for frames that hold its values resampled: its
// complex component (an MR Image source has none: MAGNITUDE, what MR images
// show unless they say otherwise) and its contrast (UNKNOWN, a defined term
// of AcquisitionContrast, when it does not say).
MrImageDescription SourceMrDescription(DcmItem& src,
                                       const DicomSeries& source) {
  const int frame = source.slices.empty() ? 0 : source.slices.front().frame;
  MrImageDescription d;
  d.complex_image_component =
      SourceMrValue(src, frame, DCM_ComplexImageComponent,
                    {"MAGNITUDE", "PHASE", "REAL", "IMAGINARY"});
  if (d.complex_image_component.empty())
    d.complex_image_component = "MAGNITUDE";
  d.acquisition_contrast =
      SourceMrValue(src, frame, DCM_AcquisitionContrast,
                    {"DIFFUSION", "FLOW_ENCODED", "FLUID_ATTENUATED",
                     "PERFUSION", "PROTON_DENSITY", "STIR", "TAGGING", "T1",
                     "T2", "T2_STAR", "TOF", "UNKNOWN"});
  if (d.acquisition_contrast.empty()) d.acquisition_contrast = "UNKNOWN";
  // The agency whose MR safety standard the acquisition followed: the
  // source's, else IEC (IEC 60601-2-33, the international MR equipment
  // safety standard; an MR Image source does not say).
  d.applicable_safety_standard_agency = SourceMrValue(
      src, frame, DCM_ApplicableSafetyStandardAgency, {"IEC", "FDA", "MHW"});
  if (d.applicable_safety_standard_agency.empty()) {
    d.applicable_safety_standard_agency = "IEC";
  }
  return d;
}

// Writes the Common CT/MR (C.8.16.2) and MR (C.8.13.3) Image Description
// macros' values of our frames into `to`.
void PutMrImageDescription(const MrImageDescription& d, DcmItem& to) {
  to.putAndInsertString(DCM_PixelPresentation, "MONOCHROME");
  to.putAndInsertString(DCM_VolumetricProperties, "VOLUME");
  to.putAndInsertString(DCM_VolumeBasedCalculationTechnique, "NONE");
  to.putAndInsertString(DCM_ComplexImageComponent,
                        d.complex_image_component.c_str());
  to.putAndInsertString(DCM_AcquisitionContrast,
                        d.acquisition_contrast.c_str());
}

// Turns the encoded object into an Enhanced MR Image (PS3.3 A.36.2): its SOP
// class, the MR Series module's Modality, and the Enhanced MR Image module
// (C.8.13.1) in place of the Enhanced CT Image module: the same Image Type,
// Content Qualification and Common CT/MR Image Description macro (written
// by EctEnhancedCT), plus the MR Image Description macro. The MR Pulse
// Sequence module and the MR acquisition groups (Timing, FOV/Geometry,
// Echo, ...), like ResonantNucleus, MagneticFieldStrength and
// KSpaceFiltering, are required only for ORIGINAL or MIXED frames: ours are
// DERIVED.
// The shared MR Image Frame Type functional group (C.8.13.5.1) is written
// into the dataset here: dcmfg has no class for it, and its FGUnknown
// crashes when copied (FGUnknown::clone, DCMTK 3.6.7), which
// addForAllFrames does.
absl::Status ConvertToEnhancedMr(const MrImageDescription& d, DcmItem& ds) {
  DcmItem* shared = nullptr;
  DcmItem* type = nullptr;
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      ds.findAndGetSequenceItem(DCM_SharedFunctionalGroupsSequence, shared, 0),
      "find the shared functional groups"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      shared->findOrCreateSequenceItem(DCM_MRImageFrameTypeSequence, type, 0),
      "create the MR image frame type"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(type->putAndInsertString(DCM_FrameType, kDerivedFrameType),
                    "set the frame type"));
  PutMrImageDescription(d, *type);
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      ds.putAndInsertString(DCM_ApplicableSafetyStandardAgency,
                            d.applicable_safety_standard_agency.c_str()),
      "set the applicable safety standard agency"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      ds.putAndInsertString(DCM_SOPClassUID, UID_EnhancedMRImageStorage),
      "set the SOP class"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      ds.putAndInsertString(DCM_Modality, "MR"), "set the modality"));
  PutMrImageDescription(d, ds);
  return absl::OkStatus();
}

// The CT-only shared functional groups (PS3.3 A.38.1.4): CT Image Frame
// Type (C.8.15.3.1) and Irradiation Event Identification (C.7.6.16.2.27).
absl::Status AddCtFunctionalGroups(DcmItem& src,
                                   const DerivedObjectIdentity& identity,
                                   const DicomWriteOptions& options,
                                   EctEnhancedCT& ct) {
  FGCTImageFrameType frame_type;
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      frame_type.setFrameType(kDerivedFrameType), "set the frame type"));
  frame_type.setPixelPresentation(FGCTImageFrameType::E_PixelPres_Monochrome);
  frame_type.setVolumetricProperties(FGCTImageFrameType::E_VolProp_Volume);
  frame_type.setVolumeBasedCalculationTechnique(
      FGCTImageFrameType::DT_VolBasedCalcTechnique_None);
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(ct.addForAllFrames(frame_type),
                                           "add the CT image frame type"));

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
      CheckEnhanced(irradiation.setIrradiationEventUID(irradiation_event),
                    "set the irradiation event UID"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(ct.addForAllFrames(irradiation),
                                           "add the irradiation event"));

  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<DerivedObjectIdentity> PlanEnhancedIntensity(
    const DicomSeries& source, const DerivedObjectIdentity& classic,
    const DicomWriteOptions& options) {
  const std::optional<EnhancedIod> iod = IodForModality(source.modality);
  if (!iod.has_value()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the enhanced DICOM layout is written for CT and MR sources (Enhanced "
        "CT Image, Enhanced MR Image); this series' modality is '",
        source.modality, "': use the classic layout"));
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
  enhanced.sop_class_uid = SopClassOf(*iod);
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
  const std::optional<EnhancedIod> iod = IodForModality(source.modality);
  if (!iod.has_value()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "enhanced intensity: written for CT and MR sources; this series' "
        "modality is '",
        source.modality, "'"));
  }
  const char* sop_class = SopClassOf(*iod);
  if (identity.sop_class_uid != sop_class ||
      identity.sop_instance_uids.size() != 1 ||
      identity.sop_instance_uids.front().empty() ||
      identity.series_instance_uid.empty() ||
      identity.dimension_organization_uid.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "enhanced intensity: the identity must name one ", IodName(*iod),
        " instance with series and dimension organization UIDs "
        "(PlanEnhancedIntensity)"));
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

  const MrImageDescription mr_description = SourceMrDescription(src, source);

  // The Enhanced CT Image module (for MR, ConvertToEnhancedMr makes it the
  // Enhanced MR Image module): a derived volume of axial-stack frames,
  // resampled (PS3.3 C.8.15.2.1.1: value 4 RESAMPLED), monochrome, not a
  // projection (VolumeBasedCalculationTechnique NONE). Its creator is
  // interslice (Enhanced General Equipment needs all four values; software
  // has no serial number).
  const IODEnhGeneralEquipmentModule::EquipmentInfo equipment(
      "interslice", "interslice", "0", options.software_version.c_str());
  EctEnhancedCT* raw = nullptr;
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      EctEnhancedCT::create(
          raw, static_cast<Uint16>(ny), static_cast<Uint16>(nx),
          encoding.is_signed ? OFTrue : OFFalse, EctTypes::E_ImageType1_Derived,
          EctTypes::DT_ImageType3_Volume, EctTypes::DT_ImageType4_Resampled,
          "1", EctTypes::E_ContQuali_Research, EctTypes::E_PixelPres_Monochrome,
          EctTypes::E_VolProps_Volume, EctTypes::DT_VolBasedCalcTechnique_None,
          equipment),
      "create the object"));
  std::unique_ptr<EctEnhancedCT> object(raw);

  // Identity; patient and study are copied from the source after encoding.
  const std::string date = CurrentDate();
  const std::string time = CurrentTime();
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      object->getStudy().setStudyInstanceUID(
          (identity.study_instance_uid.empty() ? source.study_instance_uid
                                               : identity.study_instance_uid)
              .c_str()),
      "set StudyInstanceUID"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->getFrameOfReference().setFrameOfReferenceUID(
                        (identity.frame_of_reference_uid.empty()
                             ? source.frame_of_reference_uid
                             : identity.frame_of_reference_uid)
                            .c_str()),
                    "set FrameOfReferenceUID"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->getSeries().setSeriesInstanceUID(
                        identity.series_instance_uid.c_str()),
                    "set SeriesInstanceUID"));
  object->getSeries().setSeriesNumber(
      std::to_string(identity.series_number).c_str());
  object->getSeries().setSeriesDescription(
      identity.series_description.substr(0, 64).c_str());
  object->getSeries().setSeriesDate(date.c_str());
  object->getSeries().setSeriesTime(time.c_str());
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->getSOPCommon().setSOPInstanceUID(
                        identity.sop_instance_uids.front().c_str()),
                    "set SOPInstanceUID"));
  object->getIODMultiFrameFGModule().setContentDate(date.c_str());
  object->getIODMultiFrameFGModule().setContentTime(time.c_str());

  // Shared functional groups.
  FGPixelMeasures measures;
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(measures.setPixelSpacing(
                        absl::StrCat(FormatDecimalString(grid.spacing[1]), "\\",
                                     FormatDecimalString(grid.spacing[0]))
                            .c_str()),
                    "set the pixel spacing"));
  const std::string slice_spacing = FormatDecimalString(grid.spacing[2]);
  measures.setSliceThickness(slice_spacing.c_str());
  measures.setSpacingBetweenSlices(slice_spacing.c_str());
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->addForAllFrames(measures), "add pixel measures"));
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
        "enhanced intensity: cannot create the plane orientation");
  }
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      object->addForAllFrames(*orientation), "add plane orientation"));

  // The classic layout's rescale ("HU" for CT; "US" for MR, whose classic
  // images carry it only when it is not the identity): stored values map to
  // the same modality values in both layouts.
  FGPixelValueTransformation transformation;
  transformation.setFGType(
      *iod == EnhancedIod::kCt
          ? FGPixelValueTransformation::E_PixelValTrans_CT
          : FGPixelValueTransformation::E_PixelValTrans_Normal);
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(transformation.setRescaleIntercept(
                        FormatDecimalString(encoding.intercept).c_str()),
                    "set the rescale intercept"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(transformation.setRescaleSlope(
                        FormatDecimalString(encoding.slope).c_str()),
                    "set the rescale slope"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      transformation.setRescaleType(encoding.rescale_type.c_str()),
      "set the rescale type"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->addForAllFrames(transformation),
                    "add the pixel value transformation"));

  FGFrameVOILUT voi;
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(voi.setWindowCenter(window_text.centers.c_str()),
                    "set the window centre"));
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      voi.setWindowWidth(window_text.widths.c_str()), "set the window width"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->addForAllFrames(voi), "add the frame VOI LUT"));

  const AnatomicRegion region = RegionOf(src);
  FGFrameAnatomy anatomy;
  // Unpaired: the region is named as a whole, neither side (the source's
  // laterality, if any, is of the study, not of these frames).
  anatomy.setLaterality(FGFrameAnatomy::LATERALITY_UNPAIRED);
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(anatomy.getAnatomy().getAnatomicRegion().set(
                        region.code, "SCT", region.meaning),
                    "set the anatomic region"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckEnhanced(object->addForAllFrames(anatomy), "add the frame anatomy"));

  if (*iod == EnhancedIod::kCt) {
    INTERSLICE_RETURN_IF_ERROR(
        AddCtFunctionalGroups(src, identity, options, *object));
  }  // (MR: its frame type is written at the end, ConvertToEnhancedMr.)

  // One dimension: the position along the normal.
  IODMultiframeDimensionModule& dimensions = object->getDimensions();
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(
      dimensions.addDimensionIndex(
          DCM_ImagePositionPatient, identity.dimension_organization_uid.c_str(),
          DCM_PlanePositionSequence, "ImagePositionPatient"),
      "add the position dimension"));
  dimensions.setDimensionOrganizationType("3D");

  // The frames: the classic layout's stored values, slice by slice.
  std::vector<Uint16> stored(static_cast<size_t>(nx * ny));
  EctEnhancedCT::FramesType frames = object->getFrames();
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
        return absl::InternalError("enhanced intensity: no signed frame store");
      }
      added = typed->addFrame(reinterpret_cast<Sint16*>(stored.data()),
                              stored.size(), per_frame);
    } else {
      auto* typed = OFget<EctEnhancedCT::Frames<Uint16>>(&frames);
      if (typed == nullptr) {
        return absl::InternalError(
            "enhanced intensity: no unsigned frame store");
      }
      added = typed->addFrame(stored.data(), stored.size(), per_frame);
    }
    INTERSLICE_RETURN_IF_ERROR(
        CheckEnhanced(added, absl::StrCat("add frame ", k + 1)));
  }
  if (static_cast<int64_t>(object->getNumberOfFrames()) != nz) {
    return absl::InternalError(
        absl::StrFormat("enhanced intensity: %d of %d frames were added",
                        object->getNumberOfFrames(), nz));
  }

  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  INTERSLICE_RETURN_IF_ERROR(CheckEnhanced(object->writeDataset(ds), "encode"));
  if (*iod == EnhancedIod::kMr) {
    INTERSLICE_RETURN_IF_ERROR(ConvertToEnhancedMr(mr_description, ds));
  }
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
