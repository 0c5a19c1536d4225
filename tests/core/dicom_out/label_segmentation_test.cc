// The fill's DICOM writers (label_segmentation.h, rtstruct.h) on the real
// 4-slice CT: segment numbering and descriptions, references, colours, and
// every INVALID_ARGUMENT. End to end through `interslice fill` (dciodvfy,
// read back by core/labels) in tests/client/fill_cli_test.cc.
#include "core/dicom_out/label_segmentation.h"

#include <filesystem>
#include <set>
#include <string>
#include <vector>

#include "core/dicom/series_reader.h"
#include "core/dicom_out/rtstruct.h"
#include "core/labels/segmentation_reader.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/core/dicom_out/dicom_test_util.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";

TEST(LabelSegmentTest, DefaultsAreDistinctAndColoursConvert) {
  std::set<std::array<uint8_t, 3>> colours;
  for (int label = 1; label <= 20; ++label) {
    const LabelSegment s = DefaultLabelSegment(label);
    EXPECT_EQ(s.label, "Label " + std::to_string(label));
    EXPECT_EQ(s.category.value, "85756007");
    EXPECT_EQ(s.type.scheme, "SCT");
    ASSERT_TRUE(s.rgb.has_value());
    colours.insert(*s.rgb);
    // RGB -> DICOM CIELab -> RGB comes back within rounding.
    LabelSegment lab_only;
    lab_only.number = label;
    lab_only.cielab = SegmentCieLab(s);
    const std::array<uint8_t, 3> back = SegmentRgb(lab_only);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(back[c], (*s.rgb)[c], 2) << label;
  }
  EXPECT_EQ(colours.size(), 20u);
}

TEST(LabelSegmentTest, ReferencedImagesNeedOneInstancePerSlice) {
  DicomSeries source;
  source.series_instance_uid = "1.2.3";
  source.sop_class_uid = "1.2.840.10008.5.1.4.1.1.2";
  source.image.grid.size = {4, 4, 2};
  source.image.grid.spacing = {0.5, 0.5, 5};
  source.image.grid.origin = {-1, 2, 10};
  source.slices.resize(2);
  source.slices[0].sop_instance_uid = "1.2.3.1";
  source.slices[1].sop_instance_uid = "1.2.3.2";
  source.slices[0].image_position = {-1, 2, 10};
  source.slices[1].image_position = {-1, 2, 15.004};  // within rounding
  absl::StatusOr<DerivedObjectIdentity> images =
      ReferencedImagesOfSource(source);
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_EQ(images->sop_instance_uids,
            (std::vector<std::string>{"1.2.3.1", "1.2.3.2"}));
  // An image off its slot of the regular grid (an uneven gap) cannot be the
  // image a frame on the grid names.
  source.slices[1].image_position = {-1, 2, 16.2};
  EXPECT_THAT(ReferencedImagesOfSource(source).status().message(),
              HasSubstr("reference slice 1 lies 1.200 mm from its place"));
  source.slices[1].image_position = {-1, 2, 15};
  source.slices[1].sop_instance_uid = "1.2.3.1";  // two frames of one image
  EXPECT_THAT(ReferencedImagesOfSource(source).status().message(),
              HasSubstr("multi-frame"));
  source.slices[1].sop_instance_uid = "";
  EXPECT_THAT(ReferencedImagesOfSource(source).status().message(),
              HasSubstr("no SOPInstanceUID"));
}

// The real tilted CT: the reader resamples it onto an orthogonal grid, so its
// images are not where the grid's slices are and the fill's DICOM outputs
// must lie on a derived intensity series; the regular thick CT's images are
// referenced directly (LabelWritersTest's fixture).
TEST(LabelSegmentTest, TiltedSeriesImagesAreNotReferencedAsGridSlices) {
  QuietDicomToolkitLogging();
  absl::StatusOr<DicomSeries> tilted = ReadDicomSeries(
      {(fs::path(::interslice::testing::TestDataDir()) / "ct-tilt").string()},
      {}, {});
  ASSERT_TRUE(tilted.ok()) << tilted.status();
  ASSERT_NE(tilted->gantry_tilt_degrees, 0);
  EXPECT_THAT(ReferencedImagesOfSource(*tilted).status().message(),
              HasSubstr("gantry tilt"));
}

class LabelWritersTest : public ::testing::Test {
 protected:
  void SetUp() override {
    QuietDicomToolkitLogging();
    absl::StatusOr<DicomSeries> series =
        ReadDicomSeries({kThick.string()}, {}, {});
    ASSERT_TRUE(series.ok()) << series.status();
    source_ = *std::move(series);
    absl::StatusOr<DerivedObjects> objects =
        PlanDerivedObjects(source_, source_.image.grid.size[2], {});
    ASSERT_TRUE(objects.ok()) << objects.status();
    objects_ = *std::move(objects);
    absl::StatusOr<DerivedObjectIdentity> images =
        ReferencedImagesOfSource(source_);
    ASSERT_TRUE(images.ok()) << images.status();
    images_ = *std::move(images);
    labels_.grid = source_.image.grid;
    labels_.data.assign(labels_.grid.VoxelCount(), 0);
  }

  DicomSeries source_;
  DerivedObjects objects_;
  DerivedObjectIdentity images_;
  Volume<uint16_t> labels_;
  interslice::testing::TempDir dir_;
};

TEST_F(LabelWritersTest, SegmentsAreNumberedInLabelOrderWithTheirDescriptions) {
  // Labels 7 and 3 (not 1..N), label 7 described, label 3 not.
  for (int64_t j = 100; j < 120; ++j) {
    for (int64_t i = 100; i < 130; ++i) {
      labels_.at(i, j, 1) = 7;
      labels_.at(i + 50, j, 2) = 3;
    }
  }
  LabelSegment liver;
  liver.number = 7;
  liver.label = "liver";
  liver.rgb = std::array<uint8_t, 3>{200, 30, 30};
  liver.category = {"123037004", "SCT", "Anatomical Structure"};
  liver.type = {"10200004", "SCT", "Liver"};
  const std::string path = (dir_.path() / "seg.dcm").string();
  ASSERT_TRUE(WriteLabelSegmentation(source_, labels_, {liver},
                                     objects_.segmentation, images_, {}, path)
                  .ok());
  interslice::testing::ExpectValidIod({path});
  absl::StatusOr<SegmentationInput> back = ReadDicomSegmentation(
      path, {source_.image.grid, source_.series_instance_uid,
             source_.frame_of_reference_uid});
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->segments.size(), 2u);
  EXPECT_EQ(back->segments[0].label, "Label 3");  // segment 1 = label 3
  EXPECT_EQ(back->segments[1].label, "liver");    // segment 2 = label 7
  EXPECT_EQ(back->segments[1].type.meaning, "Liver");
  ASSERT_TRUE(back->segments[1].cielab.has_value());
  EXPECT_EQ(*back->segments[1].cielab, SegmentCieLab(liver));
  EXPECT_EQ(back->frames, 2);  // only the slices holding a segment
  for (size_t n = 0; n < labels_.data.size(); ++n) {
    const int expected = labels_.data[n] == 3   ? 1
                         : labels_.data[n] == 7 ? 2
                                                : 0;
    ASSERT_EQ(back->labels.data[n], expected) << n;
  }
}

TEST_F(LabelWritersTest, BadInputIsInvalidArgumentAndWritesNothing) {
  const std::string seg = (dir_.path() / "seg.dcm").string();
  EXPECT_THAT(WriteLabelSegmentation(source_, labels_, {},
                                     objects_.segmentation, images_, {}, seg)
                  .message(),
              HasSubstr("no voxel holds a label"));
  Volume<uint16_t> wrong = labels_;
  wrong.grid.size[2] += 1;
  wrong.data.resize(wrong.grid.VoxelCount());
  EXPECT_EQ(WriteLabelSegmentation(source_, wrong, {}, objects_.segmentation,
                                   images_, {}, seg)
                .code(),
            absl::StatusCode::kInvalidArgument);

  const std::string rt = (dir_.path() / "rt.dcm").string();
  const Grid& grid = source_.image.grid;
  RoiContours roi;
  roi.roi = DefaultLabelSegment(0);
  roi.slices[1] = {{{10, 10}, {20, 10}, {20, 20}}};
  EXPECT_THAT(WriteRtStructureSet(source_, grid, {roi}, objects_.segmentation,
                                  images_, {}, rt)
                  .message(),
              HasSubstr("ROI number 0"));
  roi.roi.number = 5;
  EXPECT_THAT(WriteRtStructureSet(source_, grid, {roi, roi},
                                  objects_.segmentation, images_, {}, rt)
                  .message(),
              HasSubstr("given twice"));
  roi.slices[9] = roi.slices[1];
  EXPECT_THAT(WriteRtStructureSet(source_, grid, {roi}, objects_.segmentation,
                                  images_, {}, rt)
                  .message(),
              HasSubstr("slice 9, outside the grid"));
  roi.slices.erase(9);
  roi.slices[2] = {{{10, 10}, {20, 10}}};
  EXPECT_THAT(WriteRtStructureSet(source_, grid, {roi}, objects_.segmentation,
                                  images_, {}, rt)
                  .message(),
              HasSubstr("contour of 2 points on slice 2"));
  EXPECT_FALSE(fs::exists(seg));
  EXPECT_FALSE(fs::exists(rt));
}

}  // namespace
}  // namespace interslice
