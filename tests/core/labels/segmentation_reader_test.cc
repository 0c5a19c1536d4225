// RTSTRUCT reading (DICOM SEG reading is tested end to end in
// tests/client/fill_cli_test.cc with the SEG `interslice run --seg` writes).
#include "core/labels/segmentation_reader.h"

#include <unistd.h>

#include <filesystem>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

using ::testing::HasSubstr;

constexpr char kFrame[] = "1.2.826.0.1.3680043.2.1125.1";

struct Contour {
  int roi;
  std::vector<std::array<double, 2>> points;
  double z;
};

// A minimal RT Structure Set: ROIs (number, name) and planar contours.
std::string WriteRtStruct(const std::string& name,
                          const std::vector<std::pair<int, std::string>>& rois,
                          const std::vector<Contour>& contours,
                          const std::string& frame = kFrame) {
  DcmFileFormat file;
  DcmDataset* d = file.getDataset();
  d->putAndInsertString(DCM_SOPClassUID, UID_RTStructureSetStorage);
  d->putAndInsertString(DCM_SOPInstanceUID, "1.2.826.0.1.3680043.2.1125.2");
  d->putAndInsertString(DCM_Modality, "RTSTRUCT");
  d->putAndInsertString(DCM_StructureSetLabel, "test");
  for (const auto& [number, roi_name] : rois) {
    DcmItem* item = nullptr;
    d->findOrCreateSequenceItem(DCM_StructureSetROISequence, item, -2);
    item->putAndInsertString(DCM_ROINumber, std::to_string(number).c_str());
    item->putAndInsertString(DCM_ROIName, roi_name.c_str());
    item->putAndInsertString(DCM_ReferencedFrameOfReferenceUID, frame.c_str());
    item->putAndInsertString(DCM_ROIGenerationAlgorithm, "MANUAL");
    DcmItem* roi = nullptr;
    d->findOrCreateSequenceItem(DCM_ROIContourSequence, roi, -2);
    roi->putAndInsertString(DCM_ReferencedROINumber,
                            std::to_string(number).c_str());
    roi->putAndInsertString(DCM_ROIDisplayColor, "255\\0\\0");
    for (const Contour& c : contours) {
      if (c.roi != number) continue;
      DcmItem* contour = nullptr;
      roi->findOrCreateSequenceItem(DCM_ContourSequence, contour, -2);
      contour->putAndInsertString(DCM_ContourGeometricType, "CLOSED_PLANAR");
      contour->putAndInsertString(DCM_NumberOfContourPoints,
                                  std::to_string(c.points.size()).c_str());
      std::vector<std::string> values;
      for (const auto& p : c.points) {
        values.push_back(absl::StrCat(p[0]));
        values.push_back(absl::StrCat(p[1]));
        values.push_back(absl::StrCat(c.z));
      }
      contour->putAndInsertString(DCM_ContourData,
                                  absl::StrJoin(values, "\\").c_str());
    }
  }
  const std::string path =
      (std::filesystem::temp_directory_path() /
       absl::StrCat("rtstruct_test_", getpid(), "_", name, ".dcm"))
          .string();
  EXPECT_TRUE(file.saveFile(path.c_str(), EXS_LittleEndianExplicit).good());
  return path;
}

ReferenceSeries Reference() {
  ReferenceSeries r;
  r.grid.size = {20, 20, 5};
  r.grid.spacing = {1, 1, 2};
  r.grid.origin = {-5, -5, 0};
  r.frame_of_reference_uid = kFrame;
  return r;
}

std::vector<std::array<double, 2>> Square(double x0, double y0, double x1,
                                          double y1) {
  return {{x0, y0}, {x1, y0}, {x1, y1}, {x0, y1}};
}

TEST(RtStructTest, PolygonsWithHolesOnTheirSlices) {
  // ROI 4 "ring": a square with a square hole on slice 1 (z = 2 mm) and a
  // second polygon beside it; ROI 9 "cap": a square on slice 3 (z = 6 mm).
  // Patient x = -5 + i, y = -5 + j.
  const std::string path =
      WriteRtStruct("ok", {{4, "ring"}, {9, "cap"}},
                    {{4, Square(-3.5, -3.5, 6.5, 6.5), 2},
                     {4, Square(-0.5, -0.5, 2.5, 2.5), 2},
                     {4, Square(9.5, 9.5, 11.5, 11.5), 2},
                     {9, Square(-1.5, -1.5, 0.5, 0.5), 6}});
  absl::StatusOr<SegmentationInput> in = ReadDicomLabels(path, Reference());
  std::filesystem::remove(path);
  ASSERT_TRUE(in.ok()) << in.status();
  EXPECT_TRUE(in->rtstruct);
  ASSERT_EQ(in->segments.size(), 2u);
  EXPECT_EQ(in->segments[0].label, "ring");
  ASSERT_TRUE(in->segments[0].rgb.has_value());
  EXPECT_EQ(*in->segments[0].rgb, (std::array<uint8_t, 3>{255, 0, 0}));
  // The polygons are kept, in index coordinates, for the exact distance.
  ASSERT_EQ(in->contours.polygons.at(4).at(1).size(), 3u);
  EXPECT_EQ(in->contours.polygons.at(4).at(1)[0][0],
            (std::array<double, 2>{1.5, 1.5}));
  EXPECT_EQ(in->contours.Find(9, 3)->size(), 1u);
  EXPECT_EQ(in->contours.Find(9, 1), nullptr);
  const LabelVolume& v = in->labels;
  // Ring: pixels i in [2, 11] minus the hole [5, 7] -> 10 * 10 - 3 * 3.
  int64_t ring = 0, cap = 0;
  for (int64_t j = 0; j < 20; ++j) {
    for (int64_t i = 0; i < 20; ++i) {
      ring += v.at(i, j, 1) == 4;
      cap += v.at(i, j, 3) == 9;
      EXPECT_EQ(v.at(i, j, 0), 0);
      EXPECT_EQ(v.at(i, j, 2), 0);
    }
  }
  EXPECT_EQ(ring, 100 - 9 + 4);
  EXPECT_EQ(cap, 4);
  EXPECT_EQ(v.at(2, 2, 1), 4);
  EXPECT_EQ(v.at(11, 11, 1), 4);
  EXPECT_EQ(v.at(12, 12, 1), 0);
  EXPECT_EQ(v.at(6, 6, 1), 0);  // the hole
  EXPECT_EQ(v.at(15, 15, 1), 4);
  EXPECT_EQ(v.at(4, 4, 3), 9);
}

TEST(RtStructTest, Errors) {
  const ReferenceSeries reference = Reference();
  std::string path =
      WriteRtStruct("off", {{1, "liver"}}, {{1, Square(0, 0, 5, 5), 3.0}});
  EXPECT_THAT(ReadDicomLabels(path, reference).status().message(),
              HasSubstr("ROI 'liver' (1) contour 1 is not on a slice plane"));
  std::filesystem::remove(path);

  path =
      WriteRtStruct("overlap", {{1, "body"}, {2, "liver"}},
                    {{1, Square(-3, -3, 8, 8), 2}, {2, Square(0, 0, 3, 3), 2}});
  EXPECT_THAT(ReadDicomLabels(path, reference).status().message(),
              HasSubstr("ROIs 'body' (1) and 'liver' (2) overlap on slice 1"));
  // Choosing one of them is fine.
  absl::StatusOr<SegmentationInput> liver =
      ReadDicomLabels(path, reference, {2});
  ASSERT_TRUE(liver.ok()) << liver.status();
  EXPECT_EQ(liver->labels.at(6, 6, 1), 2);
  std::filesystem::remove(path);

  path = WriteRtStruct("frame", {{1, "liver"}}, {{1, Square(0, 0, 3, 3), 2}},
                       "1.2.3");
  EXPECT_THAT(ReadDicomLabels(path, reference).status().message(),
              HasSubstr("another frame of reference"));
  std::filesystem::remove(path);

  path = WriteRtStruct("number", {{0, "zero"}}, {});
  EXPECT_THAT(ReadDicomLabels(path, reference).status().message(),
              HasSubstr("1..65535"));
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace interslice
