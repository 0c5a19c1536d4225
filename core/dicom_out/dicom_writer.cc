// Helpers shared by the DICOM writers, DerivedContentName and
// MeshConventionNote.
#include "core/dicom_out/dicom_writer.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <mutex>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/dicom_out/dicom_out_internal.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcitem.h"
#include "dcmtk/dcmdata/dcrleerg.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcvrda.h"
#include "dcmtk/dcmdata/dcvrtm.h"

namespace interslice {

std::string MeshConventionNote(const DicomSeries& source) {
  return absl::StrCat(
      "Mesh coordinate convention (interslice)\n"
      "Vertex coordinates are DICOM patient coordinates (LPS) in millimetres:\n"
      "  +x towards the patient's left, +y towards the patient's posterior,\n"
      "  +z towards the patient's head,\n"
      "in the Frame of Reference of the source series, so they overlay the\n"
      "source images and the derived DICOM series/SEG without any transform.\n"
      "FrameOfReferenceUID: ",
      source.frame_of_reference_uid,
      "\n"
      "Source SeriesInstanceUID: ",
      source.series_instance_uid,
      "\n"
      "Triangles are counter-clockwise seen from outside (normals point out).\n"
      "Tools that expect RAS (e.g. 3D Slicer's default) need x -> -x and\n"
      "y -> -y (which preserves orientation; no winding change needed).\n");
}

namespace dicom_out_internal {

absl::Status CheckDcmtk(const OFCondition& condition, absl::string_view object,
                        absl::string_view what) {
  if (condition.good()) return absl::OkStatus();
  return absl::InternalError(
      absl::StrCat(object, ": cannot ", what, ": ", condition.text()));
}

absl::Status ValidateOutputGrid(const DicomSeries& source, const Grid& grid,
                                size_t voxel_count, const char* what) {
  if (absl::Status status = grid.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, " grid: ", status.message()));
  }
  if (static_cast<int64_t>(voxel_count) != grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        absl::StrFormat("%s holds %d voxels but its grid %s needs %d", what,
                        voxel_count, grid.DebugString(), grid.VoxelCount()));
  }
  if (grid.size[0] > 65535 || grid.size[1] > 65535) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s slices are %dx%d; DICOM allows at most 65535 rows and columns",
        what, grid.size[0], grid.size[1]));
  }
  if (source.slices.empty() ||
      static_cast<int64_t>(source.slices.size()) != source.image.grid.size[2]) {
    return absl::InvalidArgumentError(
        "source series has no slices (or slices do not match its grid)");
  }
  for (int i = 0; i < 9; ++i) {
    if (std::abs(grid.direction[i] - source.image.grid.direction[i]) > 1e-4) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s grid direction differs from the source series' (output %s, "
          "source %s); DICOM slices must share the source orientation",
          what, grid.DebugString(), source.image.grid.DebugString()));
    }
  }
  return absl::OkStatus();
}

double SlicePositionAlongNormal(const Grid& grid, int64_t k) {
  const Vec3 p = grid.IndexToPhysical({0, 0, static_cast<double>(k)});
  const Vec3 n = grid.Axis(2);
  return p[0] * n[0] + p[1] * n[1] + p[2] * n[2];
}

std::vector<int64_t> NearestSourceSlices(const DicomSeries& source,
                                         double position) {
  constexpr double kOnSlice = 1e-3;  // mm
  const auto& slices = source.slices;
  const int64_t n = static_cast<int64_t>(slices.size());
  // slices are sorted by position_along_normal (the reader's contract).
  int64_t upper = 0;
  while (upper < n && slices[upper].position_along_normal < position) ++upper;
  if (upper < n &&
      std::abs(slices[upper].position_along_normal - position) <= kOnSlice) {
    return {upper};
  }
  if (upper > 0 && std::abs(slices[upper - 1].position_along_normal -
                            position) <= kOnSlice) {
    return {upper - 1};
  }
  if (upper == 0) return {0};
  if (upper == n) return {n - 1};
  return {upper - 1, upper};
}

absl::StatusOr<std::unique_ptr<DcmFileFormat>> LoadSourceHeader(
    const DicomSeries& source) {
  if (source.slices.empty()) {
    return absl::InvalidArgumentError("source series has no slices");
  }
  const std::string& path = source.slices.front().path;
  auto file = std::make_unique<DcmFileFormat>();
  // Large values (pixel data) stay on disk: only the header is needed.
  const OFCondition cond =
      file->loadFile(OFFilename(path.c_str()), EXS_Unknown, EGL_noChange,
                     /*maxReadLength=*/4096, ERM_autoDetect);
  if (cond.bad()) {
    return absl::FailedPreconditionError(
        absl::StrCat("cannot read the source file ",
                     std::filesystem::path(path).filename().string(),
                     " again to copy patient and study data: ", cond.text()));
  }
  return file;
}

namespace {

// Type 2 attributes of the copied modules: written empty when absent.
const DcmTagKey kType2Tags[] = {
    DCM_PatientName,
    DCM_PatientID,
    DCM_PatientBirthDate,
    DCM_PatientSex,
    DCM_StudyDate,
    DCM_StudyTime,
    DCM_ReferringPhysicianName,
    DCM_StudyID,
    DCM_AccessionNumber,
    DCM_PositionReferenceIndicator,
};

// Patient, Clinical Trial Subject, General Study, Patient Study, Clinical
// Trial Study and Frame of Reference modules (DICOM PS3.3 C.7.1.1, C.7.1.3,
// C.7.2.1, C.7.2.2, C.7.2.3, C.7.4.1), the attributes DCMTK 3.6.7 knows.
const DcmTagKey kCopiedTags[] = {
    DCM_SpecificCharacterSet,
    // Patient
    DCM_PatientName,
    DCM_PatientID,
    DCM_IssuerOfPatientID,
    DCM_IssuerOfPatientIDQualifiersSequence,
    DCM_TypeOfPatientID,
    DCM_PatientBirthDate,
    DCM_PatientBirthTime,
    DCM_PatientSex,
    DCM_QualityControlSubject,
    DCM_OtherPatientIDsSequence,
    DCM_OtherPatientNames,
    DCM_EthnicGroup,
    DCM_PatientComments,
    DCM_PatientSpeciesDescription,
    DCM_PatientSpeciesCodeSequence,
    DCM_PatientBreedDescription,
    DCM_PatientBreedCodeSequence,
    DCM_BreedRegistrationSequence,
    DCM_StrainDescription,
    DCM_ResponsiblePerson,
    DCM_ResponsiblePersonRole,
    DCM_ResponsibleOrganization,
    DCM_PatientIdentityRemoved,
    DCM_DeidentificationMethod,
    DCM_DeidentificationMethodCodeSequence,
    // Clinical Trial Subject
    DCM_ClinicalTrialSponsorName,
    DCM_ClinicalTrialProtocolID,
    DCM_ClinicalTrialProtocolName,
    DCM_ClinicalTrialSiteID,
    DCM_ClinicalTrialSiteName,
    DCM_ClinicalTrialSubjectID,
    DCM_ClinicalTrialSubjectReadingID,
    // General Study
    DCM_StudyInstanceUID,
    DCM_StudyDate,
    DCM_StudyTime,
    DCM_ReferringPhysicianName,
    DCM_ReferringPhysicianIdentificationSequence,
    DCM_ConsultingPhysicianName,
    DCM_ConsultingPhysicianIdentificationSequence,
    DCM_StudyID,
    DCM_AccessionNumber,
    DCM_IssuerOfAccessionNumberSequence,
    DCM_StudyDescription,
    DCM_PhysiciansOfRecord,
    DCM_PhysiciansOfRecordIdentificationSequence,
    DCM_NameOfPhysiciansReadingStudy,
    DCM_PhysiciansReadingStudyIdentificationSequence,
    DCM_RequestingServiceCodeSequence,
    DCM_ReferencedStudySequence,
    DCM_ProcedureCodeSequence,
    DCM_ReasonForPerformedProcedureCodeSequence,
    // Patient Study
    DCM_AdmittingDiagnosesDescription,
    DCM_AdmittingDiagnosesCodeSequence,
    DCM_PatientAge,
    DCM_PatientSize,
    DCM_PatientWeight,
    DCM_PatientSizeCodeSequence,
    DCM_Occupation,
    DCM_AdditionalPatientHistory,
    DCM_AdmissionID,
    DCM_IssuerOfAdmissionIDSequence,
    DCM_ServiceEpisodeID,
    DCM_IssuerOfServiceEpisodeIDSequence,
    DCM_ServiceEpisodeDescription,
    DCM_PatientSexNeutered,
    DCM_MedicalAlerts,
    DCM_Allergies,
    DCM_SmokingStatus,
    DCM_PregnancyStatus,
    DCM_LastMenstrualDate,
    DCM_PatientState,
    // Clinical Trial Study
    DCM_ClinicalTrialTimePointID,
    DCM_ClinicalTrialTimePointDescription,
    DCM_ConsentForClinicalTrialUseSequence,
    // Frame of Reference
    DCM_FrameOfReferenceUID,
    DCM_PositionReferenceIndicator,
};

}  // namespace

void CopyAnatomy(DcmItem& from, DcmItem& to) {
  // Body parts PS3.16 Annex L lists as unpaired and dciodvfy (dicom3tools)
  // accepts without Laterality; every other term, known or not, may be
  // paired.
  static const std::set<std::string>* const kUnpaired =
      new std::set<std::string>{
          "ABDOMEN",        "ABDOMENPELVIS", "AORTA",     "BLADDER",
          "BRAIN",          "CERVIX",        "CHEST",     "CHESTABDOMEN",
          "CHESTABDPELVIS", "COCCYX",        "COLON",     "CSPINE",
          "CTSPINE",        "DUODENUM",      "ESOPHAGUS", "FACE",
          "GALLBLADDER",    "HEAD",          "HEADNECK",  "HEART",
          "ILEUM",          "JAW",           "JEJUNUM",   "LARYNX",
          "LIVER",          "LSPINE",        "MAXILLA",   "MEDIASTINUM",
          "MOUTH",          "NECK",          "NOSE",      "PANCREAS",
          "PELVIS",         "PENIS",         "PHARYNX",   "PROSTATE",
          "RECTUM",         "SKULL",         "SPINE",     "SPLEEN",
          "STERNUM",        "STOMACH",       "THYMUS",    "THYROID",
          "TLSPINE",        "TRACHEA",       "TSPINE",    "UTERUS",
          "VAGINA",         "WHOLEBODY"};
  const auto value_of = [&from](const DcmTagKey& tag) {
    OFString value;
    if (from.findAndGetOFString(tag, value).good()) {
      return std::string(absl::StripAsciiWhitespace(value.c_str()));
    }
    return std::string();
  };
  to.findAndDeleteElement(DCM_BodyPartExamined);
  to.findAndDeleteElement(DCM_Laterality);
  to.findAndDeleteElement(DCM_ImageLaterality);
  std::string body_part = value_of(DCM_BodyPartExamined);
  const bool valid_cs =
      !body_part.empty() && body_part.size() <= 16 &&
      std::all_of(body_part.begin(), body_part.end(), [](char c) {
        return absl::ascii_isupper(c) || absl::ascii_isdigit(c) || c == ' ' ||
               c == '_';
      });
  if (valid_cs) {
    to.putAndInsertString(DCM_BodyPartExamined, body_part.c_str());
  } else {
    body_part.clear();
  }
  const std::string laterality = value_of(DCM_Laterality);
  const std::string image_laterality = value_of(DCM_ImageLaterality);
  const bool has_image_laterality =
      image_laterality == "R" || image_laterality == "L" ||
      image_laterality == "U" || image_laterality == "B";
  if (has_image_laterality) {
    to.putAndInsertString(DCM_ImageLaterality, image_laterality.c_str());
    return;  // Laterality only when ImageLaterality is not sent
  }
  if (laterality == "R" || laterality == "L") {
    to.putAndInsertString(DCM_Laterality, laterality.c_str());
  } else if (kUnpaired->count(body_part) == 0) {
    to.insertEmptyElement(DCM_Laterality);
  }
}

void CopyPatientStudyFrameOfReference(DcmItem& from,
                                      const DerivedObjectIdentity& identity,
                                      DcmItem& to) {
  for (const DcmTagKey& tag : kCopiedTags) {
    DcmElement* element = nullptr;
    if (from.findAndGetElement(tag, element, /*searchIntoSub=*/OFFalse,
                               /*createCopy=*/OFTrue)
            .good() &&
        element != nullptr) {
      // Empty values (and sequences without items) are dropped: for type 2
      // attributes an empty one is written below; for type 1C/2C/3 ones an
      // empty value is an error of the source (dciodvfy flags it).
      if (element->isEmpty()) {
        delete element;
        continue;
      }
      to.insert(element, /*replaceOld=*/OFTrue);
    }
  }
  for (const DcmTagKey& tag : kType2Tags) {
    if (!to.tagExists(tag)) to.insertEmptyElement(tag);
  }
  if (!identity.study_instance_uid.empty()) {
    to.putAndInsertString(DCM_StudyInstanceUID,
                          identity.study_instance_uid.c_str());
  }
  if (!identity.frame_of_reference_uid.empty()) {
    to.putAndInsertString(DCM_FrameOfReferenceUID,
                          identity.frame_of_reference_uid.c_str());
  }
  // Patient Identity Removed "YES" makes De-identification Method (or its
  // code sequence) type 1C. An anonymiser that said YES but left the method
  // empty would make every derived object invalid; repair it with a value
  // that says only what is known.
  OFString removed;
  if (to.findAndGetOFString(DCM_PatientIdentityRemoved, removed).good() &&
      removed == "YES" && !to.tagExists(DCM_DeidentificationMethod) &&
      !to.tagExists(DCM_DeidentificationMethodCodeSequence)) {
    to.putAndInsertString(DCM_DeidentificationMethod,
                          "unknown: not stated in the source series");
  }
}

void AddReferencedSeries(const DicomSeries& source, DcmItem& to) {
  to.findAndDeleteElement(DCM_ReferencedSeriesSequence);
  if (source.series_instance_uid.empty() || source.sop_class_uid.empty()) {
    return;
  }
  DcmItem* series = nullptr;
  to.findOrCreateSequenceItem(DCM_ReferencedSeriesSequence, series, 0);
  series->putAndInsertString(DCM_SeriesInstanceUID,
                             source.series_instance_uid.c_str());
  for (size_t i = 0; i < source.slices.size(); ++i) {
    if (source.slices[i].sop_instance_uid.empty()) continue;
    DcmItem* instance = nullptr;
    series->findOrCreateSequenceItem(DCM_ReferencedInstanceSequence, instance,
                                     -2 /* append */);
    instance->putAndInsertString(DCM_ReferencedSOPClassUID,
                                 source.sop_class_uid.c_str());
    instance->putAndInsertString(DCM_ReferencedSOPInstanceUID,
                                 source.slices[i].sop_instance_uid.c_str());
  }
}

void AddReferencedImageSeries(const DerivedObjectIdentity& series,
                              DcmItem& to) {
  to.findAndDeleteElement(DCM_ReferencedSeriesSequence);
  DcmItem* item = nullptr;
  to.findOrCreateSequenceItem(DCM_ReferencedSeriesSequence, item, 0);
  item->putAndInsertString(DCM_SeriesInstanceUID,
                           series.series_instance_uid.c_str());
  for (const std::string& uid : series.sop_instance_uids) {
    DcmItem* instance = nullptr;
    item->findOrCreateSequenceItem(DCM_ReferencedInstanceSequence, instance,
                                   -2 /* append */);
    instance->putAndInsertString(DCM_ReferencedSOPClassUID,
                                 series.sop_class_uid.c_str());
    instance->putAndInsertString(DCM_ReferencedSOPInstanceUID, uid.c_str());
  }
}

bool IsEnhancedImageSopClass(const std::string& sop_class_uid) {
  return sop_class_uid == UID_EnhancedCTImageStorage ||
         sop_class_uid == UID_EnhancedMRImageStorage;
}

SliceImageReference ReferenceSliceImage(const DerivedObjectIdentity& referenced,
                                        int64_t k) {
  if (IsEnhancedImageSopClass(referenced.sop_class_uid) &&
      referenced.sop_instance_uids.size() == 1) {
    return {referenced.sop_instance_uids.front(), k + 1};
  }
  return {referenced.sop_instance_uids[static_cast<size_t>(k)], 0};
}

absl::Status CheckReferencedSeries(const DerivedObjectIdentity& identity,
                                   const DerivedObjectIdentity& referenced,
                                   const Grid& grid, const char* what) {
  if (identity.series_instance_uid.empty() ||
      identity.sop_instance_uids.size() != 1 ||
      identity.sop_instance_uids.front().empty() ||
      identity.dimension_organization_uid.empty() ||
      identity.series_number <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        what,
        ": its identity needs a series UID, one SOP instance UID, a "
        "dimension organization UID and a series number"));
  }
  const bool one_multi_frame_instance =
      IsEnhancedImageSopClass(referenced.sop_class_uid) &&
      referenced.sop_instance_uids.size() == 1;
  if ((!one_multi_frame_instance &&
       static_cast<int64_t>(referenced.sop_instance_uids.size()) !=
           grid.size[2]) ||
      referenced.series_instance_uid.empty() ||
      referenced.sop_class_uid.empty()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: the referenced image series names %d images for %d slices", what,
        referenced.sop_instance_uids.size(), grid.size[2]));
  }
  return absl::OkStatus();
}

std::string FormatDecimalString(double value) {
  if (value == 0) return "0";  // also turns -0 into 0
  for (int precision = 15; precision > 0; --precision) {
    std::string text = absl::StrFormat("%.*g", precision, value);
    if (text.size() <= 16) return text;
  }
  return absl::StrFormat("%.0e", value);
}

std::string CurrentDate() {
  OFString date;
  DcmDate::getCurrentDate(date);
  return std::string(date.c_str());
}

std::string CurrentTime() {
  OFString time;
  DcmTime::getCurrentTime(time, /*seconds=*/OFTrue, /*fraction=*/OFFalse);
  return std::string(time.c_str());
}

absl::StatusOr<std::string> SaveFileUnsynced(DcmFileFormat& file,
                                             const std::string& path,
                                             E_TransferSyntax xfer) {
  if (DcmXfer(xfer).isEncapsulated()) {
    static std::once_flag once;
    // DCMTK's codec registry is process-wide; registering twice would add
    // duplicate codecs.
    std::call_once(once, [] { DcmRLEEncoderRegistration::registerCodecs(); });
    const OFCondition encoded =
        file.getDataset()->chooseRepresentation(xfer, nullptr);
    if (encoded.bad() || !file.getDataset()->canWriteXfer(xfer)) {
      return absl::InternalError(absl::StrCat(
          "cannot encode ", path, " as ", DcmXfer(xfer).getXferName(), ": ",
          encoded.bad() ? encoded.text() : "no codec for its pixel data"));
    }
  }
  thread_local std::mt19937_64 random(std::random_device{}());
  const std::string temp =
      absl::StrFormat("%s.tmp-%016x", path, static_cast<uint64_t>(random()));
  const OFCondition cond =
      file.saveFile(OFFilename(temp.c_str()), xfer, EET_ExplicitLength,
                    EGL_recalcGL, EPD_withoutPadding);
  if (cond.bad()) {
    std::remove(temp.c_str());
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", cond.text()));
  }
  // Start the writeback now, while other files are encoded; CommitFile's
  // fsync then waits for little. Advisory: its failure is CommitFile's to
  // report.
  const int fd = ::open(temp.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd >= 0) {
    ::sync_file_range(fd, 0, 0, SYNC_FILE_RANGE_WRITE);
    ::close(fd);
  }
  return temp;
}

absl::Status CommitFile(const std::string& temp, const std::string& path) {
  // Data on disk before the name: after a crash the target is either the old
  // file or the complete new one.
  const int fd = ::open(temp.c_str(), O_RDONLY | O_CLOEXEC);
  const bool synced = fd >= 0 && ::fsync(fd) == 0;
  const int sync_errno = errno;
  if (fd >= 0) ::close(fd);
  if (!synced) {
    std::remove(temp.c_str());
    return absl::InternalError(
        absl::StrCat("cannot sync ", path, ": ", std::strerror(sync_errno)));
  }
  if (std::rename(temp.c_str(), path.c_str()) != 0) {
    const int rename_errno = errno;
    std::remove(temp.c_str());
    return absl::InternalError(absl::StrCat("cannot rename into ", path, ": ",
                                            std::strerror(rename_errno)));
  }
  return absl::OkStatus();
}

absl::Status SyncDirectory(const std::string& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  const bool synced = fd >= 0 && ::fsync(fd) == 0;
  const int sync_errno = errno;
  if (fd >= 0) ::close(fd);
  if (!synced) {
    return absl::InternalError(
        absl::StrCat("cannot sync ", dir, ": ", std::strerror(sync_errno)));
  }
  return absl::OkStatus();
}

absl::Status SaveFileAtomically(DcmFileFormat& file, const std::string& path,
                                E_TransferSyntax xfer) {
  absl::StatusOr<std::string> temp = SaveFileUnsynced(file, path, xfer);
  if (!temp.ok()) return temp.status();
  return CommitFile(*temp, path);
}

}  // namespace dicom_out_internal
}  // namespace interslice
