// WriteRtStructureSet: the filled labels as an RT Structure Set (DCMTK
// dcmrt).
#include "core/dicom_out/rtstruct.h"

#include <memory>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmrt/drtstrct.h"

namespace interslice {
namespace {

using dicom_out_internal::CopyPatientStudyFrameOfReference;
using dicom_out_internal::CurrentDate;
using dicom_out_internal::CurrentTime;
using dicom_out_internal::FormatDecimalString;
using dicom_out_internal::LoadSourceHeader;
using dicom_out_internal::SaveFileAtomically;
using dicom_out_internal::ValidateOutputGrid;

absl::Status CheckRtStruct(const OFCondition& cond, absl::string_view what) {
  return dicom_out_internal::CheckDcmtk(cond, "RTSTRUCT", what);
}

// The SOP Class a referenced study is named by (DICOM PS3.3 C.8.8.5: the
// retired Detached Study Management SOP Class, still required there).
constexpr char kStudyComponentClass[] = "1.2.840.10008.3.1.2.3.1";

}  // namespace

absl::Status WriteRtStructureSet(const DicomSeries& source, const Grid& grid,
                                 const std::vector<RoiContours>& rois,
                                 const DerivedObjectIdentity& identity,
                                 const DerivedObjectIdentity& referenced,
                                 const DicomWriteOptions& options,
                                 const std::string& path) {
  INTERSLICE_RETURN_IF_ERROR(ValidateOutputGrid(
      source, grid, static_cast<size_t>(grid.VoxelCount()), "RTSTRUCT grid"));
  if (identity.series_instance_uid.empty() ||
      identity.sop_instance_uids.size() != 1 || identity.series_number <= 0) {
    return absl::InvalidArgumentError(
        "RTSTRUCT: its identity needs a series UID, one SOP instance UID and a "
        "series number");
  }
  if (static_cast<int64_t>(referenced.sop_instance_uids.size()) !=
          grid.size[2] ||
      referenced.series_instance_uid.empty() ||
      referenced.sop_class_uid.empty()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "RTSTRUCT: the referenced image series names %d images for %d slices",
        referenced.sop_instance_uids.size(), grid.size[2]));
  }
  std::set<int> numbers;
  for (const RoiContours& r : rois) {
    if (r.roi.number < 1 || r.roi.number > 65535 ||
        !numbers.insert(r.roi.number).second) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "RTSTRUCT: ROI number %d is out of 1..65535 or given twice",
          r.roi.number));
    }
    for (const auto& [k, polygons] : r.slices) {
      if (k < 0 || k >= grid.size[2]) {
        return absl::InvalidArgumentError(absl::StrFormat(
            "RTSTRUCT: ROI %d has contours on slice %d, outside the grid",
            r.roi.number, k));
      }
      for (const auto& polygon : polygons) {
        if (polygon.size() < 3) {
          return absl::InvalidArgumentError(absl::StrFormat(
              "RTSTRUCT: ROI %d has a contour of %d points on slice %d",
              r.roi.number, polygon.size(), k));
        }
      }
    }
  }
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& src = *source_file->getDataset();
  const std::string study = identity.study_instance_uid.empty()
                                ? source.study_instance_uid
                                : identity.study_instance_uid;
  const std::string frame = identity.frame_of_reference_uid.empty()
                                ? source.frame_of_reference_uid
                                : identity.frame_of_reference_uid;

  // DRTStructureSetIOD is large (its own note): keep it off the stack.
  auto rt = std::make_unique<DRTStructureSetIOD>();
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      rt->setSOPClassUID(UID_RTStructureSetStorage), "set SOPClassUID"));
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      rt->setSOPInstanceUID(identity.sop_instance_uids.front().c_str()),
      "set SOPInstanceUID"));
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      rt->setStudyInstanceUID(study.c_str()), "set StudyInstanceUID"));
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      rt->setSeriesInstanceUID(identity.series_instance_uid.c_str()),
      "set SeriesInstanceUID"));
  rt->setModality("RTSTRUCT");
  rt->setSeriesNumber(std::to_string(identity.series_number).c_str());
  rt->setSeriesDescription(identity.series_description.substr(0, 64).c_str());
  rt->setSeriesDate(CurrentDate().c_str());
  rt->setSeriesTime(CurrentTime().c_str());
  rt->setManufacturer("interslice");
  rt->setSoftwareVersions(options.software_version.substr(0, 64).c_str());
  rt->setInstanceNumber("1");
  rt->setInstanceCreationDate(CurrentDate().c_str());
  rt->setInstanceCreationTime(CurrentTime().c_str());
  rt->setStructureSetLabel("INTERSLICE");
  rt->setStructureSetDate(CurrentDate().c_str());
  rt->setStructureSetTime(CurrentTime().c_str());

  // Referenced frame of reference -> study -> series -> every image.
  DRTReferencedFrameOfReferenceSequence::Item* for_item = nullptr;
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      rt->getReferencedFrameOfReferenceSequence().addItem(for_item),
      "add the referenced frame of reference"));
  for_item->setFrameOfReferenceUID(frame.c_str());
  DRTRTReferencedStudySequence::Item* study_item = nullptr;
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      for_item->getRTReferencedStudySequence().addItem(study_item),
      "add the referenced study"));
  study_item->setReferencedSOPClassUID(kStudyComponentClass);
  study_item->setReferencedSOPInstanceUID(study.c_str());
  DRTRTReferencedSeriesSequence::Item* series_item = nullptr;
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
      study_item->getRTReferencedSeriesSequence().addItem(series_item),
      "add the referenced series"));
  series_item->setSeriesInstanceUID(referenced.series_instance_uid.c_str());
  for (const std::string& uid : referenced.sop_instance_uids) {
    DRTContourImageSequence::Item* image = nullptr;
    INTERSLICE_RETURN_IF_ERROR(
        CheckRtStruct(series_item->getContourImageSequence().addItem(image),
                      "add a referenced image"));
    image->setReferencedSOPClassUID(referenced.sop_class_uid.c_str());
    image->setReferencedSOPInstanceUID(uid.c_str());
  }

  for (const RoiContours& r : rois) {
    const std::string number = std::to_string(r.roi.number);
    const std::string name =
        r.roi.label.empty() ? absl::StrCat("Label ", number) : r.roi.label;
    DRTStructureSetROISequence::Item* roi = nullptr;
    INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
        rt->getStructureSetROISequence().addItem(roi), "add an ROI"));
    roi->setROINumber(number.c_str());
    roi->setReferencedFrameOfReferenceUID(frame.c_str());
    roi->setROIName(name.substr(0, 64).c_str());
    roi->setROIGenerationAlgorithm("SEMIAUTOMATIC");
    roi->setROIGenerationDescription("interslice fill between key slices");

    DRTROIContourSequence::Item* contours = nullptr;
    INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
        rt->getROIContourSequence().addItem(contours), "add an ROI contour"));
    contours->setReferencedROINumber(number.c_str());
    const std::array<uint8_t, 3> rgb = SegmentRgb(r.roi);
    contours->setROIDisplayColor(
        absl::StrFormat("%d\\%d\\%d", rgb[0], rgb[1], rgb[2]).c_str());
    int contour_number = 0;
    for (const auto& [k, polygons] : r.slices) {
      for (const auto& polygon : polygons) {
        DRTContourSequence::Item* contour = nullptr;
        INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(
            contours->getContourSequence().addItem(contour), "add a contour"));
        contour->setContourNumber(std::to_string(++contour_number).c_str());
        contour->setContourGeometricType("CLOSED_PLANAR");
        contour->setNumberOfContourPoints(
            std::to_string(polygon.size()).c_str());
        std::vector<std::string> values;
        values.reserve(3 * polygon.size());
        for (const auto& v : polygon) {
          const Vec3 p =
              grid.IndexToPhysical({v[0], v[1], static_cast<double>(k)});
          for (int c = 0; c < 3; ++c)
            values.push_back(FormatDecimalString(p[c]));
        }
        INTERSLICE_RETURN_IF_ERROR(
            CheckRtStruct(contour->setContourData(
                              absl::StrJoin(values, "\\").c_str(), OFFalse),
                          "set ContourData"));
        DRTContourImageSequence::Item* image = nullptr;
        INTERSLICE_RETURN_IF_ERROR(
            CheckRtStruct(contour->getContourImageSequence().addItem(image),
                          "add a contour image"));
        image->setReferencedSOPClassUID(referenced.sop_class_uid.c_str());
        image->setReferencedSOPInstanceUID(
            referenced.sop_instance_uids[static_cast<size_t>(k)].c_str());
      }
    }

    DRTRTROIObservationsSequence::Item* observation = nullptr;
    INTERSLICE_RETURN_IF_ERROR(
        CheckRtStruct(rt->getRTROIObservationsSequence().addItem(observation),
                      "add an ROI observation"));
    observation->setObservationNumber(number.c_str());
    observation->setReferencedROINumber(number.c_str());
    observation->setRTROIInterpretedType("");
    observation->setROIInterpreter("");
  }

  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  INTERSLICE_RETURN_IF_ERROR(CheckRtStruct(rt->write(ds), "encode"));
  CopyPatientStudyFrameOfReference(src, identity, ds);
  return SaveFileAtomically(file, path);
}

}  // namespace interslice
