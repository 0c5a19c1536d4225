#include "core/pipeline/pipeline.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <set>
#include <thread>

#include "core/dicom/series_reader.h"
#include "core/sdf/signed_distance.h"
#include "core/slab/slab_deconvolution.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "nlohmann/json.hpp"
#include "tests/testing/dciodvfy.h"
#include "tests/testing/paths.h"
// osconfig.h must precede every other DCMTK header.
#include "absl/strings/str_format.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;

const std::string kSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-thick";

class PipelineTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice_pipeline_test_" + std::to_string(getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  JobSpec SmallJob() const {
    JobSpec spec;
    spec.inputs = {kSeries};
    spec.lower_threshold = 300;
    spec.roi = VoxelBox{{200, 40, 0}, {280, 120, 4}};
    spec.z_resolution.factor = 4;
    spec.solver.method = SolverMethod::kDirect;
    spec.output_dir = dir_.string();
    spec.volume_formats = {"nrrd"};
    spec.mesh_formats = {"stl"};
    return spec;
  }
  fs::path dir_;
};

TEST_F(PipelineTest, RunsEveryStageAndWritesConsistentOutputs) {
  std::vector<std::string> stages_seen;
  ComputeContext context;
  context.progress = [&](const ProgressEvent& e) {
    if (stages_seen.empty() || stages_seen.back() != e.stage) {
      stages_seen.push_back(e.stage);
    }
  };
  const auto report = RunJob(SmallJob(), context);
  ASSERT_TRUE(report.ok()) << report.status();
  std::vector<std::string> timed;
  for (const StageTiming& s : report->stages) timed.push_back(s.stage);
  EXPECT_THAT(timed, ::testing::ElementsAre("read", "contour", "stack", "solve",
                                            "mesh", "write"));
  EXPECT_THAT(stages_seen, ::testing::IsSupersetOf({"read", "contour", "stack",
                                                    "solve", "mesh", "write"}));
  EXPECT_EQ(report->output_grid.size, (Index3{80, 80, 13}));
  EXPECT_EQ(report->input_grid.size, (Index3{512, 512, 4}));
  EXPECT_GT(report->mesh_triangles, 0);
  // distance, mask, surface, and the coordinate note beside the surface.
  ASSERT_EQ(report->artifacts.size(), 4u);

  // Original slices of the written distance volume are exactly the 2D
  // signed distance maps of the input (the solver never touches them).
  const auto distance = ReadVolumeAsFloat((dir_ / "distance.nrrd").string());
  ASSERT_TRUE(distance.ok()) << distance.status();
  const auto series = ReadDicomSeries({kSeries}, {}, {});
  ASSERT_TRUE(series.ok());
  const Volume<float> roi = CropVolume(series->image, *SmallJob().roi);
  ContourOptions contour;
  contour.lower = 300;
  const auto maps = ComputeSliceDistanceMaps(roi, contour, {});
  ASSERT_TRUE(maps.ok());
  const int64_t plane = 80 * 80;
  for (int64_t s = 0; s < 4; ++s) {
    EXPECT_EQ(std::memcmp(&distance->data[s * 4 * plane],
                          &maps->data[s * plane], plane * sizeof(float)),
              0)
        << "original slice " << s;
  }
  // The mask is the sign of the field.
  const auto mask = ReadVolumeAsFloat((dir_ / "mask.nrrd").string());
  ASSERT_TRUE(mask.ok());
  for (size_t n = 0; n < mask->data.size(); ++n) {
    ASSERT_EQ(mask->data[n], distance->data[n] >= 0 ? 1.0f : 0.0f) << n;
  }
}

// Issue 25: a job whose DICOM objects are all it delivers (the DICOM node's
// jobs that send to PACS peers) does not write the files those objects carry:
// no surface.stl beside the Encapsulated STL, no mask beside the SEG, no
// distance volume beside the distance map, no coordinates note without a
// mesh file. The Encapsulated STL embeds the same mesh as surface.stl of the
// same job written in full, and no temporary file is left.
TEST_F(PipelineTest, FilesTheDicomObjectsCarryAreOmittedWhenAsked) {
  JobSpec full = SmallJob();
  full.output_series = {"intensity", "mask", "distance"};
  full.output_dir = (dir_ / "full").string();
  JobSpec omitted = full;
  omitted.output_dir = (dir_ / "omitted").string();
  omitted.omit_files_dicom_objects_carry = true;
  const auto full_report = RunJob(full, {.threads = 2});
  ASSERT_TRUE(full_report.ok()) << full_report.status();
  const auto report = RunJob(omitted, {.threads = 2});
  ASSERT_TRUE(report.ok()) << report.status();

  std::set<std::string> files, listed;
  for (const auto& entry : fs::directory_iterator(dir_ / "omitted")) {
    files.insert(entry.path().filename().string());
  }
  for (const Artifact& a : report->artifacts) {
    listed.insert(fs::path(a.path).filename().string());
  }
  EXPECT_EQ(files, listed);
  EXPECT_THAT(files,
              ::testing::IsSupersetOf({"series-intensity", "seg.dcm",
                                       "distance.dcm", "surface-stl.dcm"}));
  for (const char* name :
       {"surface.stl", "surface-coordinates.txt", "mask.nrrd", "distance.nrrd",
        ".surface-dicom.stl"}) {
    EXPECT_EQ(files.count(name), 0u) << name;
    if (std::string(name) != ".surface-dicom.stl") {
      EXPECT_TRUE(fs::exists(dir_ / "full" / name)) << name;
    }
  }
  // The embedded mesh: the bytes of the full job's surface.stl (the mesh is
  // small enough to be stored as extracted).
  std::ifstream in(dir_ / "full" / "surface.stl", std::ios::binary);
  const std::string stl((std::istreambuf_iterator<char>(in)),
                        std::istreambuf_iterator<char>());
  DcmFileFormat file;
  ASSERT_TRUE(
      file.loadFile(OFFilename((dir_ / "omitted/surface-stl.dcm").c_str()))
          .good());
  const Uint8* document = nullptr;
  unsigned long length = 0;
  ASSERT_TRUE(
      file.getDataset()
          ->findAndGetUint8Array(DCM_EncapsulatedDocument, document, &length)
          .good());
  ASSERT_GE(length, stl.size());
  // The element has even length: one pad byte after an odd-sized document.
  EXPECT_LE(length, stl.size() + 1);
  EXPECT_EQ(std::memcmp(document, stl.data(), stl.size()), 0);
}

// Issue 26: every DICOM object a job writes (intensity series, SEG, distance
// map, Encapsulated STL, preview series) passes dciodvfy (exit status and
// no Error line) on every real series in tests/data, and the SEG's segment
// is named for what it is: bone for CT at 300 HU, a region above the
// threshold for MR.
TEST_F(PipelineTest, EveryObjectOfEveryRealSeriesPassesDciodvfy) {
  const std::string data = ::interslice::testing::TestDataDir();
  struct Case {
    const char* name;
    std::string input;
    float threshold;
    std::string volume;
    const char* segment_label;
  };
  const Case cases[] = {
      {"ct-thick", data + "/ct-thick", 300, "", "Bone"},
      {"ct-tilt", data + "/ct-tilt", 300, "", "Bone"},
      {"mr-xa10", data + "/multiframe/siemens-xa10-6_1.dcm", 100, "",
       "Region above 100 units"},
      {"mr-enhanced", data + "/multiframe/philips-enhanced-mr-64frames.dcm",
       100,
       "stack 1, temporal position 1, frame type "
       "ORIGINAL\\PRIMARY\\T1\\M (MAGNITUDE)",
       "Region above 100 units"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    JobSpec spec;
    spec.inputs = {c.input};
    spec.multiframe_volume = c.volume;
    spec.lower_threshold = c.threshold;
    spec.solver.method = SolverMethod::kLinear;
    spec.z_resolution.factor = 2;
    spec.output_dir = (dir_ / c.name).string();
    spec.volume_formats = {};
    spec.mesh_formats = {"stl"};
    spec.output_series = {"intensity", "distance", "mask"};
    spec.intensity_method = "linear";
    spec.preview_formats = {"dicom"};
    absl::StatusOr<JobReport> report = RunJob(spec, {.threads = 2});
    ASSERT_TRUE(report.ok()) << report.status();
    std::vector<std::string> files;
    for (const Artifact& a : report->artifacts) {
      if (fs::is_directory(a.path)) {
        for (const auto& entry : fs::directory_iterator(a.path)) {
          if (entry.path().extension() == ".dcm") {
            files.push_back(entry.path().string());
          }
        }
      } else if (fs::path(a.path).extension() == ".dcm") {
        files.push_back(a.path);
      }
    }
    // intensity slices, seg, distance, surface STL, four previews
    ASSERT_GE(files.size(), 8u);
    std::string errors;
    EXPECT_EQ(testing::DciodvfyErrors(files, &errors), 0) << errors;

    DcmSegmentation* raw = nullptr;
    ASSERT_TRUE(
        DcmSegmentation::loadFile((dir_ / c.name / "seg.dcm").c_str(), raw)
            .good());
    std::unique_ptr<DcmSegmentation> seg(raw);
    OFString label;
    seg->getSegment(1)->getSegmentLabel(label);
    EXPECT_EQ(std::string(label.c_str()), c.segment_label);
  }
}

// --dicom-layout enhanced (issue 25) on an MR source: one Enhanced MR Image
// instance that the job's SEG, distance map, DICOM previews and STL lie on,
// every object valid for dciodvfy.
TEST_F(PipelineTest, EnhancedLayoutOfAnMrSourceIsOneValidEnhancedMr) {
  JobSpec spec;
  spec.inputs = {std::string(::interslice::testing::TestDataDir()) +
                 "/multiframe/siemens-xa10-6_1.dcm"};
  spec.lower_threshold = 100;
  spec.solver.method = SolverMethod::kLinear;
  spec.z_resolution.factor = 2;
  spec.output_dir = dir_.string();
  spec.volume_formats = {};
  spec.mesh_formats = {"stl"};
  spec.output_series = {"intensity", "distance", "mask"};
  spec.preview_formats = {"dicom"};
  spec.dicom_layout = "enhanced";
  absl::StatusOr<JobReport> report = RunJob(spec, {.threads = 2});
  ASSERT_TRUE(report.ok()) << report.status();
  std::vector<std::string> intensity;
  for (const auto& entry : fs::directory_iterator(dir_ / "series-intensity")) {
    intensity.push_back(entry.path().filename().string());
  }
  EXPECT_EQ(intensity, std::vector<std::string>{"enhanced.dcm"});
  DcmFileFormat enhanced;
  ASSERT_TRUE(
      enhanced.loadFile((dir_ / "series-intensity" / "enhanced.dcm").c_str())
          .good());
  OFString sop_class, frames;
  enhanced.getDataset()->findAndGetOFString(DCM_SOPClassUID, sop_class);
  enhanced.getDataset()->findAndGetOFString(DCM_NumberOfFrames, frames);
  EXPECT_EQ(std::string(sop_class.c_str()), UID_EnhancedMRImageStorage);
  EXPECT_EQ(std::string(frames.c_str()),
            std::to_string(report->output_grid.size[2]));
  std::vector<std::string> files;
  for (const auto& entry : fs::recursive_directory_iterator(dir_)) {
    if (entry.path().extension() == ".dcm") {
      files.push_back(entry.path().string());
    }
  }
  // enhanced, seg, distance, surface STL, four previews
  EXPECT_GE(files.size(), 8u);
  std::string errors;
  EXPECT_EQ(testing::DciodvfyErrors(files, &errors), 0) << errors;
}

// A modality without an enhanced IOD here (PT: the thick CT relabelled) is
// refused before the computation, naming it and the modalities written.
TEST_F(PipelineTest, EnhancedLayoutOfAPtSourceIsRefusedBeforeComputing) {
  const fs::path pt = dir_ / "pt";
  fs::create_directories(pt);
  for (const auto& entry : fs::directory_iterator(kSeries)) {
    if (entry.path().extension() != ".dcm") continue;
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile(entry.path().c_str()).good());
    file.getDataset()->putAndInsertString(DCM_Modality, "PT");
    ASSERT_TRUE(file.saveFile((pt / entry.path().filename()).c_str()).good());
  }
  JobSpec spec = SmallJob();
  spec.inputs = {pt.string()};
  spec.output_dir = (dir_ / "out").string();
  spec.output_series = {"intensity"};
  spec.dicom_layout = "enhanced";
  std::vector<std::string> stages;
  ComputeContext context;
  context.progress = [&](const ProgressEvent& e) {
    if (stages.empty() || stages.back() != e.stage) stages.push_back(e.stage);
  };
  absl::StatusOr<JobReport> report = RunJob(spec, context);
  ASSERT_EQ(report.status().code(), absl::StatusCode::kFailedPrecondition)
      << report.status();
  EXPECT_THAT(report.status().message(), ::testing::HasSubstr("'PT'"));
  EXPECT_THAT(report.status().message(),
              ::testing::HasSubstr("Enhanced CT and Enhanced MR"));
  EXPECT_THAT(stages, ::testing::Not(::testing::Contains("solve")));
  EXPECT_FALSE(fs::exists(dir_ / "out" / "series-intensity"));
}

// --segment-label / --segment-code reach the SEG, and change its UIDs (it is
// another object).
TEST_F(PipelineTest, SegmentLabelAndCodeReachTheSeg) {
  JobSpec spec = SmallJob();
  spec.mesh_formats = {};
  spec.write_seg = true;
  spec.preview_formats = {};
  spec.output_dir = (dir_ / "default").string();
  ASSERT_TRUE(RunJob(spec, {}).ok());
  spec.segment_label = "Brain mask";
  spec.segment_code = "SCT:12738006:Brain";
  spec.output_dir = (dir_ / "named").string();
  ASSERT_TRUE(RunJob(spec, {}).ok());
  std::string uids[2];
  int n = 0;
  for (const char* name : {"default", "named"}) {
    DcmSegmentation* raw = nullptr;
    ASSERT_TRUE(
        DcmSegmentation::loadFile((dir_ / name / "seg.dcm").c_str(), raw)
            .good());
    std::unique_ptr<DcmSegmentation> seg(raw);
    OFString label, code, scheme, uid;
    seg->getSegment(1)->getSegmentLabel(label);
    seg->getSegment(1)->getSegmentedPropertyTypeCode().getCodeValue(code);
    seg->getSegment(1)
        ->getSegmentedPropertyTypeCode()
        .getCodingSchemeDesignator(scheme);
    seg->getSOPCommon().getSOPInstanceUID(uid);
    uids[n++] = uid.c_str();
    if (std::string(name) == "default") {
      EXPECT_EQ(std::string(label.c_str()), "Bone");
      EXPECT_EQ(std::string(code.c_str()), "272673000");
    } else {
      EXPECT_EQ(std::string(label.c_str()), "Brain mask");
      EXPECT_EQ(std::string(code.c_str()), "12738006");
      EXPECT_EQ(std::string(scheme.c_str()), "SCT");
    }
  }
  EXPECT_NE(uids[0], uids[1]);
}

TEST_F(PipelineTest, ReportJsonHasTheDocumentedFields) {
  auto report = RunJob(SmallJob(), {});
  ASSERT_TRUE(report.ok()) << report.status();
  report->peak_rss_bytes = PeakRssBytes();
  const nlohmann::json j = nlohmann::json::parse(JobReportToJson(*report));
  EXPECT_TRUE(j["stages"].contains("solve"));
  EXPECT_EQ(j["solver"]["method"], "direct");
  EXPECT_EQ(j["solver"]["energy_units"], "voxel");
  EXPECT_EQ(j["grid"]["size"][2], 13);
  EXPECT_GT(j["peak_rss_bytes"].get<int64_t>(), 1 << 20);
  // Complete input files: nothing inferred.
  ASSERT_TRUE(j["input"]["notes"].is_array());
  EXPECT_TRUE(j["input"]["notes"].empty());
}

TEST(JobReportJsonTest, InputNotesAreListed) {
  JobReport report;
  report.input_notes = {
      "SeriesInstanceUID missing on 4 files: series grouped "
      "by modality, orientation, size and pixel spacing",
      "StudyInstanceUID missing on 4 files"};
  const nlohmann::json j = nlohmann::json::parse(JobReportToJson(report));
  EXPECT_EQ(j["input"]["notes"],
            nlohmann::json(std::vector<std::string>(report.input_notes)));
  // The server's worker process hands reports over as JSON.
  const auto back = JobReportFromJson(JobReportToJson(report));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->input_notes, report.input_notes);
}

TEST_F(PipelineTest, CancellationStopsTheJobAndWritesNothing) {
  CancellationToken token;
  ComputeContext context;
  context.cancel = &token;
  context.progress = [&](const ProgressEvent& e) {
    if (e.stage == "solve") token.Cancel();
  };
  JobSpec spec = SmallJob();
  spec.solver.method = SolverMethod::kConjugateGradient;
  const auto report = RunJob(spec, context);
  EXPECT_EQ(report.status().code(), absl::StatusCode::kCancelled);
  EXPECT_FALSE(fs::exists(dir_ / "distance.nrrd"));
}

// The intensity morph runs on its own thread beside the solve, mesh and
// preview stages: progress is still never reported concurrently, the
// "intensity" stage is still reported, and a job cancelled during the solve
// ends cancelled with no intensity series (the morph's thread is waited for
// before what it reads goes: ASan/TSan would see it otherwise).
TEST_F(PipelineTest, IntensityMorphBesideTheShapeStages) {
  JobSpec spec = SmallJob();
  spec.output_series = {"intensity"};
  spec.intensity_method = "morph";
  spec.volume_formats = {};
  std::atomic<int> inside{0};
  std::atomic<bool> overlapped{false};
  std::vector<std::string> stages;
  ComputeContext context;
  context.threads = 2;
  context.progress = [&](const ProgressEvent& e) {
    if (inside.fetch_add(1) != 0) overlapped = true;
    if (stages.empty() || stages.back() != e.stage) stages.push_back(e.stage);
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
    inside.fetch_sub(1);
  };
  absl::StatusOr<JobReport> report = RunJob(spec, context);
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_FALSE(overlapped.load());
  EXPECT_THAT(stages, ::testing::Contains("intensity"));
  EXPECT_EQ(report->intensity_method, "morph");
  EXPECT_GT(report->intensity_gaps, 0);

  CancellationToken token;
  ComputeContext cancelling;
  cancelling.threads = 2;
  cancelling.cancel = &token;
  cancelling.progress = [&](const ProgressEvent& e) {
    if (e.stage == "solve") token.Cancel();
  };
  spec.output_dir = (dir_ / "cancelled").string();
  const auto cancelled = RunJob(spec, cancelling);
  EXPECT_EQ(cancelled.status().code(), absl::StatusCode::kCancelled);
  EXPECT_FALSE(fs::exists(dir_ / "cancelled" / "series-intensity"));
}

TEST_F(PipelineTest, RejectsBadSpecsWithClearErrors) {
  JobSpec spec = SmallJob();
  spec.roi = VoxelBox{{0, 0, 0}, {10, 10, 1}};
  auto r = RunJob(spec, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("at least 2 slices"));

  spec = SmallJob();
  spec.roi = VoxelBox{{0, 0, 0}, {10, 10, 9}};
  r = RunJob(spec, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("along z"));

  spec = SmallJob();
  spec.upper_threshold = 100;
  EXPECT_EQ(RunJob(spec, {}).status().code(),
            absl::StatusCode::kInvalidArgument);

  spec = SmallJob();
  spec.mesh_formats = {"dxf"};
  EXPECT_EQ(RunJob(spec, {}).status().code(),
            absl::StatusCode::kInvalidArgument);

  spec = SmallJob();
  spec.max_output_voxels = 1000;
  EXPECT_EQ(RunJob(spec, {}).status().code(),
            absl::StatusCode::kResourceExhausted);

  // The input limit reaches the reader (512 x 512 x 4 voxels here).
  spec = SmallJob();
  spec.max_input_voxels = 512 * 512 * 4 - 1;
  r = RunJob(spec, {});
  EXPECT_FALSE(r.ok());
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("voxels"));
  spec.max_input_voxels = 512 * 512 * 4;
  EXPECT_TRUE(RunJob(spec, {}).ok());
}

// "nii-uncompressed" writes distance.nii / mask.nii beside (or instead of)
// the .nii.gz: the same voxels and grid, no gzip stream (a NIfTI-1 single
// file starts with sizeof_hdr = 348, a gzip stream with 1f 8b).
TEST_F(PipelineTest, UncompressedNiftiHoldsTheSameVolumes) {
  JobSpec spec = SmallJob();
  spec.volume_formats = {"nii", "nii-uncompressed"};
  auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  int distance_artifacts = 0;
  for (const Artifact& a : report->artifacts) {
    distance_artifacts += a.kind == "distance";
  }
  EXPECT_EQ(distance_artifacts, 2);
  for (const char* name : {"distance", "mask"}) {
    SCOPED_TRACE(name);
    const fs::path raw = dir_ / (std::string(name) + ".nii");
    const fs::path gz = dir_ / (std::string(name) + ".nii.gz");
    std::ifstream in(raw, std::ios::binary);
    int32_t sizeof_hdr = 0;
    in.read(reinterpret_cast<char*>(&sizeof_hdr), sizeof(sizeof_hdr));
    EXPECT_EQ(sizeof_hdr, 348);
    EXPECT_GT(fs::file_size(raw), 348u + 80u * 80u * 13u - 1u);
    const auto a = ReadVolumeAsFloat(raw.string());
    const auto b = ReadVolumeAsFloat(gz.string());
    ASSERT_TRUE(a.ok()) << a.status();
    ASSERT_TRUE(b.ok()) << b.status();
    EXPECT_EQ(a->grid.size, b->grid.size);
    EXPECT_EQ(a->grid.spacing, b->grid.spacing);
    EXPECT_EQ(a->grid.origin, b->grid.origin);
    EXPECT_EQ(a->data, b->data);
  }
  spec.volume_formats = {"nii-gz"};
  EXPECT_THAT(RunJob(spec, {}).status().message(),
              ::testing::HasSubstr("nii-uncompressed"));
  spec = SmallJob();
  spec.dicom_compression = "jpeg";
  EXPECT_THAT(RunJob(spec, {}).status().message(),
              ::testing::HasSubstr("DICOM compression 'jpeg'"));
}

TEST_F(PipelineTest, SameResultWhateverTheThreadCount) {
  JobSpec spec = SmallJob();
  spec.solver.method = SolverMethod::kConjugateGradient;
  spec.output_dir = (dir_ / "one").string();
  ComputeContext one;
  one.threads = 1;
  ASSERT_TRUE(RunJob(spec, one).ok());
  spec.output_dir = (dir_ / "two").string();
  ComputeContext two;
  two.threads = 2;
  ASSERT_TRUE(RunJob(spec, two).ok());
  for (const char* name : {"distance.nrrd", "surface.stl"}) {
    std::ifstream a(dir_ / "one" / name, std::ios::binary);
    std::ifstream b(dir_ / "two" / name, std::ios::binary);
    const std::string bytes_a((std::istreambuf_iterator<char>(a)), {});
    const std::string bytes_b((std::istreambuf_iterator<char>(b)), {});
    EXPECT_FALSE(bytes_a.empty());
    EXPECT_EQ(bytes_a, bytes_b) << name;
  }
}

TEST_F(PipelineTest, MissingSliceIsPlacedOnItsNodeUnlessSpacingIsStrict) {
  // I10, I20 and I40: gaps of 5 and 10 mm.
  const fs::path inputs = dir_.string() + "_in";
  fs::create_directories(inputs);
  for (const char* name : {"I10.dcm", "I20.dcm", "I40.dcm"}) {
    fs::copy_file(fs::path(kSeries) / name, inputs / name,
                  fs::copy_options::overwrite_existing);
  }
  JobSpec spec = SmallJob();
  spec.inputs = {inputs.string()};
  spec.roi = VoxelBox{{200, 40, 0}, {280, 120, 3}};
  spec.z_resolution = {.spacing_mm = 2.5};
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  // Median gap 7.5 mm, N = 3 -> 2.5 mm; nodes 0, 2, 6 exactly.
  EXPECT_EQ(report->output_grid.size[2], 7);
  EXPECT_NEAR(report->output_grid.spacing[2], 2.5, 1e-9);
  EXPECT_NEAR(report->max_snap_mm, 0, 1e-9);
  EXPECT_NEAR(report->output_grid.origin[2], 696.21, 1e-9);
  const auto json = nlohmann::json::parse(JobReportToJson(*report));
  EXPECT_TRUE(json["grid"].contains("max_snap_mm"));

  spec.strict_spacing = true;
  const auto strict = RunJob(spec, {});
  EXPECT_EQ(strict.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(strict.status().message()),
              ::testing::AllOf(::testing::HasSubstr("5.000"),
                               ::testing::HasSubstr("10.000")));
  // A uniform series passes strict spacing with no snap.
  JobSpec uniform = SmallJob();
  uniform.strict_spacing = true;
  const auto ok = RunJob(uniform, {});
  ASSERT_TRUE(ok.ok()) << ok.status();
  EXPECT_LT(ok->max_snap_mm, 1e-6);
  fs::remove_all(inputs);
}

TEST_F(PipelineTest, SlabDeconvolutionContoursTheEstimatesAndSaysSo) {
  // The 5 mm thick slices (SliceThickness 5): the field's original slices
  // are the distance maps of their slab deconvolution on the job's factor,
  // not of the slices as read.
  JobSpec spec = SmallJob();
  spec.slab_deconvolution = true;
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_EQ(report->slab_thickness_mm, 5.0);
  EXPECT_GT(report->slab_iterations, 0);
  EXPECT_LT(report->slab_residual_after, 0.5);
  EXPECT_GT(report->slab_residual_before, report->slab_residual_after);
  const auto json = nlohmann::json::parse(JobReportToJson(*report));
  EXPECT_EQ(json["input"]["slab_deconvolution"]["iterations"].get<int>(),
            report->slab_iterations);
  const auto back = JobReportFromJson(JobReportToJson(*report));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->slab_iterations, report->slab_iterations);
  EXPECT_EQ(back->slab_thickness_mm, 5.0);

  const auto distance = ReadVolumeAsFloat((dir_ / "distance.nrrd").string());
  ASSERT_TRUE(distance.ok()) << distance.status();
  const auto series = ReadDicomSeries({kSeries}, {}, {});
  ASSERT_TRUE(series.ok());
  EXPECT_EQ(series->slice_thickness_mm, 5.0);
  const Volume<float> roi = CropVolume(series->image, *spec.roi);
  SlabDeconvolutionOptions slab;
  slab.slab_thickness_mm = 5.0;
  slab.factor = 4;
  const auto estimates = DeconvolveSlabs(roi, slab, {});
  ASSERT_TRUE(estimates.ok()) << estimates.status();
  EXPECT_EQ(estimates->iterations, report->slab_iterations);
  ContourOptions contour;
  contour.lower = 300;
  const auto maps = ComputeSliceDistanceMaps(estimates->slices, contour, {});
  const auto raw_maps = ComputeSliceDistanceMaps(roi, contour, {});
  ASSERT_TRUE(maps.ok() && raw_maps.ok());
  const int64_t plane = 80 * 80;
  for (int64_t s = 0; s < 4; ++s) {
    EXPECT_EQ(std::memcmp(&distance->data[s * 4 * plane],
                          &maps->data[s * plane], plane * sizeof(float)),
              0)
        << "original slice " << s;
  }
  EXPECT_NE(maps->data, raw_maps->data);

  // Without the option nothing is reported.
  const auto plain = RunJob(SmallJob(), {});
  ASSERT_TRUE(plain.ok());
  EXPECT_EQ(plain->slab_thickness_mm, 0);
  EXPECT_FALSE(nlohmann::json::parse(JobReportToJson(*plain))["input"].contains(
      "slab_deconvolution"));

  // Non-uniform spacing (I10, I20, I40) is refused, naming the gaps.
  const fs::path inputs = dir_.string() + "_in";
  fs::create_directories(inputs);
  for (const char* name : {"I10.dcm", "I20.dcm", "I40.dcm"}) {
    fs::copy_file(fs::path(kSeries) / name, inputs / name,
                  fs::copy_options::overwrite_existing);
  }
  spec.inputs = {inputs.string()};
  spec.roi = VoxelBox{{200, 40, 0}, {280, 120, 3}};
  spec.z_resolution = {.spacing_mm = 2.5};
  const auto uneven = RunJob(spec, {});
  EXPECT_EQ(uneven.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(uneven.status().message()),
              ::testing::HasSubstr("uniform slice spacing"));
  fs::remove_all(inputs);
}

// The SOP Instance UID of a job's DICOM object (a file, or the first file
// of a folder).
std::string SopInstanceUidOf(const fs::path& path) {
  fs::path file = path;
  if (fs::is_directory(path)) {
    std::set<fs::path> files;
    for (const auto& entry : fs::directory_iterator(path)) {
      files.insert(entry.path());
    }
    if (files.empty()) return "";
    file = *files.begin();
  }
  DcmFileFormat dicom;
  OFString uid;
  if (!dicom.loadFile(OFFilename(file.c_str())).good() ||
      !dicom.getDataset()->findAndGetOFString(DCM_SOPInstanceUID, uid).good()) {
    return "";
  }
  return uid.c_str();
}

// Every parameter that changes an object changes its UIDs, and only that
// object's: two jobs that differed only in slab deconvolution got the same
// UIDs for different distance maps, SEGs and meshes, and a PACS that keeps
// the first instance of a UID (Orthanc's default) showed the first job's
// results for the second. The Encapsulated STL's own simplification changes
// the STL alone; the thresholds, the solver and slab deconvolution leave the
// intensity series as it is, so jobs that differ only in them share it (one
// copy in the study instead of one per rule, issue 44).
TEST_F(PipelineTest, ParametersThatChangeAnObjectChangeItsUidsAndOnlyItsOwn) {
  const char* const kObjects[] = {"series-intensity", "distance.dcm", "seg.dcm",
                                  "surface-stl.dcm"};
  auto run = [&](const char* name, auto edit) {
    JobSpec spec = SmallJob();
    spec.output_series = {"intensity", "mask", "distance"};
    spec.intensity_method = "linear";
    spec.output_dir = (dir_ / name).string();
    edit(spec);
    const auto report = RunJob(spec, {.threads = 2});
    EXPECT_TRUE(report.ok()) << name << ": " << report.status();
    std::map<std::string, std::string> uids;
    for (const char* object : kObjects) {
      uids[object] = SopInstanceUidOf(dir_ / name / object);
      EXPECT_FALSE(uids[object].empty()) << name << " " << object;
    }
    return uids;
  };
  const auto plain = run("plain", [](JobSpec&) {});
  const auto again = run("again", [](JobSpec&) {});
  const auto slab =
      run("slab", [](JobSpec& spec) { spec.slab_deconvolution = true; });
  const auto mesh =
      run("mesh", [](JobSpec& spec) { spec.dicom_mesh_adaptivity = 0.5; });
  const auto capped =
      run("capped", [](JobSpec& spec) { spec.dicom_mesh_max_mb = 10; });
  const auto t250 =
      run("t250", [](JobSpec& spec) { spec.lower_threshold = 250; });
  const auto cg = run("cg", [](JobSpec& spec) {
    spec.solver.method = SolverMethod::kConjugateGradient;
  });
  const auto morph =
      run("morph", [](JobSpec& spec) { spec.intensity_method = "morph"; });
  const auto finer =
      run("finer", [](JobSpec& spec) { spec.z_resolution.factor = 5; });
  // The same job: the same objects (a PACS replaces them).
  EXPECT_EQ(again, plain);
  // What shapes the objects but not a grey value: every shape object
  // changes, the intensity series is shared (the same UIDs, and so the same
  // series number).
  for (const auto* other : {&slab, &t250, &cg}) {
    for (const char* object : {"distance.dcm", "seg.dcm", "surface-stl.dcm"}) {
      EXPECT_NE(other->at(object), plain.at(object)) << object;
    }
    EXPECT_EQ(other->at("series-intensity"), plain.at("series-intensity"));
  }
  // A shared series says the same of itself whichever job wrote it: its
  // number and description (no threshold in them).
  auto header = [&](const char* name, const DcmTagKey& tag) {
    std::set<fs::path> files;
    for (const auto& entry :
         fs::directory_iterator(dir_ / name / "series-intensity")) {
      files.insert(entry.path());
    }
    DcmFileFormat file;
    OFString value;
    EXPECT_TRUE(file.loadFile(OFFilename(files.begin()->c_str())).good());
    file.getDataset()->findAndGetOFString(tag, value);
    return std::string(value.c_str());
  };
  for (const DcmTagKey& tag : {DCM_SeriesNumber, DCM_SeriesDescription}) {
    EXPECT_EQ(header("t250", tag), header("plain", tag)) << tag;
    EXPECT_FALSE(header("plain", tag).empty()) << tag;
  }
  EXPECT_THAT(header("plain", DCM_SeriesDescription),
              ::testing::Not(::testing::HasSubstr("300")));
  // The grey values' method changes the intensity series alone; the grid
  // changes everything.
  EXPECT_NE(morph.at("series-intensity"), plain.at("series-intensity"));
  for (const char* object : kObjects) {
    EXPECT_NE(finer.at(object), plain.at(object)) << object;
  }
  // The STL's own simplification: the STL only.
  for (const auto* other : {&mesh, &capped}) {
    EXPECT_NE(other->at("surface-stl.dcm"), plain.at("surface-stl.dcm"));
    for (const char* object : {"series-intensity", "distance.dcm", "seg.dcm"}) {
      EXPECT_EQ(other->at(object), plain.at(object)) << object;
    }
  }
  EXPECT_NE(mesh.at("surface-stl.dcm"), capped.at("surface-stl.dcm"));
}

TEST_F(PipelineTest, RoiOfANonUniformSeriesStartsAtItsFirstSlice) {
  const fs::path inputs = dir_.string() + "_in";
  fs::create_directories(inputs);
  for (const char* name : {"I10.dcm", "I30.dcm", "I40.dcm"}) {
    fs::copy_file(fs::path(kSeries) / name, inputs / name,
                  fs::copy_options::overwrite_existing);
  }
  JobSpec spec = SmallJob();
  spec.inputs = {inputs.string()};
  // Slices 1..2 of {696.21, 706.21, 711.21}: the grid's median spacing
  // (7.5 mm) would put slice 1 at 703.71.
  spec.roi = VoxelBox{{200, 40, 1}, {280, 120, 3}};
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_NEAR(report->output_grid.origin[2], 706.21, 1e-9);
  fs::remove_all(inputs);
}

TEST_F(PipelineTest, MorphIntensitySeriesKeepsSourceSlicesAndReports) {
  JobSpec spec = SmallJob();
  spec.output_series = {"intensity"};
  spec.mesh_formats = {};
  spec.volume_formats = {};
  spec.intensity_method = "morph";
  const auto morph = RunJob(spec, {});
  ASSERT_TRUE(morph.ok()) << morph.status();
  EXPECT_EQ(morph->intensity_method, "morph");
  EXPECT_EQ(morph->intensity_gaps, 3);
  EXPECT_GE(morph->intensity_fallback_fraction, 0.0);
  EXPECT_LE(morph->intensity_fallback_fraction, 1.0);
  EXPECT_GT(morph->intensity_mean_displacement_mm, 0.0);
  const auto morph_series =
      ReadDicomSeries({(dir_ / "series-intensity").string()}, {}, {});
  ASSERT_TRUE(morph_series.ok()) << morph_series.status();
  ASSERT_EQ(morph_series->image.grid.size, (Index3{80, 80, 13}));

  // The source slices are in it unchanged (to the storage step, 1 HU here).
  const auto source = ReadDicomSeries({kSeries}, {}, {});
  ASSERT_TRUE(source.ok());
  const Volume<float> roi = CropVolume(source->image, *spec.roi);
  const int64_t plane = 80 * 80;
  for (int64_t s = 0; s < 4; ++s)
    for (int64_t v = 0; v < plane; ++v)
      ASSERT_NEAR(morph_series->image.data[4 * s * plane + v],
                  roi.data[s * plane + v], 0.5)
          << "source slice " << s << " pixel " << v;

  // The same job with linear values: the same source slices, other inserted
  // slices, other UIDs (the method is part of what the series is).
  spec.intensity_method = "linear";
  fs::remove_all(dir_);
  const auto linear = RunJob(spec, {});
  ASSERT_TRUE(linear.ok()) << linear.status();
  EXPECT_EQ(linear->intensity_method, "linear");
  EXPECT_EQ(linear->intensity_gaps, 0);
  const auto linear_series =
      ReadDicomSeries({(dir_ / "series-intensity").string()}, {}, {});
  ASSERT_TRUE(linear_series.ok()) << linear_series.status();
  double difference = 0;
  for (int64_t k = 1; k < 4; ++k)
    for (int64_t v = 0; v < plane; ++v)
      difference += std::abs(linear_series->image.data[k * plane + v] -
                             morph_series->image.data[k * plane + v]);
  EXPECT_GT(difference / (3 * plane), 1.0);  // HU per voxel
  EXPECT_NE(linear_series->series_instance_uid,
            morph_series->series_instance_uid);

  // The report says what happened, and reads back.
  const std::string json = JobReportToJson(*morph);
  const nlohmann::json j = nlohmann::json::parse(json);
  EXPECT_EQ(j["intensity"]["method"], "morph");
  EXPECT_EQ(j["intensity"]["gaps"], 3);
  EXPECT_TRUE(j["intensity"].contains("fallback_fraction"));
  EXPECT_TRUE(j["intensity"].contains("gaps_not_registered"));
  const auto back = JobReportFromJson(json);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->intensity_method, "morph");
  EXPECT_EQ(back->intensity_gaps, 3);
  EXPECT_EQ(back->intensity_fallback_fraction,
            morph->intensity_fallback_fraction);
  EXPECT_EQ(back->intensity_mean_displacement_mm,
            morph->intensity_mean_displacement_mm);
  // No intensity series, no intensity section.
  JobSpec no_series = SmallJob();
  fs::remove_all(dir_);
  const auto plain = RunJob(no_series, {});
  ASSERT_TRUE(plain.ok());
  EXPECT_FALSE(
      nlohmann::json::parse(JobReportToJson(*plain)).contains("intensity"));
}

TEST_F(PipelineTest, MorphIntensityHandlesAMissingSlice) {
  // I10, I20 and I40: gaps of 5 and 10 mm; the 10 mm gap is 2 median
  // gaps, registered as any other.
  const fs::path inputs = dir_.string() + "_in";
  fs::create_directories(inputs);
  for (const char* name : {"I10.dcm", "I20.dcm", "I40.dcm"}) {
    fs::copy_file(fs::path(kSeries) / name, inputs / name,
                  fs::copy_options::overwrite_existing);
  }
  JobSpec spec = SmallJob();
  spec.inputs = {inputs.string()};
  spec.roi = VoxelBox{{200, 40, 0}, {280, 120, 3}};
  spec.z_resolution = {.spacing_mm = 2.5};
  spec.output_series = {"intensity"};
  spec.intensity_method = "morph";
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_EQ(report->intensity_gaps, 2);
  const auto written =
      ReadDicomSeries({(dir_ / "series-intensity").string()}, {}, {});
  ASSERT_TRUE(written.ok()) << written.status();
  const auto source = ReadDicomSeries({inputs.string()}, {}, {});
  ASSERT_TRUE(source.ok());
  const Volume<float> roi = CropVolume(source->image, *spec.roi);
  const int64_t plane = 80 * 80;
  // Nodes 0, 2 and 6 hold the source slices.
  const int64_t nodes[3] = {0, 2, 6};
  for (int64_t s = 0; s < 3; ++s)
    for (int64_t v = 0; v < plane; ++v)
      ASSERT_NEAR(written->image.data[nodes[s] * plane + v],
                  roi.data[s * plane + v], 0.5)
          << "source slice " << s;
  fs::remove_all(inputs);
}

TEST_F(PipelineTest, UnknownIntensityMethodIsRejected) {
  JobSpec spec = SmallJob();
  spec.intensity_method = "cubic";
  const auto report = RunJob(spec, {});
  EXPECT_EQ(report.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(report.status().message()),
              ::testing::AllOf(::testing::HasSubstr("intensity method"),
                               ::testing::HasSubstr("cubic")));
}

}  // namespace
}  // namespace interslice

namespace interslice {
namespace {

// The colour of the original-slice ticks (core/preview).
bool IsTickColour(const uint8_t* p) {
  return p[0] > 200 && p[1] > 150 && p[2] < 60;
}

class PipelinePreviewTest : public PipelineTest {};

TEST_F(PipelinePreviewTest, PngAndDicomPreviewsAreAStageAndArtifacts) {
  JobSpec spec = SmallJob();
  spec.preview_formats = {"png", "dicom"};
  spec.output_series = {"intensity"};
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  std::vector<std::string> timed;
  for (const StageTiming& s : report->stages) timed.push_back(s.stage);
  EXPECT_THAT(timed, ::testing::ElementsAre("read", "contour", "stack", "solve",
                                            "mesh", "preview", "write"));
  EXPECT_TRUE(report->preview_notes.empty())
      << ::testing::PrintToString(report->preview_notes);
  std::map<std::string, std::string> kinds;
  for (const Artifact& a : report->artifacts) kinds[a.kind] = a.path;
  ASSERT_TRUE(kinds.count("previews"));
  ASSERT_TRUE(kinds.count("previews-dicom"));
  EXPECT_EQ(kinds["previews"], (dir_ / "previews").string());
  for (const char* name :
       {"axial.png", "coronal.png", "sagittal.png", "3d-front.png"}) {
    std::ifstream in(dir_ / "previews" / name, std::ios::binary);
    std::string head(8, '\0');
    in.read(head.data(), 8);
    EXPECT_EQ(head.substr(1, 3), "PNG") << name;
  }
  for (int n = 1; n <= 4; ++n) {
    EXPECT_TRUE(
        fs::exists(dir_ / "previews-dicom" / absl::StrFormat("IM%05d.dcm", n)));
  }
  EXPECT_FALSE(fs::exists(dir_ / "previews-dicom" / "IM00005.dcm"));
  // The report carries the previews' notes (none) and reads back.
  const std::string json = JobReportToJson(*report);
  EXPECT_TRUE(nlohmann::json::parse(json).contains("previews"));
  JobReport with_note = *report;
  with_note.preview_notes = {"the object is empty: no outline"};
  const auto back = JobReportFromJson(JobReportToJson(with_note));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->preview_notes, with_note.preview_notes);
}

// The original slices reach the previews at their positions on the output
// grid: the ROI's 4 slices at factor 4 are output slices 0, 4, 8, 12, each a
// tick row beside the coronal view (16 tick pixels: 8 on each side).
TEST_F(PipelinePreviewTest, OriginalSlicesAreTickedInTheWrittenPreview) {
  JobSpec spec = SmallJob();
  spec.preview_formats = {"dicom"};
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  DcmFileFormat file;
  ASSERT_TRUE(
      file.loadFile((dir_ / "previews-dicom" / "IM00002.dcm").c_str()).good());
  DcmDataset& ds = *file.getDataset();
  OFString comments;
  ds.findAndGetOFString(DCM_ImageComments, comments);
  EXPECT_THAT(comments.c_str(), ::testing::HasSubstr("coronal"));
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  const Uint8* pixels = nullptr;
  ASSERT_TRUE(ds.findAndGetUint8Array(DCM_PixelData, pixels).good());
  int tick_rows = 0;
  for (int y = 0; y < rows; ++y) {
    int ticks = 0;
    for (int x = 0; x < columns; ++x) {
      ticks +=
          IsTickColour(pixels + (static_cast<size_t>(y) * columns + x) * 3);
    }
    tick_rows += ticks == 16 ? 1 : 0;
  }
  // 13 output slices of 0.45 mm stretched to the display: the 4 ticks are
  // far apart.
  EXPECT_EQ(tick_rows, 4);
}

TEST_F(PipelinePreviewTest, EmptyMaskAndTinyRoiStillGivePreviews) {
  JobSpec spec = SmallJob();
  spec.preview_formats = {"png"};
  spec.lower_threshold = 30000;  // nothing is that dense
  auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_THAT(report->preview_notes,
              ::testing::Contains(::testing::HasSubstr("the object is empty")));
  EXPECT_TRUE(fs::exists(dir_ / "previews" / "3d-front.png"));

  spec = SmallJob();
  spec.preview_formats = {"png"};
  spec.roi = VoxelBox{{250, 60, 1}, {253, 63, 3}};
  spec.z_resolution.factor = 2;
  report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_TRUE(fs::exists(dir_ / "previews" / "axial.png"));
}

TEST_F(PipelinePreviewTest, UnknownFormatIsRefused) {
  JobSpec spec = SmallJob();
  spec.preview_formats = {"gif"};
  const auto report = RunJob(spec, {});
  EXPECT_EQ(report.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(report.status().message(), ::testing::HasSubstr("'gif'"));
  spec.preview_formats = {"png"};
  spec.series_number_base = 2147483647 - 5;
  EXPECT_EQ(RunJob(spec, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// --- roi_mm (issue 26: a region of interest as a viewer gives it) ---

// A series' voxel centres computed from its headers alone (DCMTK), without
// the reader: slices sorted along n = row x column direction, voxel (i, j, k)
// of the reader's grid at IPP(first) + r i sx + c j sy + n (position(k) -
// position(first)) (series_reader.h: tilted slices are resampled onto the
// first slice's in-plane grid).
struct HeaderGeometry {
  Vec3 first = {0, 0, 0}, r = {0, 0, 0}, c = {0, 0, 0}, n = {0, 0, 0};
  double sx = 0, sy = 0;
  int64_t columns = 0, rows = 0;
  std::vector<double> offsets;  // along n from the first slice, sorted
  Vec3 Centre(int64_t i, int64_t j, int64_t k) const {
    Vec3 p;
    for (int a = 0; a < 3; ++a) {
      p[a] = first[a] + r[a] * i * sx + c[a] * j * sy + n[a] * offsets[k];
    }
    return p;
  }
};

HeaderGeometry ReadHeaderGeometry(const std::string& folder) {
  HeaderGeometry g;
  std::vector<Vec3> positions;
  for (const auto& entry : fs::directory_iterator(folder)) {
    if (entry.path().extension() != ".dcm") continue;
    DcmFileFormat file;
    EXPECT_TRUE(file.loadFile(entry.path().c_str()).good());
    DcmDataset* d = file.getDataset();
    Vec3 ipp;
    for (int a = 0; a < 3; ++a) {
      EXPECT_TRUE(
          d->findAndGetFloat64(DCM_ImagePositionPatient, ipp[a], a).good());
    }
    positions.push_back(ipp);
    if (positions.size() > 1) continue;
    for (int a = 0; a < 3; ++a) {
      d->findAndGetFloat64(DCM_ImageOrientationPatient, g.r[a], a);
      d->findAndGetFloat64(DCM_ImageOrientationPatient, g.c[a], a + 3);
    }
    // PixelSpacing = row spacing (along c), column spacing (along r).
    d->findAndGetFloat64(DCM_PixelSpacing, g.sy, 0);
    d->findAndGetFloat64(DCM_PixelSpacing, g.sx, 1);
    Uint16 columns = 0, rows = 0;
    d->findAndGetUint16(DCM_Columns, columns);
    d->findAndGetUint16(DCM_Rows, rows);
    g.columns = columns;
    g.rows = rows;
  }
  g.n = {g.r[1] * g.c[2] - g.r[2] * g.c[1], g.r[2] * g.c[0] - g.r[0] * g.c[2],
         g.r[0] * g.c[1] - g.r[1] * g.c[0]};
  auto along = [&](const Vec3& p) {
    return p[0] * g.n[0] + p[1] * g.n[1] + p[2] * g.n[2];
  };
  std::sort(positions.begin(), positions.end(),
            [&](const Vec3& a, const Vec3& b) { return along(a) < along(b); });
  g.first = positions.front();
  for (const Vec3& p : positions) {
    g.offsets.push_back(along(p) - along(g.first));
  }
  return g;
}

// The brute-force answer: the index bounding box of every voxel centre
// inside the LPS box (none: begin > end).
VoxelBox BruteForceVoxelBox(const HeaderGeometry& g, const PhysicalBox& box) {
  VoxelBox out{{INT64_MAX, INT64_MAX, INT64_MAX}, {0, 0, 0}};
  for (int64_t k = 0; k < static_cast<int64_t>(g.offsets.size()); ++k) {
    for (int64_t j = 0; j < g.rows; ++j) {
      for (int64_t i = 0; i < g.columns; ++i) {
        const Vec3 p = g.Centre(i, j, k);
        bool inside = true;
        for (int a = 0; a < 3; ++a) {
          inside &= p[a] >= box.min[a] - 1e-6 && p[a] <= box.max[a] + 1e-6;
        }
        if (!inside) continue;
        const Index3 v = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          out.begin[a] = std::min(out.begin[a], v[a]);
          out.end[a] = std::max(out.end[a], v[a] + 1);
        }
      }
    }
  }
  return out;
}

// The LPS bounding box of the centres of voxel box `v`, widened by `margin`
// mm on every side.
PhysicalBox CentresBox(const HeaderGeometry& g, const VoxelBox& v,
                       double margin) {
  PhysicalBox box{{INFINITY, INFINITY, INFINITY},
                  {-INFINITY, -INFINITY, -INFINITY}};
  for (int corner = 0; corner < 8; ++corner) {
    const Vec3 p = g.Centre((corner & 1) ? v.end[0] - 1 : v.begin[0],
                            (corner & 2) ? v.end[1] - 1 : v.begin[1],
                            (corner & 4) ? v.end[2] - 1 : v.begin[2]);
    for (int a = 0; a < 3; ++a) {
      box.min[a] = std::min(box.min[a], p[a] - margin);
      box.max[a] = std::max(box.max[a], p[a] + margin);
    }
  }
  return box;
}

// On the axial thick series, the mm box around the centres of SmallJob's
// voxel ROI (widened by less than half a voxel) is that ROI: the same voxel
// box, the same output grid, both forms in the report.
TEST_F(PipelineTest, RoiMmOnAnAxialSeriesIsTheVoxelBoxItCovers) {
  const HeaderGeometry g = ReadHeaderGeometry(kSeries);
  ASSERT_EQ(g.offsets.size(), 4u);
  const VoxelBox voxels = *SmallJob().roi;
  const PhysicalBox mm = CentresBox(g, voxels, 0.1);
  JobSpec spec = SmallJob();
  spec.roi.reset();
  spec.roi_mm = mm;
  spec.mesh_formats.clear();
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  ASSERT_TRUE(report->roi.has_value());
  EXPECT_EQ(report->roi->begin, voxels.begin);
  EXPECT_EQ(report->roi->end, voxels.end);
  ASSERT_TRUE(report->roi_mm.has_value());
  EXPECT_EQ(report->roi_mm->min, mm.min);
  EXPECT_EQ(report->roi_mm->max, mm.max);
  EXPECT_EQ(report->output_grid.size, (Index3{80, 80, 13}));
  // The output's origin is the centre of the ROI's first voxel.
  const Vec3 origin = g.Centre(voxels.begin[0], voxels.begin[1], 0);
  for (int a = 0; a < 3; ++a) {
    EXPECT_NEAR(report->output_grid.origin[a], origin[a], 1e-3) << a;
  }
  // Both forms in the JSON report, and back.
  const nlohmann::json j = nlohmann::json::parse(JobReportToJson(*report));
  EXPECT_EQ(j["input"]["roi"]["begin"], nlohmann::json(voxels.begin));
  EXPECT_EQ(j["input"]["roi_mm"]["max"], nlohmann::json(mm.max));
  const auto back = JobReportFromJson(JobReportToJson(*report));
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_TRUE(back->roi.has_value() && back->roi_mm.has_value());
  EXPECT_EQ(back->roi->begin, voxels.begin);
  EXPECT_EQ(back->roi->end, voxels.end);
  EXPECT_EQ(back->roi_mm->min, mm.min);
  EXPECT_EQ(back->roi_mm->max, mm.max);

  // Half a voxel narrower in-plane than the ROI's centres: one voxel less
  // on each side (the axial series' rows and columns run along LPS x, y).
  PhysicalBox smaller = mm;
  for (int a = 0; a < 2; ++a) {
    const double spacing = a == 0 ? g.sx : g.sy;
    smaller.min[a] += 0.1 + 0.5 * spacing;
    smaller.max[a] -= 0.1 + 0.5 * spacing;
  }
  spec.roi_mm = smaller;
  const auto shrunk = RunJob(spec, {});
  ASSERT_TRUE(shrunk.ok()) << shrunk.status();
  EXPECT_EQ(shrunk->roi->begin, (Index3{voxels.begin[0] + 1,
                                        voxels.begin[1] + 1, voxels.begin[2]}));
  EXPECT_EQ(shrunk->roi->end,
            (Index3{voxels.end[0] - 1, voxels.end[1] - 1, voxels.end[2]}));
}

// On the tilted series (gantry tilt, the slice plane oblique to the patient
// axes) a mm box around a known voxel region maps to a voxel box that
// contains the region, is exactly the brute-force box of the voxel centres
// inside, and not much more.
TEST_F(PipelineTest, RoiMmOnATiltedSeriesCoversTheRegionAndLittleMore) {
  const std::string tilted =
      std::string(::interslice::testing::TestDataDir()) + "/ct-tilt";
  const HeaderGeometry g = ReadHeaderGeometry(tilted);
  ASSERT_EQ(g.offsets.size(), 3u);
  const VoxelBox region{{200, 200, 0}, {280, 280, 3}};
  const PhysicalBox mm = CentresBox(g, region, 0.01);
  JobSpec spec = SmallJob();
  spec.inputs = {tilted};
  spec.roi.reset();
  spec.roi_mm = mm;
  spec.mesh_formats.clear();
  const auto report = RunJob(spec, {});
  ASSERT_TRUE(report.ok()) << report.status();
  ASSERT_NE(report->gantry_tilt_degrees, 0);
  ASSERT_TRUE(report->roi.has_value());
  const VoxelBox& got = *report->roi;
  const VoxelBox expected = BruteForceVoxelBox(g, mm);
  EXPECT_EQ(got.begin, expected.begin);
  EXPECT_EQ(got.end, expected.end);
  for (int a = 0; a < 3; ++a) {
    EXPECT_LE(got.begin[a], region.begin[a]) << a;
    EXPECT_GE(got.end[a], region.end[a]) << a;
    // The region's LPS box is oblique to the slices: it holds a row more
    // on each side (what the brute force finds), not a bounding box of
    // the whole slice.
    EXPECT_LE(got.Size()[a], region.Size()[a] + 2) << a;
  }
  EXPECT_EQ(report->input_slices, 3);
}

TEST_F(PipelineTest, RoiMmOutsideTheSeriesOrWithRoiIsAClearError) {
  const HeaderGeometry g = ReadHeaderGeometry(kSeries);
  JobSpec spec = SmallJob();
  spec.roi.reset();
  // 1 m above the series along the slice axis.
  PhysicalBox above = CentresBox(g, *SmallJob().roi, 0.1);
  above.min[2] += 1000;
  above.max[2] += 1000;
  spec.roi_mm = above;
  auto r = RunJob(spec, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("misses the series"));
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("z (slices)"));
  EXPECT_FALSE(fs::exists(dir_ / "distance.nrrd"));
  // Between two voxel centres along x: overlaps, holds no centre.
  PhysicalBox thin = CentresBox(g, *SmallJob().roi, 0.1);
  thin.min[0] = g.first[0] + g.r[0] * 100.3 * g.sx;
  thin.max[0] = g.first[0] + g.r[0] * 100.6 * g.sx;
  if (thin.min[0] > thin.max[0]) std::swap(thin.min[0], thin.max[0]);
  spec.roi_mm = thin;
  r = RunJob(spec, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("no voxel centre"));
  // Both forms at once.
  spec = SmallJob();
  spec.roi_mm = CentresBox(g, *SmallJob().roi, 0.1);
  r = RunJob(spec, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("roi (voxels)"));
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("roi_mm"));
}

}  // namespace
}  // namespace interslice
