// The kinds of job behind job::JobKind: chosen from the wire, pointed at a
// spool's folders, run with one report shape.
#include "job/job.h"

#include <filesystem>
#include <fstream>
#include <string>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "job/options.h"
#include "job/wire.h"
#include "nlohmann/json.hpp"
#include "tests/testing/paths.h"

namespace interslice::job {
namespace {

namespace fs = std::filesystem;
using ::testing::AllOf;
using ::testing::Contains;
using ::testing::HasSubstr;

const std::string kSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-thick";

fs::path FreshDir(const std::string& name) {
  const fs::path dir = fs::path(::testing::TempDir()) / ("job-test-" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

TEST(JobKindTest, TheWireSpecChoosesTheKind) {
  v1::JobSpec interpolation;
  interpolation.set_threshold(300);
  absl::StatusOr<std::unique_ptr<JobKind>> a = MakeJobFromWire(interpolation);
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_EQ((*a)->name(), "interpolate");
  EXPECT_EQ((*a)->min_upload_files(), 1);
  EXPECT_FALSE((*a)->writes_dicom());
  EXPECT_TRUE((*a)->named_uploads().empty());
  interpolation.mutable_segmentation()->set_enabled(true);
  EXPECT_TRUE((*MakeJobFromWire(interpolation))->writes_dicom());

  v1::JobSpec fill;
  fill.mutable_fill()->set_segmentation_file("labels.nii.gz");
  absl::StatusOr<std::unique_ptr<JobKind>> b = MakeJobFromWire(fill);
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ((*b)->name(), "fill");
  EXPECT_EQ((*b)->min_upload_files(), 2);
  ASSERT_EQ((*b)->named_uploads().size(), 1u);
  EXPECT_EQ((*b)->named_uploads()[0].client_name, "labels.nii.gz");
  EXPECT_EQ((*b)->named_uploads()[0].path, "segmentation/segmentation.nii.gz");
  EXPECT_EQ((*b)->named_uploads()[0].field, "spec.fill.segmentation_file");
  // With label names: a second named upload beside the segmentation, and
  // one more file at least.
  fill.mutable_fill()->set_label_names_file("names/Colours.JSON");
  absl::StatusOr<std::unique_ptr<JobKind>> c = MakeJobFromWire(fill);
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ((*c)->min_upload_files(), 3);
  ASSERT_EQ((*c)->named_uploads().size(), 2u);
  EXPECT_EQ((*c)->named_uploads()[1].client_name, "names/Colours.JSON");
  EXPECT_EQ((*c)->named_uploads()[1].path, "segmentation/label-names.json");
  EXPECT_EQ((*c)->named_uploads()[1].field, "spec.fill.label_names_file");

  v1::JobSpec bad;  // no threshold
  EXPECT_THAT(std::string(MakeJobFromWire(bad).status().message()),
              HasSubstr("spec.threshold: missing"));
}

TEST(JobKindTest, SegmentationUploadPathKeepsTheReaderChoosingExtension) {
  EXPECT_EQ(SegmentationUploadPath("Labels.NII.GZ"),
            "segmentation/segmentation.nii.gz");
  EXPECT_EQ(SegmentationUploadPath("a.nii"), "segmentation/segmentation.nii");
  EXPECT_EQ(SegmentationUploadPath("x/y.nrrd"),
            "segmentation/segmentation.nrrd");
  EXPECT_EQ(SegmentationUploadPath("seg"), "segmentation/segmentation.dcm");
  EXPECT_EQ(LabelNamesUploadPath("a.CSV"), "segmentation/label-names.csv");
  EXPECT_EQ(LabelNamesUploadPath("b.txt"), "segmentation/label-names.txt");
  EXPECT_EQ(LabelNamesUploadPath("c.json"), "segmentation/label-names.json");
  EXPECT_EQ(MediaTypeForArtifact("seg.dcm"), "application/dicom");
  EXPECT_EQ(MediaTypeForArtifact("surface.stl"), "model/stl");
}

TEST(JobKindTest, FillInSpoolNeedsItsSegmentationAndSeries) {
  v1::JobSpec wire;
  wire.mutable_fill()->set_segmentation_file("labels.nii.gz");
  std::unique_ptr<JobKind> fill = *MakeJobFromWire(wire);
  const fs::path upload = FreshDir("fill-upload");
  absl::Status s = fill->UseSpool(upload.string(), "out", 0);
  EXPECT_EQ(s.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(s.message()), HasSubstr("segmentation"));
  fs::create_directories(upload / "segmentation");
  std::ofstream(upload / SegmentationUploadPath("labels.nii.gz")) << "x";
  s = fill->UseSpool(upload.string(), "out", 0);
  EXPECT_THAT(std::string(s.message()), HasSubstr("no reference series"));
  std::ofstream(upload / "000000.dcm") << "x";
  EXPECT_TRUE(fill->UseSpool(upload.string(), "out", 0).ok());

  // Label names the spec names must be in the upload too.
  wire.mutable_fill()->set_label_names_file("names.csv");
  std::unique_ptr<JobKind> named = *MakeJobFromWire(wire);
  s = named->UseSpool(upload.string(), "out", 0);
  EXPECT_EQ(s.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(s.message()),
              HasSubstr("spec.fill.label_names_file names is missing"));
  std::ofstream(upload / LabelNamesUploadPath("names.csv")) << "1,Bone\n";
  EXPECT_TRUE(named->UseSpool(upload.string(), "out", 0).ok());
}

// The human summary gives a box in mm as given and the voxel box it became.
TEST(JobKindTest, RoiMmSummaryGivesBothForms) {
  InterpolationOptions o;
  o.inputs = {kSeries};
  o.threshold = 300;
  // Corners in the reverse order. The thick phantom's slices are axial:
  // IPP (-115.5, -1.85, 696.21 + 5k), 0.451171875 mm pixels, so x in
  // [-10, 30] holds the centres of columns 234..322, y in [20, 60] rows
  // 49..137, z in [690, 720] all four slices.
  o.roi_mm = "30,20,720,-10,60,690";
  o.method = "linear";
  o.volume = "nrrd";
  o.mesh = "none";
  o.previews = "none";
  o.out = FreshDir("roi-mm").string();
  absl::StatusOr<JobSpec> spec = BuildJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  ComputeContext context;
  context.threads = 1;
  absl::StatusOr<JobResult> result = MakeInterpolationJob(*spec)->Run(context);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_THAT(
      result->summary,
      Contains(AllOf(HasSubstr("region    voxels x 234..323, y 49..138, z "
                               "0..4 (half-open)"),
                     HasSubstr("from the box (-10, 20, 690)..(30, 60, 720) "
                               "LPS mm"))));
  const nlohmann::json report = nlohmann::json::parse(result->report_json);
  EXPECT_EQ(report["input"]["roi_mm"]["min"], nlohmann::json({-10, 20, 690}));
  EXPECT_EQ(report["input"]["roi"]["begin"], nlohmann::json({234, 49, 0}));
  EXPECT_EQ(report["input"]["roi"]["end"], nlohmann::json({323, 138, 4}));
}

// One run through the interface, in place and in a spool: the same files,
// stages and artifacts as the core's RunJob reports, the report's paths
// relative to the output folder only in the spool.
TEST(JobKindTest, InterpolationRunsAndReportsInOneShape) {
  InterpolationOptions o;
  o.inputs = {kSeries};
  o.threshold = 300;
  o.roi = "200,40,0,296,136,4";
  o.method = "direct";
  o.volume = "nii";
  o.mesh = "stl";
  const fs::path local = FreshDir("local");
  o.out = local.string();
  absl::StatusOr<JobSpec> spec = BuildJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  ComputeContext context;
  context.threads = 1;
  absl::StatusOr<JobResult> in_place =
      MakeInterpolationJob(*spec)->Run(context);
  ASSERT_TRUE(in_place.ok()) << in_place.status();
  std::vector<std::string> stages;
  for (const StageTiming& t : in_place->stages) stages.push_back(t.stage);
  EXPECT_EQ(stages,
            (std::vector<std::string>{"read", "contour", "stack", "solve",
                                      "mesh", "preview", "write"}));
  // distance, mask, surface and its coordinates note, the previews (PNG by
  // default).
  ASSERT_EQ(in_place->artifacts.size(), 5u);
  for (const Artifact& a : in_place->artifacts) {
    EXPECT_TRUE(fs::exists(a.path)) << a.path;
    EXPECT_EQ(fs::path(a.path).parent_path(), local);
  }
  EXPECT_GT(in_place->peak_rss_bytes, 0);
  EXPECT_THAT(in_place->summary.front(), HasSubstr("wrote 5 file(s)"));
  EXPECT_THAT(in_place->summary,
              Contains(HasSubstr("region    voxels x 200..296, y 40..136, "
                                 "z 0..4 (half-open)")));
  nlohmann::json report = nlohmann::json::parse(in_place->report_json);
  EXPECT_EQ(report["artifacts"][0]["path"], in_place->artifacts[0].path);

  // The same job from the wire, in a spool.
  const fs::path upload = FreshDir("upload");
  for (const auto& entry : fs::directory_iterator(kSeries)) {
    fs::copy_file(entry.path(), upload / entry.path().filename());
  }
  const fs::path output = FreshDir("output");
  std::unique_ptr<JobKind> spooled = *MakeJobFromWire(ToWire(*spec));
  ASSERT_TRUE(spooled->UseSpool(upload.string(), output.string(), 0).ok());
  absl::StatusOr<JobResult> in_spool = spooled->Run(context);
  ASSERT_TRUE(in_spool.ok()) << in_spool.status();
  ASSERT_EQ(in_spool->artifacts.size(), in_place->artifacts.size());
  report = nlohmann::json::parse(in_spool->report_json);
  for (size_t n = 0; n < in_spool->artifacts.size(); ++n) {
    const fs::path a = in_spool->artifacts[n].path;
    const fs::path b = in_place->artifacts[n].path;
    EXPECT_EQ(a.parent_path(), output);
    EXPECT_EQ(report["artifacts"][n]["path"], a.filename().string());
    // A folder (the previews): each of its files.
    std::vector<std::pair<fs::path, fs::path>> files = {{a, b}};
    if (fs::is_directory(a)) {
      files.clear();
      for (const auto& entry : fs::directory_iterator(b)) {
        files.push_back({a / entry.path().filename(), entry.path()});
      }
      EXPECT_EQ(files.size(), 4u) << a;
    }
    for (const auto& [x, y] : files) {
      std::ifstream fa(x, std::ios::binary), fb(y, std::ios::binary);
      const std::string da((std::istreambuf_iterator<char>(fa)), {});
      const std::string db((std::istreambuf_iterator<char>(fb)), {});
      EXPECT_FALSE(db.empty()) << y;
      EXPECT_EQ(da, db) << x << " differs from the in-place run";
    }
  }
}

}  // namespace
}  // namespace interslice::job
