#include "core/labels/segmentation_reader.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <set>
#include <string>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmfg/fgplanor.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmfg/fgseg.h"
#include "dcmtk/dcmrt/drtstrct.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"
#include "dcmtk/dcmseg/segutils.h"

namespace interslice {
namespace {

std::string BaseName(const std::string& path) {
  const size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? path : path.substr(slash + 1);
}

CodedConcept Concept(CodeSequenceMacro& code) {
  CodedConcept c;
  OFString v;
  if (code.getCodeValue(v).good()) c.value = v.c_str();
  if (code.getCodingSchemeDesignator(v).good()) c.scheme = v.c_str();
  if (code.getCodeMeaning(v).good()) c.meaning = v.c_str();
  return c;
}

}  // namespace

bool LooksLikeDicomFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  char magic[132];
  if (!in.read(magic, sizeof(magic))) return false;
  return std::memcmp(magic + 128, "DICM", 4) == 0;
}

absl::StatusOr<SegmentationInput> ReadDicomSegmentation(
    const std::string& path, const ReferenceSeries& reference,
    const std::vector<int>& only) {
  const std::string name = BaseName(path);
  const auto error = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("SEG ", name, ": ", what));
  };
  if (absl::Status s = reference.grid.Validate(); !s.ok()) return s;

  // The references first, from the plain dataset (dcmseg does not expose
  // the Referenced Series Sequence).
  DcmFileFormat file;
  if (OFCondition c = file.loadFile(path.c_str()); c.bad()) {
    return error(absl::StrCat("cannot read: ", c.text()));
  }
  DcmDataset* dataset = file.getDataset();
  OFString sop_class;
  dataset->findAndGetOFString(DCM_SOPClassUID, sop_class);
  if (sop_class != UID_SegmentationStorage) {
    return error("not a DICOM Segmentation (SOPClassUID " +
                 std::string(sop_class.c_str()) + ")");
  }
  OFString frame_of_reference;
  dataset->findAndGetOFString(DCM_FrameOfReferenceUID, frame_of_reference);
  if (!reference.frame_of_reference_uid.empty() &&
      frame_of_reference.c_str() != reference.frame_of_reference_uid) {
    return error(
        "its FrameOfReferenceUID is not the reference series' (it was drawn "
        "on another scan or registration)");
  }
  DcmItem* referenced = nullptr;
  if (dataset
          ->findAndGetSequenceItem(DCM_ReferencedSeriesSequence, referenced, 0)
          .good() &&
      referenced != nullptr && !reference.series_instance_uid.empty()) {
    OFString series;
    referenced->findAndGetOFString(DCM_SeriesInstanceUID, series);
    if (!series.empty() && series.c_str() != reference.series_instance_uid) {
      return error(
          "it references another series than the reference series "
          "(ReferencedSeriesSequence)");
    }
  }

  DcmSegmentation* raw = nullptr;
  if (OFCondition c = DcmSegmentation::loadDataset(*dataset, raw); c.bad()) {
    return error(absl::StrCat("dcmseg cannot read it: ", c.text()));
  }
  std::unique_ptr<DcmSegmentation> seg(raw);
  Uint16 rows = 0, columns = 0;
  dataset->findAndGetUint16(DCM_Rows, rows);
  dataset->findAndGetUint16(DCM_Columns, columns);
  const Grid& g = reference.grid;
  if (rows != g.size[1] || columns != g.size[0]) {
    return error(absl::StrFormat(
        "frames are %d x %d pixels but the reference series' slices %d x %d",
        columns, rows, g.size[0], g.size[1]));
  }

  SegmentationInput out;
  out.fractional = seg->getSegmentationType() == DcmSegTypes::ST_FRACTIONAL;
  Uint16 max_fraction = 255;
  if (out.fractional) {
    dataset->findAndGetUint16(DCM_MaximumFractionalValue, max_fraction);
    if (max_fraction == 0) return error("MaximumFractionalValue is 0");
  }
  const size_t segments = seg->getNumberOfSegments();
  if (segments > 65535) return error("more than 65535 segments");
  for (size_t n = 1; n <= segments; ++n) {
    DcmSegment* segment = seg->getSegment(n);
    if (segment == nullptr) continue;
    LabelSegment d;
    d.number = static_cast<int>(n);
    OFString label;
    if (segment->getSegmentLabel(label).good()) d.label = label.c_str();
    Uint16 l = 0, a = 0, b = 0;
    if (segment->getRecommendedDisplayCIELabValue(l, a, b).good()) {
      d.cielab = std::array<uint16_t, 3>{l, a, b};
    }
    d.category = Concept(segment->getSegmentedPropertyCategoryCode());
    d.type = Concept(segment->getSegmentedPropertyTypeCode());
    out.segments.push_back(std::move(d));
  }

  out.labels.grid = g;
  out.labels.data.assign(g.VoxelCount(), 0);
  const int64_t plane = g.SliceVoxelCount();
  FGInterface& groups = seg->getFunctionalGroups();
  out.frames = static_cast<int64_t>(seg->getNumberOfFrames());
  const Vec3 row_axis = g.Axis(0), column_axis = g.Axis(1);
  for (int64_t f = 0; f < out.frames; ++f) {
    const Uint32 frame = static_cast<Uint32>(f);
    auto* position = dynamic_cast<FGPlanePosPatient*>(
        groups.get(frame, DcmFGTypes::EFG_PLANEPOSPATIENT));
    auto* segmentation = dynamic_cast<FGSegmentation*>(
        groups.get(frame, DcmFGTypes::EFG_SEGMENTATION));
    Float64 x = 0, y = 0, z = 0;
    Uint16 number = 0;
    if (position == nullptr ||
        position->getImagePositionPatient(x, y, z).bad()) {
      return error(
          absl::StrFormat("frame %d has no ImagePositionPatient", f + 1));
    }
    if (segmentation == nullptr ||
        segmentation->getReferencedSegmentNumber(number).bad() || number == 0 ||
        number > segments) {
      return error(absl::StrFormat(
          "frame %d has no valid ReferencedSegmentNumber", f + 1));
    }
    auto* orientation = dynamic_cast<FGPlaneOrientationPatient*>(
        groups.get(frame, DcmFGTypes::EFG_PLANEORIENTPATIENT));
    if (orientation != nullptr) {
      Float64 o[6];
      if (orientation
              ->getImageOrientationPatient(o[0], o[1], o[2], o[3], o[4], o[5])
              .good()) {
        for (int c = 0; c < 3; ++c) {
          if (std::abs(o[c] - row_axis[c]) > 1e-3 ||
              std::abs(o[3 + c] - column_axis[c]) > 1e-3) {
            return error(absl::StrFormat(
                "frame %d: ImageOrientationPatient is not the reference "
                "series'",
                f + 1));
          }
        }
      }
    }
    const Vec3 index = g.PhysicalToIndex({x, y, z});
    const int64_t k = std::llround(index[2]);
    if (std::abs(index[2] - static_cast<double>(k)) > 0.01 || k < 0 ||
        k >= g.size[2]) {
      return error(absl::StrFormat(
          "frame %d (segment %d) is not on a slice of the reference series "
          "(at slice position %.3f)",
          f + 1, number, index[2]));
    }
    if (std::abs(index[0]) > 0.01 || std::abs(index[1]) > 0.01) {
      return error(absl::StrFormat(
          "frame %d (segment %d) is shifted in plane by (%.3f, %.3f) pixels "
          "against the reference series",
          f + 1, number, index[0], index[1]));
    }
    if (!only.empty() &&
        std::find(only.begin(), only.end(), number) == only.end()) {
      continue;
    }
    const DcmIODTypes::Frame* data = seg->getFrame(f);
    if (data == nullptr) {
      return error(absl::StrFormat("frame %d has no pixel data", f + 1));
    }
    std::unique_ptr<DcmIODTypes::Frame> unpacked;
    const Uint8* pixels = data->pixData;
    if (!out.fractional) {
      unpacked.reset(DcmSegUtils::unpackBinaryFrame(data, rows, columns));
      if (unpacked == nullptr ||
          unpacked->length < static_cast<size_t>(plane)) {
        return error(absl::StrFormat("frame %d: bad binary pixel data", f + 1));
      }
      pixels = unpacked->pixData;
    } else if (data->length < static_cast<size_t>(plane)) {
      return error(absl::StrFormat("frame %d: short pixel data", f + 1));
    }
    uint16_t* slice = out.labels.data.data() + k * plane;
    for (int64_t p = 0; p < plane; ++p) {
      const bool set = out.fractional ? 2 * static_cast<int>(pixels[p]) >=
                                            static_cast<int>(max_fraction)
                                      : pixels[p] != 0;
      if (!set) continue;
      if (slice[p] != 0 && slice[p] != number) {
        return error(absl::StrFormat(
            "segments %d and %d overlap on slice %d (pixel %d, %d): a label "
            "map needs one segment per pixel",
            slice[p], number, k, p % g.size[0], p / g.size[0]));
      }
      slice[p] = number;
    }
  }
  return out;
}

absl::StatusOr<SegmentationInput> ReadRtStruct(const std::string& path,
                                               const ReferenceSeries& reference,
                                               const std::vector<int>& only) {
  const std::string name = BaseName(path);
  const auto error = [&](const std::string& what) {
    return absl::InvalidArgumentError(
        absl::StrCat("RTSTRUCT ", name, ": ", what));
  };
  if (absl::Status s = reference.grid.Validate(); !s.ok()) return s;
  DcmFileFormat file;
  if (OFCondition c = file.loadFile(path.c_str()); c.bad()) {
    return error(absl::StrCat("cannot read: ", c.text()));
  }
  DRTStructureSetIOD rt;
  if (OFCondition c = rt.read(*file.getDataset()); c.bad()) {
    return error(absl::StrCat("dcmrt cannot read it: ", c.text()));
  }
  const Grid& g = reference.grid;
  SegmentationInput out;
  out.rtstruct = true;
  out.labels.grid = g;
  out.labels.data.assign(g.VoxelCount(), 0);

  // ROI number -> name, after the frame of reference check.
  std::map<int, std::string> names;
  DRTStructureSetROISequence& rois = rt.getStructureSetROISequence();
  for (size_t n = 0; n < rois.getNumberOfItems(); ++n) {
    DRTStructureSetROISequence::Item& item = rois.getItem(n);
    OFString number_text, roi_name, frame;
    item.getROINumber(number_text);
    item.getROIName(roi_name);
    item.getReferencedFrameOfReferenceUID(frame);
    int number = 0;
    if (!absl::SimpleAtoi(number_text.c_str(), &number) || number < 1 ||
        number > 65535) {
      return error(absl::StrCat("ROI '", roi_name.c_str(), "' has number '",
                                number_text.c_str(),
                                "'; labels need 1..65535"));
    }
    if (!reference.frame_of_reference_uid.empty() && !frame.empty() &&
        frame.c_str() != reference.frame_of_reference_uid) {
      return error(absl::StrCat(
          "ROI '", roi_name.c_str(), "' (", number,
          ") is in another frame of reference than the reference series"));
    }
    names[number] = roi_name.c_str();
  }

  // The reference's images, for counting the references that name none.
  std::set<std::string> images;
  if (reference.image_sop_instance_uids.has_value()) {
    images.insert(reference.image_sop_instance_uids->begin(),
                  reference.image_sop_instance_uids->end());
  }

  const int64_t plane = g.SliceVoxelCount();
  DRTROIContourSequence& contours = rt.getROIContourSequence();
  for (size_t n = 0; n < contours.getNumberOfItems(); ++n) {
    DRTROIContourSequence::Item& roi = contours.getItem(n);
    Sint32 number = 0;
    if (roi.getReferencedROINumber(number).bad() || number < 1 ||
        number > 65535) {
      return error(absl::StrFormat(
          "ROI contour item %d has no valid ReferencedROINumber", n + 1));
    }
    if (!only.empty() &&
        std::find(only.begin(), only.end(), number) == only.end()) {
      continue;
    }
    const std::string roi_name =
        names.count(number) ? names[number] : absl::StrCat("#", number);
    LabelSegment d;
    d.number = number;
    d.label = roi_name;
    Sint32 rgb[3];
    if (roi.getROIDisplayColor(rgb[0], 0).good() &&
        roi.getROIDisplayColor(rgb[1], 1).good() &&
        roi.getROIDisplayColor(rgb[2], 2).good()) {
      d.rgb = std::array<uint8_t, 3>{
          static_cast<uint8_t>(std::clamp(rgb[0], 0, 255)),
          static_cast<uint8_t>(std::clamp(rgb[1], 0, 255)),
          static_cast<uint8_t>(std::clamp(rgb[2], 0, 255))};
    }
    out.segments.push_back(d);
    // Polygons per slice, in continuous in-plane index coordinates.
    std::map<int64_t, std::vector<std::vector<std::array<double, 2>>>> slices;
    DRTContourSequence& sequence = roi.getContourSequence();
    for (size_t c = 0; c < sequence.getNumberOfItems(); ++c) {
      DRTContourSequence::Item& contour = sequence.getItem(c);
      OFString type;
      contour.getContourGeometricType(type);
      if (type != "CLOSED_PLANAR") continue;
      if (reference.image_sop_instance_uids.has_value()) {
        DRTContourImageSequence& refs = contour.getContourImageSequence();
        for (size_t r = 0; r < refs.getNumberOfItems(); ++r) {
          OFString uid;
          refs.getItem(r).getReferencedSOPInstanceUID(uid);
          ++out.image_references;
          if (images.count(uid.c_str()) == 0) ++out.unresolved_image_references;
        }
      }
      OFVector<Float64> data;
      contour.getContourData(data);
      if (data.size() < 9 || data.size() % 3 != 0) {
        return error(
            absl::StrFormat("ROI '%s' (%d) contour %d has fewer than 3 points",
                            roi_name, number, c + 1));
      }
      std::vector<std::array<double, 2>> polygon;
      int64_t k = -1;
      for (size_t p = 0; p < data.size(); p += 3) {
        const Vec3 index =
            g.PhysicalToIndex({data[p], data[p + 1], data[p + 2]});
        const int64_t pk = std::llround(index[2]);
        if (std::abs(index[2] - static_cast<double>(pk)) > 0.05 || pk < 0 ||
            pk >= g.size[2] || (k >= 0 && pk != k)) {
          return error(absl::StrFormat(
              "ROI '%s' (%d) contour %d is not on a slice plane of the "
              "reference series (point %d at slice position %.3f)",
              roi_name, number, c + 1, p / 3 + 1, index[2]));
        }
        k = pk;
        polygon.push_back({index[0], index[1]});
      }
      slices[k].push_back(std::move(polygon));
    }
    // Kept for the exact polygon distance of the fill (polygon_distance.h).
    for (const auto& [k, polygons] : slices) {
      auto& kept = out.contours.polygons[number][k];
      kept.insert(kept.end(), polygons.begin(), polygons.end());
    }
    // Even-odd scanline fill of the pixel centres (x = i, y = j).
    for (const auto& [k, polygons] : slices) {
      uint16_t* slice = out.labels.data.data() + k * plane;
      std::vector<double> crossings;
      for (int64_t j = 0; j < g.size[1]; ++j) {
        const double y = static_cast<double>(j);
        crossings.clear();
        for (const auto& polygon : polygons) {
          for (size_t e = 0; e < polygon.size(); ++e) {
            const auto& a = polygon[e];
            const auto& b = polygon[(e + 1) % polygon.size()];
            // Half-open rule: an edge counts when y is in [min, max).
            if ((a[1] <= y) != (b[1] <= y)) {
              crossings.push_back(a[0] +
                                  (y - a[1]) / (b[1] - a[1]) * (b[0] - a[0]));
            }
          }
        }
        std::sort(crossings.begin(), crossings.end());
        for (size_t c = 0; c + 1 < crossings.size(); c += 2) {
          const int64_t i0 = std::max<int64_t>(
              0, static_cast<int64_t>(std::ceil(crossings[c])));
          const int64_t i1 = std::min<int64_t>(
              g.size[0] - 1,
              static_cast<int64_t>(std::ceil(crossings[c + 1])) - 1);
          for (int64_t i = i0; i <= i1; ++i) {
            uint16_t& v = slice[i + g.size[0] * j];
            if (v != 0 && v != number) {
              return error(absl::StrFormat(
                  "ROIs '%s' (%d) and '%s' (%d) overlap on slice %d: choose "
                  "non-overlapping ROIs with --labels",
                  names.count(v) ? names[v] : "?", v, roi_name, number, k));
            }
            v = static_cast<uint16_t>(number);
          }
        }
      }
    }
  }
  return out;
}

absl::StatusOr<SegmentationInput> ReadDicomLabels(
    const std::string& path, const ReferenceSeries& reference,
    const std::vector<int>& only) {
  DcmFileFormat file;
  OFString sop_class;
  if (file.loadFile(path.c_str(), EXS_Unknown, EGL_noChange, 4096).good()) {
    file.getDataset()->findAndGetOFString(DCM_SOPClassUID, sop_class);
  }
  if (sop_class == UID_RTStructureSetStorage) {
    return ReadRtStruct(path, reference, only);
  }
  if (sop_class == UID_SegmentationStorage) {
    return ReadDicomSegmentation(path, reference, only);
  }
  return absl::InvalidArgumentError(
      absl::StrCat(BaseName(path),
                   " is a DICOM file but neither a Segmentation nor an "
                   "RT Structure Set (SOPClassUID '",
                   sop_class.c_str(), "')"));
}

}  // namespace interslice
