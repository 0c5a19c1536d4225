// WriteLabelSegmentation: a multi-segment binary DICOM SEG of a label map
// (DCMTK dcmseg).
#include "core/dicom_out/label_segmentation.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmiod/cielabutil.h"
#include "dcmtk/dcmiod/iodmacro.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"

namespace interslice {
namespace {

using dicom_out_internal::AddSegmentationFrame;
using dicom_out_internal::CheckReferencedSeries;
using dicom_out_internal::CreateBinarySegmentation;
using dicom_out_internal::LoadSourceHeader;
using dicom_out_internal::SaveSegmentation;
using dicom_out_internal::ValidateOutputGrid;

absl::Status Check(const OFCondition& cond, const std::string& what) {
  if (cond.good()) return absl::OkStatus();
  return absl::InternalError(
      absl::StrCat("DICOM SEG: cannot ", what, ": ", cond.text()));
}

// HSV (h in [0, 1), s, v in [0, 1]) to RGB in [0, 1] (Foley et al.,
// "Computer Graphics", 2nd ed., sec. 13.3.4).
std::array<double, 3> HsvToRgb(double h, double s, double v) {
  const double h6 = h * 6;
  const int sector = static_cast<int>(std::floor(h6)) % 6;
  const double f = h6 - std::floor(h6);
  const double p = v * (1 - s), q = v * (1 - s * f), t = v * (1 - s * (1 - f));
  switch (sector) {
    case 0:
      return {v, t, p};
    case 1:
      return {q, v, p};
    case 2:
      return {p, v, t};
    case 3:
      return {p, q, v};
    case 4:
      return {t, p, v};
    default:
      return {v, p, q};
  }
}

CodeSequenceMacro Code(const CodedConcept& c) {
  return CodeSequenceMacro(c.value.c_str(), c.scheme.c_str(),
                           c.meaning.c_str());
}

}  // namespace

LabelSegment DefaultLabelSegment(int label) {
  LabelSegment s;
  s.number = label;
  s.label = absl::StrCat("Label ", label);
  // Hues one golden angle apart never repeat and keep neighbours apart.
  const double hue = std::fmod(0.61803398875 * label, 1.0);
  const std::array<double, 3> rgb = HsvToRgb(hue, 0.65, 0.95);
  s.rgb =
      std::array<uint8_t, 3>{static_cast<uint8_t>(std::lround(255 * rgb[0])),
                             static_cast<uint8_t>(std::lround(255 * rgb[1])),
                             static_cast<uint8_t>(std::lround(255 * rgb[2]))};
  s.category = {"85756007", "SCT", "Tissue"};
  s.type = {"85756007", "SCT", "Tissue"};
  return s;
}

namespace dicom_out_internal {

std::array<uint16_t, 3> RgbToDicomCieLab(const std::array<uint8_t, 3>& rgb) {
  double l = 0, a = 0, b = 0;
  IODCIELabUtil::rgb2DicomLab(l, a, b, rgb[0] / 255.0, rgb[1] / 255.0,
                              rgb[2] / 255.0);
  const auto clamp = [](double v) {
    return static_cast<uint16_t>(std::clamp(std::lround(v), 0L, 65535L));
  };
  return {clamp(l), clamp(a), clamp(b)};
}

}  // namespace dicom_out_internal

std::array<uint16_t, 3> SegmentCieLab(const LabelSegment& segment) {
  if (segment.cielab.has_value()) return *segment.cielab;
  return dicom_out_internal::RgbToDicomCieLab(
      segment.rgb.has_value() ? *segment.rgb
                              : *DefaultLabelSegment(segment.number).rgb);
}

std::array<uint8_t, 3> SegmentRgb(const LabelSegment& segment) {
  if (segment.rgb.has_value()) return *segment.rgb;
  if (!segment.cielab.has_value()) {
    return *DefaultLabelSegment(segment.number).rgb;
  }
  double r = 0, g = 0, b = 0;
  IODCIELabUtil::dicomLab2RGB(r, g, b, (*segment.cielab)[0],
                              (*segment.cielab)[1], (*segment.cielab)[2]);
  const auto clamp = [](double v) {
    return static_cast<uint8_t>(std::clamp(std::lround(255 * v), 0L, 255L));
  };
  return {clamp(r), clamp(g), clamp(b)};
}

absl::StatusOr<DerivedObjectIdentity> ReferencedImagesOfSource(
    const DicomSeries& source) {
  DerivedObjectIdentity images;
  images.series_instance_uid = source.series_instance_uid;
  images.sop_class_uid = source.sop_class_uid;
  images.study_instance_uid = source.study_instance_uid;
  images.frame_of_reference_uid = source.frame_of_reference_uid;
  std::set<std::string> seen;
  for (size_t k = 0; k < source.slices.size(); ++k) {
    const std::string& uid = source.slices[k].sop_instance_uid;
    if (uid.empty()) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "reference slice %d has no SOPInstanceUID: a DICOM output cannot "
          "reference it",
          k));
    }
    if (!seen.insert(uid).second) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "reference slice %d is a frame of an image that holds other slices "
          "too (multi-frame): its slices cannot be referenced one image each",
          k));
    }
    images.sop_instance_uids.push_back(uid);
  }
  // A frame that names image k is placed where image k is: only when every
  // image lies on its slot of the regular grid the outputs are written on.
  // The reader's grid is regular and orthogonal; a series with uneven gaps
  // or a gantry tilt has images elsewhere (their true positions), and frames
  // on the grid naming them would be drawn displaced by viewers that place
  // frames by reference.
  const Grid& grid = source.image.grid;
  if (grid.size[2] != static_cast<int64_t>(source.slices.size())) {
    return absl::InvalidArgumentError(
        absl::StrFormat("the reference grid has %d slices for %d images",
                        grid.size[2], source.slices.size()));
  }
  const double tolerance_mm =
      0.01 + 0.01 * std::min(grid.spacing[0], grid.spacing[1]);
  for (size_t k = 0; k < source.slices.size(); ++k) {
    const Vec3 slot = grid.IndexToPhysical({0.0, 0.0, static_cast<double>(k)});
    const Vec3& at = source.slices[k].image_position;
    const double off =
        std::hypot(at[0] - slot[0], at[1] - slot[1], at[2] - slot[2]);
    if (off > tolerance_mm) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "reference slice %d lies %.3f mm from its place on the regular "
          "grid (uneven gaps or gantry tilt): its image cannot be referenced "
          "as the frame's",
          k, off));
    }
  }
  if (images.series_instance_uid.empty() || images.sop_class_uid.empty()) {
    return absl::InvalidArgumentError(
        "the reference series has no SeriesInstanceUID or SOPClassUID: a "
        "DICOM output cannot reference it");
  }
  return images;
}

absl::Status WriteLabelSegmentation(const DicomSeries& source,
                                    const Volume<uint16_t>& labels,
                                    const std::vector<LabelSegment>& segments,
                                    const DerivedObjectIdentity& identity,
                                    const DerivedObjectIdentity& referenced,
                                    const DicomWriteOptions& options,
                                    const std::string& path) {
  const Grid& grid = labels.grid;
  INTERSLICE_RETURN_IF_ERROR(
      ValidateOutputGrid(source, grid, labels.data.size(), "label map"));
  INTERSLICE_RETURN_IF_ERROR(
      CheckReferencedSeries(identity, referenced, grid, "segmentation"));

  // Labels present and, per label, the slices holding it.
  const int64_t nx = grid.size[0], ny = grid.size[1], nz = grid.size[2];
  const int64_t plane = nx * ny;
  std::map<int, std::vector<int64_t>> slices_of;
  for (int64_t k = 0; k < nz; ++k) {
    std::vector<bool> seen(65536, false);
    const uint16_t* s = labels.data.data() + k * plane;
    for (int64_t p = 0; p < plane; ++p) seen[s[p]] = true;
    for (int l = 1; l < 65536; ++l) {
      if (seen[l]) slices_of[l].push_back(k);
    }
  }
  if (slices_of.empty()) {
    return absl::InvalidArgumentError(
        "label map: no voxel holds a label, there is no segment to write");
  }
  if (slices_of.size() > 65535) {
    return absl::InvalidArgumentError("label map: more than 65535 labels");
  }

  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> source_file,
                              LoadSourceHeader(source));
  DcmDataset& src = *source_file->getDataset();
  INTERSLICE_ASSIGN_OR_RETURN(
      std::unique_ptr<DcmSegmentation> seg,
      CreateBinarySegmentation(source, grid, identity, options));

  // Segments, in ascending label order.
  std::map<int, Uint16> segment_of;
  for (const auto& entry : slices_of) {
    const int label = entry.first;
    LabelSegment d = DefaultLabelSegment(label);
    for (const LabelSegment& s : segments) {
      if (s.number != label) continue;
      if (!s.label.empty()) d.label = s.label;
      d.cielab = s.cielab;
      d.rgb = s.rgb.has_value() || s.cielab.has_value() ? s.rgb : d.rgb;
      if (!s.category.value.empty() && !s.category.scheme.empty() &&
          !s.category.meaning.empty()) {
        d.category = s.category;
      }
      if (!s.type.value.empty() && !s.type.scheme.empty() &&
          !s.type.meaning.empty()) {
        d.type = s.type;
      }
    }
    const std::string segment_label = d.label.substr(0, 64);
    DcmSegment* raw_segment = nullptr;
    INTERSLICE_RETURN_IF_ERROR(Check(
        DcmSegment::create(raw_segment, segment_label.c_str(), Code(d.category),
                           Code(d.type), DcmSegTypes::SAT_SEMIAUTOMATIC,
                           "interslice fill"),
        absl::StrFormat("create the segment of label %d", label)));
    const std::array<uint16_t, 3> lab = SegmentCieLab(d);
    raw_segment->setRecommendedDisplayCIELabValue(lab[0], lab[1], lab[2]);
    Uint16 number = 0;
    const OFCondition cond = seg->addSegment(raw_segment, number);
    if (cond.bad()) delete raw_segment;  // ownership passes only on success
    INTERSLICE_RETURN_IF_ERROR(
        Check(cond, absl::StrFormat("add the segment of label %d", label)));
    segment_of[label] = number;
  }

  std::vector<Uint8> frame(static_cast<size_t>(plane));
  for (const auto& [label, slices] : slices_of) {
    const Uint16 number = segment_of[label];
    for (int64_t k : slices) {
      const uint16_t* s = labels.data.data() + k * plane;
      for (int64_t p = 0; p < plane; ++p) frame[p] = s[p] == label;
      INTERSLICE_RETURN_IF_ERROR(
          AddSegmentationFrame(*seg, grid, k, number, referenced,
                               options.derivation_description, frame.data()));
    }
  }
  return SaveSegmentation(*seg, src, identity, referenced, path);
}

}  // namespace interslice
