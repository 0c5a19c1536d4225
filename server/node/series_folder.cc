#include "server/node/series_folder.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "core/common/sha256.h"
#include "nlohmann/json.hpp"
#include "server/node/dataset_scan.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice::server::node {

namespace fs = std::filesystem;

std::string Key(const std::string& called_ae, const std::string& study,
                const std::string& series) {
  Sha256 hash;
  hash.Update(called_ae);
  hash.Update(std::string_view("\0", 1));
  hash.Update(study);
  hash.Update(std::string_view("\0", 1));
  hash.Update(series);
  return HexString(hash.Finish()).substr(0, 32);
}

std::string InstanceName(const std::string& sop_instance_uid) {
  Sha256 hash;
  hash.Update(sop_instance_uid);
  return HexString(hash.Finish()).substr(0, 32) + ".dcm";
}

std::string GetString(DcmItem* item, const DcmTagKey& tag) {
  OFString value;
  if (item->findAndGetOFStringArray(tag, value).good()) {
    return std::string(value.c_str());
  }
  return "";
}

std::optional<SegmentationRef> ReadSegmentationRef(const std::string& dir) {
  std::error_code ec;
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.path().extension() == ".dcm") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  for (const std::string& file : files) {
    DcmFileFormat ff;
    if (ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange,
                            DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
            .bad()) {
      continue;
    }
    DcmDataset* ds = ff.getDataset();
    const std::string sop_class = GetString(ds, DCM_SOPClassUID);
    SegmentationRef ref;
    ref.file = file;
    const std::string own_study = GetString(ds, DCM_StudyInstanceUID);
    if (!own_study.empty()) ref.study_uids.push_back(own_study);
    if (sop_class == UID_SegmentationStorage) {
      DcmItem* series = nullptr;
      if (ds->findAndGetSequenceItem(DCM_ReferencedSeriesSequence, series, 0)
              .good()) {
        ref.series_uid = GetString(series, DCM_SeriesInstanceUID);
      }
    } else if (sop_class == UID_RTStructureSetStorage) {
      DcmItem *frame = nullptr, *study = nullptr, *series = nullptr;
      if (ds->findAndGetSequenceItem(DCM_ReferencedFrameOfReferenceSequence,
                                     frame, 0)
              .good() &&
          frame->findAndGetSequenceItem(DCM_RTReferencedStudySequence, study, 0)
              .good()) {
        const std::string referenced =
            GetString(study, DCM_ReferencedSOPInstanceUID);
        if (!referenced.empty() && referenced != own_study) {
          ref.study_uids.push_back(referenced);
        }
        if (study
                ->findAndGetSequenceItem(DCM_RTReferencedSeriesSequence, series,
                                         0)
                .good()) {
          ref.series_uid = GetString(series, DCM_SeriesInstanceUID);
        }
      }
    } else {
      continue;
    }
    if (ref.series_uid.empty() || ref.study_uids.empty()) return std::nullopt;
    return ref;
  }
  return std::nullopt;
}

// The *.dcm files of `dir`, in name order.
std::vector<std::string> DicomFiles(const std::string& dir) {
  std::error_code ec;
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.path().extension() == ".dcm") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

// The UIDs of a kept instance's header (empty where unreadable).
InstanceIds ReadInstanceIds(const std::string& file) {
  InstanceIds ids;
  DcmFileFormat ff;
  if (ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange,
                          DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
          .bad()) {
    return ids;
  }
  DcmDataset* ds = ff.getDataset();
  ids.study_uid = GetString(ds, DCM_StudyInstanceUID);
  ids.series_uid = GetString(ds, DCM_SeriesInstanceUID);
  ids.sop_instance_uid = GetString(ds, DCM_SOPInstanceUID);
  ids.frame_of_reference_uid = GetString(ds, DCM_FrameOfReferenceUID);
  return ids;
}

// The FrameOfReferenceUID of a held series: its first instance's.
std::string HeldFrameOfReference(const std::string& held) {
  const std::vector<std::string> files = DicomFiles(held);
  return files.empty() ? ""
                       : ReadInstanceIds(files.front()).frame_of_reference_uid;
}

// SHA-256 of a kept instance's data set: the bytes after the meta group,
// as the sender sent them (the meta group is written by our listener and
// names the sender, which may differ for the same instance).
absl::StatusOr<std::string> DatasetSha256(const std::string& path) {
  absl::StatusOr<Part10Meta> meta = ReadPart10Meta(path);
  if (!meta.ok()) return meta.status();
  std::ifstream in(path, std::ios::binary);
  in.seekg(meta->dataset_offset);
  if (!in) return absl::InternalError("cannot read a kept instance");
  Sha256 hash;
  std::vector<char> buffer(1 << 16);
  while (in) {
    in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    hash.Update(std::string_view(buffer.data(), in.gcount()));
  }
  if (in.bad()) return absl::InternalError("cannot read a kept instance");
  return hash.Finish();
}

// A kept series' id: its folder's name under unmatched/, <key>-<unix ms>
// (checked before it becomes part of a path).
bool IsKeptId(const std::string& id) {
  const size_t dash = id.find('-');
  if (dash != 32 || id.size() < 34 || id.size() > 33 + 19) return false;
  for (size_t i = 0; i < id.size(); ++i) {
    const char c = id[i];
    const bool ok = i < 32    ? (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f')
                    : i == 32 ? c == '-'
                              : c >= '0' && c <= '9';
    if (!ok) return false;
  }
  return true;
}

// origin.json of a series folder: the AE titles it was received with.
std::pair<std::string, std::string> ReadOrigin(const std::string& dir) {
  std::ifstream origin(fs::path(dir) / "origin.json");
  nlohmann::json j = nlohmann::json::parse(origin, nullptr, false);
  if (!j.is_object()) return {};
  return {j.value("calling_ae", ""), j.value("called_ae", "")};
}

std::string JobOrigin(const std::string& calling_ae,
                      const std::string& called_ae, const Rule& rule) {
  return absl::StrCat("dicom:", calling_ae, "->", called_ae, " rule ",
                      rule.name);
}

SeriesFacts ReadSeriesFacts(const std::string& dir) {
  SeriesFacts facts;
  std::vector<double> positions;
  bool first = true;
  std::error_code ec;
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.path().extension() == ".dcm") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  for (const std::string& file : files) {
    DcmFileFormat ff;
    if (ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange,
                            DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
            .bad()) {
      continue;
    }
    DcmDataset* ds = ff.getDataset();
    if (first) {
      first = false;
      const std::string sop_class = GetString(ds, DCM_SOPClassUID);
      facts.segmentation = sop_class == UID_SegmentationStorage ||
                           sop_class == UID_RTStructureSetStorage;
      facts.modality = GetString(ds, DCM_Modality);
      facts.sop_class_uid = sop_class;
      facts.manufacturer = GetString(ds, DCM_Manufacturer);
      facts.image_type = GetString(ds, DCM_ImageType);
      facts.own_result =
          absl::EqualsIgnoreCase(facts.manufacturer, "interslice") &&
          absl::EqualsIgnoreCase(GetString(ds, DCM_ManufacturerModelName),
                                 "interslice");
      facts.series_description = GetString(ds, DCM_SeriesDescription);
      facts.protocol_name = GetString(ds, DCM_ProtocolName);
      facts.body_part = GetString(ds, DCM_BodyPartExamined);
      Float64 thickness = 0;
      if (ds->findAndGetFloat64(DCM_SliceThickness, thickness).good() &&
          std::isfinite(thickness) && thickness > 0) {
        facts.slice_thickness_mm = thickness;
      }
    }
    Sint32 frames = 1;
    if (ds->findAndGetSint32(DCM_NumberOfFrames, frames).bad() || frames < 1) {
      frames = 1;
    }
    facts.slice_count += frames;
    // Classic single-frame images: their position along the slice normal.
    double ipp[3], iop[6];
    bool geometry = frames == 1;
    for (int i = 0; geometry && i < 3; ++i) {
      geometry =
          ds->findAndGetFloat64(DCM_ImagePositionPatient, ipp[i], i).good();
    }
    for (int i = 0; geometry && i < 6; ++i) {
      geometry =
          ds->findAndGetFloat64(DCM_ImageOrientationPatient, iop[i], i).good();
    }
    if (geometry) {
      const double n[3] = {iop[1] * iop[5] - iop[2] * iop[4],
                           iop[2] * iop[3] - iop[0] * iop[5],
                           iop[0] * iop[4] - iop[1] * iop[3]};
      positions.push_back(ipp[0] * n[0] + ipp[1] * n[1] + ipp[2] * n[2]);
    }
  }
  if (positions.size() >= 2) {
    std::sort(positions.begin(), positions.end());
    std::vector<double> gaps;
    for (size_t i = 1; i < positions.size(); ++i) {
      const double gap = positions[i] - positions[i - 1];
      if (gap > 1e-6) gaps.push_back(gap);
    }
    if (!gaps.empty()) {
      std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2,
                       gaps.end());
      facts.slice_spacing_mm = gaps[gaps.size() / 2];
    }
  }
  return facts;
}

std::pair<int64_t, int64_t> CarryInstances(const std::string& from,
                                           const std::string& dir) {
  std::error_code ec;
  int64_t n = 0, bytes = 0;
  for (const auto& f : fs::directory_iterator(from, ec)) {
    if (f.path().extension() != ".dcm") continue;
    const fs::path target = fs::path(dir) / f.path().filename();
    if (fs::exists(target, ec)) continue;  // a newer copy arrived
    std::error_code link;
    fs::create_hard_link(f.path(), target, link);
    if (link) fs::copy_file(f.path(), target, link);
    if (link) continue;
    ++n;
    bytes += static_cast<int64_t>(fs::file_size(target, ec));
  }
  return {n, bytes};
}

}  // namespace interslice::server::node
