// Segment names from a sidecar or a Slicer .seg.nrrd (issue 24), and their
// way through the fill job to the SEG and RTSTRUCT.
#include "core/labels/segment_names.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "core/dicom/series_reader.h"
#include "core/labels/fill_job.h"
#include "core/labels/segmentation_reader.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

class SegmentNamesTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice_segment_names_test_" + std::to_string(getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string Write(const std::string& name, const std::string& text) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    return path;
  }
  fs::path dir_;
};

TEST_F(SegmentNamesTest, ColourTableCsv) {
  const std::string path = Write("names.csv",
                                 "label,name,R,G,B,code\n"
                                 "# comment\n"
                                 "1,Liver,221,130,101,SCT^10200004^Liver\n"
                                 "\n"
                                 "3, \"Left kidney\" ,185,102,83\n"
                                 "7,Tumour\n");
  absl::StatusOr<std::vector<LabelSegment>> s = ReadSegmentNames(path);
  ASSERT_TRUE(s.ok()) << s.status();
  ASSERT_EQ(s->size(), 3u);
  EXPECT_EQ((*s)[0].number, 1);
  EXPECT_EQ((*s)[0].label, "Liver");
  EXPECT_EQ(*(*s)[0].rgb, (std::array<uint8_t, 3>{221, 130, 101}));
  EXPECT_EQ((*s)[0].type.scheme, "SCT");
  EXPECT_EQ((*s)[0].type.value, "10200004");
  EXPECT_EQ((*s)[0].type.meaning, "Liver");
  // Defaults where nothing is given: the generic category and type.
  const LabelSegment d = DefaultLabelSegment(3);
  EXPECT_EQ((*s)[1].label, "Left kidney");
  EXPECT_EQ((*s)[1].type.value, d.type.value);
  EXPECT_EQ((*s)[1].category.value, d.category.value);
  EXPECT_EQ((*s)[2].label, "Tumour");
  EXPECT_EQ(*(*s)[2].rgb, *DefaultLabelSegment(7).rgb);
}

TEST_F(SegmentNamesTest, Json) {
  const std::string path = Write(
      "names.json",
      R"({"segments": [{"label": 2, "name": "Heart", "rgb": [206, 110, 84],
            "type": {"scheme": "SCT", "value": "80891009", "meaning": "Heart"},
            "category": "SCT^123037004^Anatomical Structure"},
           {"label": 5}]})");
  absl::StatusOr<std::vector<LabelSegment>> s = ReadSegmentNames(path);
  ASSERT_TRUE(s.ok()) << s.status();
  ASSERT_EQ(s->size(), 2u);
  EXPECT_EQ((*s)[0].label, "Heart");
  EXPECT_EQ((*s)[0].type.value, "80891009");
  EXPECT_EQ((*s)[0].category.meaning, "Anatomical Structure");
  EXPECT_EQ((*s)[1].label, "Label 5");
}

TEST_F(SegmentNamesTest, SlicerSegmentationFields) {
  const std::vector<std::pair<std::string, std::string>> fields = {
      {"Segment0_Name", "Spleen"},
      {"Segment0_LabelValue", "4"},
      {"Segment0_Color", "0.615686 0.423529 0.635294"},
      {"Segment0_Layer", "0"},
      {"Segment0_Terminology",
       "Segmentation category and type - 3D Slicer General Anatomy "
       "list~SCT^123037004^Anatomical Structure~SCT^78961009^Spleen~^^~"
       "Anatomic codes - DICOM master list~^^~^^"},
      {"Segment1_Name", "Other"},
      {"Segmentation_ContainedRepresentationNames", "Binary labelmap|"},
  };
  absl::StatusOr<std::vector<LabelSegment>> s =
      SegmentsFromSlicerFields(fields);
  ASSERT_TRUE(s.ok()) << s.status();
  ASSERT_EQ(s->size(), 2u);
  EXPECT_EQ((*s)[0].number, 4);
  EXPECT_EQ((*s)[0].label, "Spleen");
  EXPECT_EQ(*(*s)[0].rgb, (std::array<uint8_t, 3>{157, 108, 162}));
  EXPECT_EQ((*s)[0].type.value, "78961009");
  EXPECT_EQ((*s)[0].category.value, "123037004");
  // Without LabelValue: the segment's index + 1.
  EXPECT_EQ((*s)[1].number, 2);
  EXPECT_TRUE(SegmentsFromSlicerFields({{"Other", "x"}})->empty());
}

TEST_F(SegmentNamesTest, BadSidecarsAreOneLineNamingTheProblem) {
  struct Case {
    std::string name, text, message;
  };
  const Case cases[] = {
      {"twice.csv", "1,A\n1,B\n", "twice.csv line 2: label 1 is listed twice"},
      {"colour.csv", "1,A,300,0,0\n", "'300' is not an integer 0..255"},
      {"range.csv", "70000,A\n", "label 70000 is outside 1..65535"},
      {"word.csv", "1,A\nx,B\n", "line 2: 'x' is not a label number"},
      {"code.csv", "1,A,1,2,3,SCT-1\n", "is not scheme^value^meaning"},
      {"bad.json", "[{\"name\": \"A\"}]", "entry 1: no integer \"label\""},
      {"junk.json", "{", "not valid JSON"},
      {"names.xml", "", "unknown format"},
  };
  for (const Case& c : cases) {
    absl::StatusOr<std::vector<LabelSegment>> s =
        ReadSegmentNames(Write(c.name, c.text));
    ASSERT_FALSE(s.ok()) << c.name;
    EXPECT_THAT(s.status().message(), HasSubstr(c.message)) << c.name;
    EXPECT_EQ(std::string(s.status().message()).find('\n'), std::string::npos);
  }
  EXPECT_THAT(SegmentsFromSlicerFields({{"Segment0_Name", "A"},
                                        {"Segment1_Name", "B"},
                                        {"Segment1_Layer", "1"}})
                  .status()
                  .message(),
              HasSubstr("segments overlap"));
  EXPECT_THAT(SegmentsFromSlicerFields(
                  {{"Segment0_LabelValue", "2"}, {"Segment1_LabelValue", "2"}})
                  .status()
                  .message(),
              HasSubstr("label 2 is used by two segments"));
  LabelSegment seven;
  seven.number = 7;
  EXPECT_THAT(
      CheckSegmentsAgainstLabels({seven}, {1, 2, 3}, "the label names")
          .message(),
      HasSubstr("the label names name label 7, which the label map does not "
                "hold (labels: 1, 2, 3)"));
  EXPECT_TRUE(CheckSegmentsAgainstLabels({seven}, {7}, "x").ok());
}

// The names reach the SEG and the RTSTRUCT the fill job writes: from a
// .seg.nrrd's own fields, and from a CSV sidecar given with it; a sidecar
// naming a label the map does not hold writes nothing.
TEST_F(SegmentNamesTest, NamesReachSegAndRtstruct) {
  const std::string reference =
      std::string(::interslice::testing::TestDataDir()) + "/ct-thick";
  absl::StatusOr<DicomSeries> series = ReadDicomSeries({reference}, {}, {});
  ASSERT_TRUE(series.ok()) << series.status();
  const Grid ref = series->image.grid;
  LabelVolume keys;
  keys.grid = ref;
  keys.data.assign(ref.VoxelCount(), 0);
  for (int64_t k : {0, 3}) {
    for (int64_t j = 200; j < 260; ++j) {
      for (int64_t i = 180; i < 300; ++i) keys.at(i, j, k) = i < 240 ? 1 : 2;
    }
  }
  VolumeHeaderFields fields;
  fields.key_values = {{"Segment0_Name", "Liver"},
                       {"Segment0_LabelValue", "1"},
                       {"Segment0_Color", "1 0 0"},
                       {"Segment1_Name", "Spleen"},
                       {"Segment1_LabelValue", "2"}};
  const std::string map = (dir_ / "labels.seg.nrrd").string();
  ASSERT_TRUE(WriteVolume(keys, map, fields).ok());
  const ReferenceSeries ref_series{ref, series->series_instance_uid,
                                   series->frame_of_reference_uid};

  FillJobSpec spec;
  spec.reference = {reference};
  spec.segmentation = map;
  spec.mesh_formats = {};
  spec.volume_formats = {"nrrd"};
  spec.write_seg = true;
  spec.write_rtstruct = true;
  spec.fill.method = FillMethod::kSolver;
  spec.fill.solver.method = SolverMethod::kLinear;
  spec.output_dir = (dir_ / "own").string();
  absl::StatusOr<FillJobReport> own = RunFillJob(spec, {});
  ASSERT_TRUE(own.ok()) << own.status();
  absl::StatusOr<SegmentationInput> seg =
      ReadDicomSegmentation((dir_ / "own" / "seg.dcm").string(), ref_series);
  ASSERT_TRUE(seg.ok()) << seg.status();
  ASSERT_EQ(seg->segments.size(), 2u);
  EXPECT_EQ(seg->segments[0].label, "Liver");
  EXPECT_EQ(seg->segments[1].label, "Spleen");
  absl::StatusOr<SegmentationInput> rt =
      ReadRtStruct((dir_ / "own" / "rtstruct.dcm").string(), ref_series);
  ASSERT_TRUE(rt.ok()) << rt.status();
  ASSERT_EQ(rt->segments.size(), 2u);
  EXPECT_EQ(rt->segments[0].label, "Liver");
  EXPECT_EQ(*rt->segments[0].rgb, (std::array<uint8_t, 3>{255, 0, 0}));
  // The output label map keeps the segment fields.
  absl::StatusOr<VolumeFileHeader> header =
      ReadVolumeFileHeader((dir_ / "own" / "labels.nrrd").string());
  ASSERT_TRUE(header.ok());
  EXPECT_EQ(header->key_values.size(), 5u);

  // A sidecar replaces them.
  spec.label_names = Write("names.csv", "1,Aorta,200,0,0\n2,Heart\n");
  spec.output_dir = (dir_ / "sidecar").string();
  ASSERT_TRUE(RunFillJob(spec, {}).ok());
  seg = ReadDicomSegmentation((dir_ / "sidecar" / "seg.dcm").string(),
                              ref_series);
  ASSERT_TRUE(seg.ok());
  EXPECT_EQ(seg->segments[0].label, "Aorta");
  EXPECT_EQ(seg->segments[1].label, "Heart");

  // A sidecar naming a label the map does not hold: nothing written.
  spec.label_names = Write("bad.csv", "1,Aorta\n9,Nothing\n");
  spec.output_dir = (dir_ / "bad").string();
  absl::StatusOr<FillJobReport> bad = RunFillJob(spec, {});
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(),
              HasSubstr("name label 9, which the label map does not hold"));
  EXPECT_FALSE(fs::exists(dir_ / "bad"));
  // Overlapping segments (Slicer layers): nothing written either.
  fields.key_values.emplace_back("Segment1_Layer", "1");
  ASSERT_TRUE(WriteVolume(keys, map, fields).ok());
  spec.label_names.clear();
  bad = RunFillJob(spec, {});
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("segments overlap"));
  EXPECT_FALSE(fs::exists(dir_ / "bad"));
}

}  // namespace
}  // namespace interslice
