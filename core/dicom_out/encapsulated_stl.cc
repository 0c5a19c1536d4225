// Encapsulated STL (PS3.3 A.85). The document itself is read, checked and
// embedded by DCMTK's DcmEncapsulatedDocument (insertEncapsulatedDocument,
// the code stl2dcm runs). Its header half (createHeader) is not used: in
// DCMTK 3.6.7 its values can only be set through parseArguments, i.e. an
// OFConsoleApplication command line that exits the process on a bad value,
// and it invents random Study/Series/SOP Instance UIDs. A daemon needs
// neither, so the modules around the document are filled here from the
// source and the job's plan, like the other derived objects.
#include "core/dicom_out/encapsulated_stl.h"

#include <sys/stat.h>

#include <filesystem>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dccodec.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcencdoc.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/oflog/oflog.h"

namespace interslice {
namespace {

using dicom_out_internal::CopyPatientStudyFrameOfReference;
using dicom_out_internal::CurrentDate;
using dicom_out_internal::CurrentTime;
using dicom_out_internal::LoadSourceHeader;
using dicom_out_internal::SaveFileAtomically;

std::string BaseName(const std::string& path) {
  return std::filesystem::path(path).filename().string();
}

absl::Status CheckStl(const OFCondition& cond, absl::string_view what) {
  return dicom_out_internal::CheckDcmtk(cond, "Encapsulated STL", what);
}

// SourceInstanceSequence (Encapsulated Document module, type 1C: the
// document was derived from these images).
void AddSourceInstances(const DicomSeries& source, DcmItem& to) {
  if (source.sop_class_uid.empty()) return;
  for (const DicomSliceInfo& slice : source.slices) {
    if (slice.sop_instance_uid.empty()) continue;
    DcmItem* item = nullptr;
    to.findOrCreateSequenceItem(DCM_SourceInstanceSequence, item,
                                -2 /* append */);
    item->putAndInsertString(DCM_ReferencedSOPClassUID,
                             source.sop_class_uid.c_str());
    item->putAndInsertString(DCM_ReferencedSOPInstanceUID,
                             slice.sop_instance_uid.c_str());
  }
}

}  // namespace

absl::Status WriteEncapsulatedStl(const DicomSeries& source,
                                  const std::string& stl_path,
                                  const DerivedObjectIdentity& identity,
                                  const DicomWriteOptions& options,
                                  const std::string& path) {
  if (identity.series_instance_uid.empty() ||
      identity.sop_instance_uids.size() != 1 ||
      identity.sop_instance_uids.front().empty() ||
      identity.series_number <= 0) {
    return absl::InvalidArgumentError(
        "Encapsulated STL: the identity needs a series UID, one SOP "
        "instance UID and a series number");
  }
  struct stat st {};
  if (::stat(stl_path.c_str(), &st) != 0 || !S_ISREG(st.st_mode) ||
      st.st_size == 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "Encapsulated STL: ", BaseName(stl_path), " is missing or empty"));
  }
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& src = *source_file->getDataset();

  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();

  // The document: DCMTK checks that it is a consistent binary STL and
  // embeds it (pad byte included).
  {
    DcmEncapsulatedDocument encapsulator;
    encapsulator.setFileType("stl");
    encapsulator.setInputFileName(stl_path.c_str());
    OFLogger logger = OFLog::getLogger("interslice.dicom_out.stl");
    if (encapsulator.insertEncapsulatedDocument(&ds, logger) != 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          "Encapsulated STL: ", BaseName(stl_path),
          " is not a consistent binary STL file (DICOM accepts only binary "
          "STL)"));
    }
  }
  INTERSLICE_RETURN_IF_ERROR(
      CheckStl(ds.putAndInsertUint32(DCM_EncapsulatedDocumentLength,
                                     static_cast<Uint32>(st.st_size)),
               "set EncapsulatedDocumentLength"));

  // Patient, study, frame of reference: the source's.
  CopyPatientStudyFrameOfReference(src, identity, ds);

  // SOP Common.
  const std::string& sop_uid = identity.sop_instance_uids.front();
  ds.putAndInsertString(DCM_SOPClassUID, UID_EncapsulatedSTLStorage);
  ds.putAndInsertString(DCM_SOPInstanceUID, sop_uid.c_str());
  ds.putAndInsertString(DCM_InstanceCreationDate, CurrentDate().c_str());
  ds.putAndInsertString(DCM_InstanceCreationTime, CurrentTime().c_str());

  // Encapsulated Document Series (M3D for manufacturing models).
  ds.putAndInsertString(DCM_Modality, "M3D");
  ds.putAndInsertString(DCM_SeriesInstanceUID,
                        identity.series_instance_uid.c_str());
  ds.putAndInsertString(DCM_SeriesNumber,
                        std::to_string(identity.series_number).c_str());
  ds.putAndInsertString(DCM_SeriesDescription,
                        identity.series_description.substr(0, 64).c_str());
  ds.putAndInsertString(DCM_SeriesDate, CurrentDate().c_str());
  ds.putAndInsertString(DCM_SeriesTime, CurrentTime().c_str());

  // Enhanced General Equipment: interslice made the object (a software tool
  // has no serial number; the module needs one).
  ds.putAndInsertString(DCM_Manufacturer, "interslice");
  ds.putAndInsertString(DCM_ManufacturerModelName, "interslice");
  ds.putAndInsertString(DCM_DeviceSerialNumber, "0");
  ds.putAndInsertString(DCM_SoftwareVersions, options.software_version.c_str());

  // Encapsulated Document.
  ds.putAndInsertString(DCM_InstanceNumber, "1");
  ds.putAndInsertString(DCM_ContentDate, CurrentDate().c_str());
  ds.putAndInsertString(DCM_ContentTime, CurrentTime().c_str());
  ds.insertEmptyElement(DCM_AcquisitionDateTime);
  // The mesh is geometry only: no text or faces that identify anyone.
  ds.putAndInsertString(DCM_BurnedInAnnotation, "NO");
  ds.putAndInsertString(DCM_DocumentTitle,
                        identity.series_description.substr(0, 64).c_str());
  ds.insertEmptyElement(DCM_ConceptNameCodeSequence);
  ds.putAndInsertString(DCM_MIMETypeOfEncapsulatedDocument, "model/stl");
  AddSourceInstances(source, ds);
  // Common Instance Reference: the source series (same study), which the
  // Source Instance Sequence above refers into.
  dicom_out_internal::AddReferencedSeries(source, ds);

  // Manufacturing 3D Model: vertices are millimetres.
  INTERSLICE_RETURN_IF_ERROR(
      CheckStl(DcmCodec::insertCodeSequence(
                   &ds, DCM_MeasurementUnitsCodeSequence, "UCUM", "mm", "mm"),
               "set MeasurementUnitsCodeSequence"));

  return SaveFileAtomically(file, path);
}

}  // namespace interslice
