// The previews as a Secondary Capture image series (preview_series.h).
#include "core/dicom_out/preview_series.h"

#include <filesystem>
#include <memory>
#include <random>
#include <string>
#include <system_error>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using dicom_out_internal::CopyAnatomy;
using dicom_out_internal::kSourceImagePurposeCode;
using dicom_out_internal::kSourceImagePurposeMeaning;

void AddSourceImage(DcmItem& ds, const std::string& sop_class,
                    const std::string& sop_instance) {
  DcmItem* item = nullptr;
  ds.findOrCreateSequenceItem(DCM_SourceImageSequence, item, -2);
  item->putAndInsertString(DCM_ReferencedSOPClassUID, sop_class.c_str());
  item->putAndInsertString(DCM_ReferencedSOPInstanceUID, sop_instance.c_str());
  DcmItem* purpose = nullptr;
  item->findOrCreateSequenceItem(DCM_PurposeOfReferenceCodeSequence, purpose,
                                 0);
  purpose->putAndInsertString(DCM_CodeValue, kSourceImagePurposeCode);
  purpose->putAndInsertString(DCM_CodingSchemeDesignator, "DCM");
  purpose->putAndInsertString(DCM_CodeMeaning, kSourceImagePurposeMeaning);
}

absl::Status CheckPictures(const std::vector<RgbPicture>& pictures,
                           const DerivedObjectIdentity& identity) {
  if (pictures.empty()) {
    return absl::InvalidArgumentError("the preview series has no pictures");
  }
  if (identity.sop_instance_uids.size() != pictures.size() ||
      identity.series_instance_uid.empty() || identity.series_number <= 0) {
    return absl::InvalidArgumentError(
        "the preview series' identity does not name one instance per picture");
  }
  for (const RgbPicture& p : pictures) {
    if (p.rgb == nullptr || p.width <= 0 || p.height <= 0 || p.width > 65535 ||
        p.height > 65535 ||
        p.rgb->size() != static_cast<size_t>(p.width) * p.height * 3) {
      return absl::InvalidArgumentError(
          absl::StrCat("preview ", p.name,
                       ": no pixels, a wrong size or over 65535 pixels "
                       "a side"));
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::vector<std::string>> WritePreviewSeries(
    const DicomSeries& source, const Grid& grid,
    const std::vector<RgbPicture>& pictures,
    const DerivedObjectIdentity& identity,
    const DerivedObjectIdentity* referenced, const DicomWriteOptions& options,
    const std::string& output_dir) {
  using namespace dicom_out_internal;
  INTERSLICE_RETURN_IF_ERROR(CheckPictures(pictures, identity));
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& header = *source_file->getDataset();
  const std::string date = CurrentDate();
  const std::string time = CurrentTime();

  // A fresh sibling folder, renamed into place when complete.
  const fs::path target(output_dir);
  std::random_device random;
  const fs::path temp =
      target.parent_path() /
      absl::StrCat(".", target.filename().string(), ".tmp-", random());
  std::error_code ec;
  fs::create_directories(temp, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create ", temp.string(), ": ", ec.message()));
  }
  auto fail = [&](absl::Status status) {
    std::error_code ignored;
    fs::remove_all(temp, ignored);
    return status;
  };

  std::vector<std::string> paths;
  for (size_t n = 0; n < pictures.size(); ++n) {
    const RgbPicture& picture = pictures[n];
    DcmFileFormat file;
    DcmDataset& ds = *file.getDataset();
    CopyPatientStudyFrameOfReference(header, identity, ds);
    // A picture is not in patient coordinates: the SC IOD has no Frame of
    // Reference module.
    ds.findAndDeleteElement(DCM_FrameOfReferenceUID);
    ds.findAndDeleteElement(DCM_PositionReferenceIndicator);
    CopyAnatomy(header, ds);

    // SOP Common, General Series, General and SC Equipment.
    ds.putAndInsertString(DCM_SOPClassUID, UID_SecondaryCaptureImageStorage);
    ds.putAndInsertString(DCM_SOPInstanceUID,
                          identity.sop_instance_uids[n].c_str());
    ds.putAndInsertString(DCM_InstanceCreationDate, date.c_str());
    ds.putAndInsertString(DCM_InstanceCreationTime, time.c_str());
    ds.putAndInsertString(DCM_Modality, "OT");
    ds.putAndInsertString(DCM_SeriesInstanceUID,
                          identity.series_instance_uid.c_str());
    ds.putAndInsertString(DCM_SeriesNumber,
                          std::to_string(identity.series_number).c_str());
    ds.putAndInsertString(DCM_SeriesDate, date.c_str());
    ds.putAndInsertString(DCM_SeriesTime, time.c_str());
    ds.putAndInsertString(DCM_SeriesDescription,
                          identity.series_description.substr(0, 64).c_str());
    ds.putAndInsertString(DCM_Manufacturer, "interslice");
    ds.putAndInsertString(DCM_ManufacturerModelName, "interslice");
    ds.putAndInsertString(DCM_SoftwareVersions,
                          options.software_version.c_str());
    ds.putAndInsertString(DCM_ConversionType, "WSD");
    ds.putAndInsertString(DCM_SecondaryCaptureDeviceManufacturer, "interslice");
    ds.putAndInsertString(DCM_SecondaryCaptureDeviceSoftwareVersions,
                          options.software_version.c_str());
    ds.putAndInsertString(DCM_DateOfSecondaryCapture, date.c_str());
    ds.putAndInsertString(DCM_TimeOfSecondaryCapture, time.c_str());

    // General Image.
    ds.putAndInsertString(DCM_InstanceNumber, std::to_string(n + 1).c_str());
    ds.putAndInsertString(DCM_ContentDate, date.c_str());
    ds.putAndInsertString(DCM_ContentTime, time.c_str());
    ds.putAndInsertString(DCM_ImageType, "DERIVED\\SECONDARY");
    ds.putAndInsertString(DCM_PatientOrientation,
                          picture.patient_orientation.c_str());
    ds.putAndInsertString(DCM_BurnedInAnnotation, "YES");
    ds.putAndInsertString(DCM_LossyImageCompression, "00");
    ds.putAndInsertString(DCM_ImageComments,
                          picture.description.substr(0, 10240).c_str());
    std::string derivation = absl::StrCat(options.derivation_description,
                                          "; preview: ", picture.description);
    if (derivation.size() > 1024) derivation.resize(1024);  // ST
    ds.putAndInsertString(DCM_DerivationDescription, derivation.c_str());
    if (referenced != nullptr) {
      // The images of the series on the output grid the picture shows.
      if (picture.output_slice.has_value() && *picture.output_slice >= 0 &&
          *picture.output_slice <
              static_cast<int64_t>(referenced->sop_instance_uids.size())) {
        AddSourceImage(ds, referenced->sop_class_uid,
                       referenced->sop_instance_uids[*picture.output_slice]);
      } else {
        for (const std::string& uid : referenced->sop_instance_uids) {
          AddSourceImage(ds, referenced->sop_class_uid, uid);
        }
      }
      AddReferencedImageSeries(*referenced, ds);
    } else {
      std::vector<int64_t> slices;
      if (picture.output_slice.has_value()) {
        slices = NearestSourceSlices(
            source, SlicePositionAlongNormal(grid, *picture.output_slice));
      } else {
        for (size_t s = 0; s < source.slices.size(); ++s) slices.push_back(s);
      }
      for (int64_t s : slices) {
        // An anonymised source slice without a SOP Instance UID cannot be
        // referenced.
        if (source.slices[s].sop_instance_uid.empty() ||
            source.sop_class_uid.empty()) {
          continue;
        }
        AddSourceImage(ds, source.sop_class_uid,
                       source.slices[s].sop_instance_uid);
      }
      AddReferencedSeries(source, ds);
    }

    // Image Pixel: 8-bit RGB, colour-by-pixel (PS3.3 C.7.6.3.1.3).
    ds.putAndInsertUint16(DCM_SamplesPerPixel, 3);
    ds.putAndInsertString(DCM_PhotometricInterpretation, "RGB");
    ds.putAndInsertUint16(DCM_PlanarConfiguration, 0);
    ds.putAndInsertUint16(DCM_Rows, static_cast<Uint16>(picture.height));
    ds.putAndInsertUint16(DCM_Columns, static_cast<Uint16>(picture.width));
    ds.putAndInsertUint16(DCM_BitsAllocated, 8);
    ds.putAndInsertUint16(DCM_BitsStored, 8);
    ds.putAndInsertUint16(DCM_HighBit, 7);
    ds.putAndInsertUint16(DCM_PixelRepresentation, 0);
    ds.putAndInsertUint8Array(DCM_PixelData, picture.rgb->data(),
                              picture.rgb->size());

    const std::string name = absl::StrFormat("IM%05d.dcm", n + 1);
    const absl::Status saved = SaveFileAtomically(file, (temp / name).string());
    if (!saved.ok()) return fail(saved);
    paths.push_back((target / name).string());
  }
  fs::remove_all(target, ec);
  fs::rename(temp, target, ec);
  if (ec) {
    return fail(
        absl::InternalError(absl::StrCat("cannot move the preview series into ",
                                         output_dir, ": ", ec.message())));
  }
  INTERSLICE_RETURN_IF_ERROR(SyncDirectory(
      target.parent_path().empty() ? "." : target.parent_path().string()));
  return paths;
}

}  // namespace interslice
