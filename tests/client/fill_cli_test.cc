// End-to-end tests of `interslice fill`: the real binary on the shipped
// thick CT phantom, with a two-label segmentation made from it.
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <numbers>
#include <string>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/label_segmentation.h"
#include "core/labels/segmentation_reader.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "nlohmann/json.hpp"
#include "tests/core/dicom_out/dicom_test_util.h"
#include "tests/testing/cli.h"
#include "tests/testing/mesh_checks.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

using testing::CommandResult;
using testing::RunCli;

// Every 2nd slice of the 5 mm series is a key slice (10 mm gaps).
constexpr int64_t kStep = 2;
constexpr const char* kMethod = "direct";
const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";

class FillCliTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    absl::StatusOr<DicomSeries> series =
        ReadDicomSeries({kPhantom}, {}, ComputeContext{.threads = 1});
    ASSERT_TRUE(series.ok()) << series.status();
    // Two touching structures: bone (>= 300 HU) and the soft tissue next to
    // it (0..300 HU) inside a box, so they share a long boundary.
    truth_ = new Volume<uint16_t>;
    truth_->grid = series->image.grid;
    truth_->data.assign(truth_->grid.VoxelCount(), 0);
    for (int64_t k = 0; k < truth_->grid.size[2]; ++k) {
      for (int64_t j = 150; j < 350; ++j) {
        for (int64_t i = 150; i < 350; ++i) {
          const float hu = series->image.at(i, j, k);
          if (hu >= 300) {
            truth_->at(i, j, k) = 1;
          } else if (hu >= 0) {
            truth_->at(i, j, k) = 2;
          }
        }
      }
    }
  }
  static void TearDownTestSuite() { delete truth_; }

  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice_fill_cli_test_" + std::to_string(getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  static Volume<uint16_t>* truth_;
  fs::path dir_;
};

Volume<uint16_t>* FillCliTest::truth_ = nullptr;

TEST_F(FillCliTest, FillsEverySecondSliceOfTwoTouchingLabels) {
  const std::string labels = (dir_ / "labels.nii.gz").string();
  ASSERT_TRUE(WriteVolume(*truth_, labels).ok());
  const fs::path out = dir_ / "out";
  const fs::path report = dir_ / "report.json";
  // Only every 2nd slice is given as key; the full segmentation on the
  // others is the ground truth they are compared with.
  const CommandResult r = RunCli("fill " + labels + " --reference " + kPhantom +
                                 " --key-slices 0-27:" + std::to_string(kStep) +
                                 " --method " + std::string(kMethod) +
                                 " --threads 2 "
                                 "--mesh stl,ply --volume nii,nrrd --out " +
                                 out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;

  absl::StatusOr<Volume<float>> filled =
      ReadVolumeAsFloat((out / "labels.nrrd").string());
  ASSERT_TRUE(filled.ok()) << filled.status();
  ASSERT_EQ(filled->grid.size, truth_->grid.size);
  for (int a = 0; a < 3; ++a) {
    EXPECT_NEAR(filled->grid.origin[a], truth_->grid.origin[a], 1e-3);
  }
  // Dice per label on the withheld slices, of the fill and of the
  // nearest-slice copy (the baseline a fill must beat).
  int64_t both[3] = {0, 0, 0}, count_truth[3] = {0, 0, 0},
          count_out[3] = {0, 0, 0}, both_copy[3] = {0, 0, 0},
          count_copy[3] = {0, 0, 0};
  const int64_t plane = truth_->grid.SliceVoxelCount();
  for (int64_t k = 0; k < truth_->grid.size[2]; ++k) {
    const int64_t nearest =
        std::min<int64_t>(27 / kStep * kStep, (k + kStep / 2) / kStep * kStep);
    for (int64_t p = 0; p < plane; ++p) {
      const int t = truth_->data[k * plane + p];
      const int o = static_cast<int>(filled->data[k * plane + p]);
      const int c = truth_->data[nearest * plane + p];
      if (k % kStep == 0) {
        ASSERT_EQ(o, t) << "key slice " << k << " changed at pixel " << p;
        continue;
      }
      if (k > 27 / kStep * kStep) continue;
      ++count_truth[t];
      ++count_out[o];
      ++count_copy[c];
      if (t == o) ++both[t];
      if (t == c) ++both_copy[t];
    }
  }
  for (int l : {1, 2}) {
    const double dice =
        2.0 * both[l] / static_cast<double>(count_truth[l] + count_out[l]);
    const double dice_copy =
        2.0 * both_copy[l] /
        static_cast<double>(count_truth[l] + count_copy[l]);
    std::printf("label %d: Dice fill %.3f, nearest-slice copy %.3f\n", l, dice,
                dice_copy);
    EXPECT_GT(dice, dice_copy) << "label " << l;
  }

  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  ASSERT_EQ(j["labels"].size(), 2u);
  EXPECT_EQ(j["labels"][0]["label"], 1);
  EXPECT_EQ(j["method"], "direct");
  EXPECT_EQ(j["grid"]["size"][2], truth_->grid.size[2]);
  for (int l : {1, 2}) {
    ::interslice::testing::TriangleSoup soup;
    const std::string stl =
        (out / ("label-" + std::to_string(l) + ".stl")).string();
    ASSERT_TRUE(::interslice::testing::ReadBinaryStl(stl, soup)) << stl;
    const ::interslice::testing::MeshTopology topology =
        ::interslice::testing::AnalyzeSoup(soup);
    EXPECT_EQ(topology.boundary_edges, 0) << "label " << l;
    EXPECT_TRUE(fs::exists(out / ("label-" + std::to_string(l) + ".ply")));
  }
}

TEST_F(FillCliTest, BadInputGivesOneLineAndExitCodeOne) {
  // A label map on another grid (one slice fewer), a non-label value, a
  // label that is not drawn, a bad key slice list.
  Volume<uint16_t> short_map = *truth_;
  short_map.grid.size[2] -= 1;
  short_map.data.resize(short_map.grid.VoxelCount());
  const std::string short_path = (dir_ / "short.nrrd").string();
  ASSERT_TRUE(WriteVolume(short_map, short_path).ok());
  const std::string good = (dir_ / "good.nrrd").string();
  ASSERT_TRUE(WriteVolume(*truth_, good).ok());
  Volume<float> fractional;
  fractional.grid = truth_->grid;
  fractional.data.assign(fractional.grid.VoxelCount(), 0.0f);
  fractional.data[1000] = 0.5f;
  const std::string fractional_path = (dir_ / "fractional.nrrd").string();
  ASSERT_TRUE(WriteVolume(fractional, fractional_path).ok());
  const std::string out = " --out " + (dir_ / "out").string();
  const std::string unknown_label = (dir_ / "unknown-label.csv").string();
  std::ofstream(unknown_label) << "1,Bone\n9,Nothing\n";
  const std::string bad_colour = (dir_ / "bad-colour.csv").string();
  std::ofstream(bad_colour) << "label,name,R,G,B\n1,Bone,300,0,0\n";
  struct Case {
    std::string args;
    std::string message;
  };
  const Case cases[] = {
      {"fill " + short_path + " --reference " + kPhantom + out,
       "the label map is 512 x 512 x 27 voxels"},
      {"fill " + fractional_path + " --reference " + kPhantom + out,
       "holds 0.5"},
      {"fill " + good + " --reference " + kPhantom + " --labels 1,9" + out,
       "label 9 is not drawn"},
      {"fill " + good + " --reference " + kPhantom + " --key-slices 0-x" + out,
       "--key-slices"},
      {"fill " + good + " --reference " + kPhantom + " --key-slices 0,99" + out,
       "key slice 99 is outside"},
      {"fill " + good + " --reference " + kPhantom + " --method magic" + out,
       "--method"},
      {"fill " + good + out, "--reference"},
      {"fill " + good + " --reference " + kPhantom +
           " --rtstruct --no-rtstruct" + out,
       "--rtstruct excludes --no-rtstruct"},
      {"fill " + good + " --reference " + kPhantom + " --seg --uid-root 1.02" +
           out,
       "--uid-root"},
      // Label names: the wrong kind of file, a label the map does not hold,
      // a bad row, a missing file.
      {"fill " + good + " --reference " + kPhantom +
           " --label-names names.xlsx" + out,
       "--label-names: must name a colour table (.csv, .txt) or a JSON "
       "sidecar (.json)"},
      {"fill " + good + " --reference " + kPhantom + " --label-names " +
           unknown_label + out,
       "name label 9, which the label map does not hold (labels: 1, 2)"},
      {"fill " + good + " --reference " + kPhantom + " --label-names " +
           bad_colour + out,
       "bad-colour.csv line 2: colour component '300' is not an integer "
       "0..255"},
      {"fill " + good + " --reference " + kPhantom + " --label-names " +
           (dir_ / "none.csv").string() + out,
       "cannot read the label names none.csv"},
      // The detached form needs a server.
      {"fill " + good + " --reference " + kPhantom + " --submit",
       "--submit needs --server ADDR"},
      {"fill " + good + " --reference " + kPhantom, "--out"},
  };
  for (const Case& c : cases) {
    const CommandResult r = RunCli(c.args);
    EXPECT_EQ(r.exit_code, 1) << c.args << "\n" << r.out;
    EXPECT_THAT(r.out, HasSubstr(c.message)) << c.args;
    EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << c.args << "\n"
                                                               << r.out;
  }
  EXPECT_FALSE(fs::exists(dir_ / "out" / "labels.nii.gz"));
}

// A binary SEG written by `interslice run --seg` (one segment, a frame per
// slice of its intensity series) read back as a label map, and filled.
TEST_F(FillCliTest, ReadsAndFillsADicomSeg) {
  const fs::path run = dir_ / "run";
  const std::string small =
      std::string(::interslice::testing::SourceDir()) + "/tests/data/ct-thick";
  CommandResult r = RunCli("run " + small +
                           " --threshold 300 --roi 200,40,0,296,136,4 "
                           "--method direct --factor 5 --seg --volume nrrd "
                           "--mesh none --quiet --out " +
                           run.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  absl::StatusOr<DicomSeries> series = ReadDicomSeries(
      {(run / "series-intensity").string()}, {}, ComputeContext{.threads = 1});
  ASSERT_TRUE(series.ok()) << series.status();
  ReferenceSeries reference{series->image.grid, series->series_instance_uid,
                            series->frame_of_reference_uid};
  const std::string seg_path = (run / "seg.dcm").string();
  absl::StatusOr<SegmentationInput> seg =
      ReadDicomSegmentation(seg_path, reference);
  ASSERT_TRUE(seg.ok()) << seg.status();
  EXPECT_FALSE(seg->fractional);
  ASSERT_EQ(seg->segments.size(), 1u);
  EXPECT_EQ(seg->segments[0].number, 1);
  absl::StatusOr<Volume<float>> mask =
      ReadVolumeAsFloat((run / "mask.nrrd").string());
  ASSERT_TRUE(mask.ok()) << mask.status();
  ASSERT_EQ(mask->data.size(), seg->labels.data.size());
  int64_t set = 0;
  for (size_t n = 0; n < mask->data.size(); ++n) {
    ASSERT_EQ(seg->labels.data[n], mask->data[n] > 0.5f ? 1 : 0) << n;
    set += seg->labels.data[n];
  }
  EXPECT_GT(set, 100);

  // Another frame of reference, another series, a shifted grid.
  ReferenceSeries other = reference;
  other.frame_of_reference_uid = "1.2.3";
  EXPECT_THAT(ReadDicomSegmentation(seg_path, other).status().message(),
              HasSubstr("FrameOfReferenceUID"));
  other = reference;
  other.series_instance_uid = "1.2.3";
  EXPECT_THAT(ReadDicomSegmentation(seg_path, other).status().message(),
              HasSubstr("references another series"));
  other = reference;
  other.grid.origin = other.grid.IndexToPhysical({0, 0, 0.5});
  EXPECT_THAT(ReadDicomSegmentation(seg_path, other).status().message(),
              HasSubstr("is not on a slice of the reference series"));
  other = reference;
  other.grid.size[0] += 1;
  EXPECT_THAT(ReadDicomSegmentation(seg_path, other).status().message(),
              HasSubstr("pixels"));
  EXPECT_FALSE(
      ReadDicomSegmentation((run / "series-intensity" / "IM00001.dcm").string(),
                            reference)
          .ok());

  // The CLI takes the SEG directly; every 5th slice is a key slice.
  const fs::path out = dir_ / "fill";
  const fs::path report = dir_ / "fill.json";
  r = RunCli("fill " + seg_path + " --reference " +
             (run / "series-intensity").string() +
             " --key-slices 0-15:5 --method direct --mesh none --volume nrrd "
             "--out " +
             out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  absl::StatusOr<Volume<float>> filled =
      ReadVolumeAsFloat((out / "labels.nrrd").string());
  ASSERT_TRUE(filled.ok()) << filled.status();
  const int64_t plane = filled->grid.SliceVoxelCount();
  for (int64_t k = 0; k < filled->grid.size[2]; k += 5) {
    for (int64_t p = 0; p < plane; ++p) {
      ASSERT_EQ(filled->data[k * plane + p],
                static_cast<float>(seg->labels.data[k * plane + p]));
    }
  }
  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  EXPECT_EQ(j["input"], "seg-binary");
  EXPECT_EQ(j["segments"].size(), 1u);
}

// --- DICOM outputs: SEG and RTSTRUCT ---

ReferenceSeries ReferenceOf(const std::string& folder) {
  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries({folder}, {}, ComputeContext{.threads = 1});
  EXPECT_TRUE(series.ok()) << series.status();
  if (!series.ok()) return {};
  return {series->image.grid, series->series_instance_uid,
          series->frame_of_reference_uid};
}

// Voxels where `a` and `b` differ (after mapping b's values with `map`).
int64_t CountDiffering(const std::vector<uint16_t>& a,
                       const std::vector<float>& b,
                       const std::map<int, int>& map = {}) {
  EXPECT_EQ(a.size(), b.size());
  int64_t differ = 0;
  for (size_t n = 0; n < std::min(a.size(), b.size()); ++n) {
    int v = a[n];
    if (auto it = map.find(v); it != map.end()) v = it->second;
    differ += v != static_cast<int>(b[n]);
  }
  return differ;
}

TEST_F(FillCliTest, WritesSegAndRtStructOfALabelMap) {
  const std::string labels = (dir_ / "labels.nii.gz").string();
  ASSERT_TRUE(WriteVolume(*truth_, labels).ok());
  const fs::path out = dir_ / "out";
  const fs::path report = dir_ / "report.json";
  const CommandResult r =
      RunCli("fill " + labels + " --reference " + kPhantom +
             " --key-slices 0-27:3 --method linear --mesh none --volume nrrd "
             "--seg --rtstruct --threads 2 --quiet --out " +
             out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const std::string seg = (out / "seg.dcm").string();
  const std::string rt = (out / "rtstruct.dcm").string();
  ::interslice::testing::ExpectValidIod({seg, rt});
  absl::StatusOr<Volume<float>> filled =
      ReadVolumeAsFloat((out / "labels.nrrd").string());
  ASSERT_TRUE(filled.ok()) << filled.status();
  int64_t labelled = 0;
  for (float v : filled->data) labelled += v != 0;
  ASSERT_GT(labelled, 1000);

  // The SEG references the reference series and reads back exactly.
  const ReferenceSeries reference = ReferenceOf(kPhantom);
  auto file = ::interslice::testing::LoadDicom(seg);
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(::interslice::testing::GetString(ds, DCM_FrameOfReferenceUID),
            reference.frame_of_reference_uid);
  DcmItem* series_item = nullptr;
  ASSERT_TRUE(
      ds.findAndGetSequenceItem(DCM_ReferencedSeriesSequence, series_item, 0)
          .good());
  EXPECT_EQ(
      ::interslice::testing::GetString(*series_item, DCM_SeriesInstanceUID),
      reference.series_instance_uid);
  absl::StatusOr<SegmentationInput> back =
      ReadDicomSegmentation(seg, reference);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(CountDiffering(back->labels.data, filled->data), 0);
  ASSERT_EQ(back->segments.size(), 2u);
  EXPECT_EQ(back->segments[0].label, "Label 1");
  EXPECT_EQ(back->segments[1].label, "Label 2");
  EXPECT_EQ(back->segments[0].category.value, "85756007");
  ASSERT_TRUE(back->segments[0].cielab.has_value());
  ASSERT_TRUE(back->segments[1].cielab.has_value());
  EXPECT_NE(*back->segments[0].cielab, *back->segments[1].cielab);

  // The RTSTRUCT reads back as the filled labels up to rasterisation.
  absl::StatusOr<SegmentationInput> contours = ReadRtStruct(rt, reference);
  ASSERT_TRUE(contours.ok()) << contours.status();
  const int64_t differ = CountDiffering(contours->labels.data, filled->data);
  std::printf("RTSTRUCT read back: %lld of %lld labelled voxels differ\n",
              static_cast<long long>(differ), static_cast<long long>(labelled));
  EXPECT_LE(differ, labelled / 1000);
  ASSERT_EQ(contours->segments.size(), 2u);
  EXPECT_EQ(contours->segments[0].number, 1);
  EXPECT_EQ(contours->segments[0].label, "Label 1");

  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  int dicom_artifacts = 0;
  for (const auto& a : j["artifacts"]) {
    dicom_artifacts += a["kind"] == "seg" || a["kind"] == "rtstruct";
  }
  EXPECT_EQ(dicom_artifacts, 2);
  EXPECT_EQ(j["polygon_key_slices"], 0);
}

// The study, frame of reference and SOP Instance UID of a written object.
std::array<std::string, 3> StudyFrameInstance(const fs::path& file) {
  auto loaded = ::interslice::testing::LoadDicom(file.string());
  DcmDataset& ds = *loaded->getDataset();
  return {::interslice::testing::GetString(ds, DCM_StudyInstanceUID),
          ::interslice::testing::GetString(ds, DCM_FrameOfReferenceUID),
          ::interslice::testing::GetString(ds, DCM_SOPInstanceUID)};
}

// Issue 26: `run` and `fill` of one anonymised series (SOP Instance, Study
// Instance and Frame of Reference UIDs blanked; the file meta headers kept)
// land in one study with one frame of reference, a rerun names everything
// the same, and another series gets another study.
TEST_F(FillCliTest, AnonymisedSeriesKeepsOneStudyForRunAndFill) {
  const auto strip = [&](const fs::path& from, const fs::path& to) {
    fs::create_directories(to);
    for (const auto& entry : fs::directory_iterator(from)) {
      if (entry.path().extension() != ".dcm") continue;
      DcmFileFormat file;
      ASSERT_TRUE(file.loadFile(entry.path().c_str()).good());
      ASSERT_TRUE(file.loadAllDataIntoMemory().good());
      for (const DcmTagKey& tag : {DCM_SOPInstanceUID, DCM_StudyInstanceUID,
                                   DCM_FrameOfReferenceUID}) {
        file.getDataset()->findAndDeleteElement(tag);
      }
      ASSERT_TRUE(file.saveFile((to / entry.path().filename()).c_str()).good());
    }
  };
  const fs::path anonymous = dir_ / "anonymous";
  const fs::path other = dir_ / "other";
  strip(fs::path(::interslice::testing::TestDataDir()) / "ct-thick", anonymous);
  strip(fs::path(::interslice::testing::TestDataDir()) / "ct-tilt", other);
  // A label map on the series' own grid: a run at factor 1 gives one.
  const fs::path labels_run = dir_ / "labels-run";
  ASSERT_EQ(RunCli("run " + anonymous.string() +
                   " --threshold 300 --factor 1 --method linear --mesh none "
                   "--previews none --quiet --out " +
                   labels_run.string())
                .exit_code,
            0);
  const auto run = [&](const fs::path& input, const std::string& out) {
    const CommandResult r = RunCli(
        "run " + input.string() +
        " --threshold 300 --method linear --intensity-method linear "
        "--seg --mesh none --volume none --previews none --quiet --out " +
        (dir_ / out).string());
    EXPECT_EQ(r.exit_code, 0) << r.out;
    return StudyFrameInstance(dir_ / out / "seg.dcm");
  };
  const auto fill = [&](const std::string& out) {
    const CommandResult r =
        RunCli("fill " + (labels_run / "mask.nii.gz").string() +
               " --reference " + anonymous.string() +
               " --method linear --seg --mesh none --volume none --previews "
               "none --quiet --out " +
               (dir_ / out).string());
    EXPECT_EQ(r.exit_code, 0) << r.out;
    return StudyFrameInstance(dir_ / out / "seg.dcm");
  };
  const std::array<std::string, 3> run1 = run(anonymous, "run1");
  const std::array<std::string, 3> run2 = run(anonymous, "run2");
  const std::array<std::string, 3> fill1 = fill("fill1");
  const std::array<std::string, 3> fill2 = fill("fill2");
  const std::array<std::string, 3> tilt = run(other, "other");
  EXPECT_FALSE(run1[0].empty());
  EXPECT_FALSE(run1[1].empty());
  EXPECT_EQ(fill1[0], run1[0]);  // one study
  EXPECT_EQ(fill1[1], run1[1]);  // one frame of reference
  EXPECT_NE(fill1[2], run1[2]);  // two objects
  EXPECT_EQ(run2, run1);         // a rerun replaces, never duplicates
  EXPECT_EQ(fill2, fill1);
  EXPECT_NE(tilt[0], run1[0]);
  EXPECT_NE(tilt[1], run1[1]);
}

// --label-names: a colour table names the labels of a label map; the names,
// colours and codes reach the SEG's segments and the RTSTRUCT's ROIs.
TEST_F(FillCliTest, LabelNamesReachSegAndRtStruct) {
  const std::string labels = (dir_ / "labels.nii.gz").string();
  ASSERT_TRUE(WriteVolume(*truth_, labels).ok());
  const std::string names = (dir_ / "names.csv").string();
  std::ofstream(names) << "label,name,R,G,B,code\n"
                          "1,Skull,255,250,220,SCT^89546000^Bone of cranium\n"
                          "2,Scalp,200,120,100\n";
  const fs::path out = dir_ / "out";
  const CommandResult r = RunCli(
      "fill " + labels + " --reference " + kPhantom +
      " --key-slices 0-27:3 --method linear --mesh none --volume nrrd --seg "
      "--rtstruct --label-names " +
      names + " --threads 2 --quiet --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const ReferenceSeries reference = ReferenceOf(kPhantom);
  absl::StatusOr<SegmentationInput> seg =
      ReadDicomSegmentation((out / "seg.dcm").string(), reference);
  ASSERT_TRUE(seg.ok()) << seg.status();
  ASSERT_EQ(seg->segments.size(), 2u);
  EXPECT_EQ(seg->segments[0].label, "Skull");
  EXPECT_EQ(seg->segments[0].type.value, "89546000");
  EXPECT_EQ(seg->segments[0].type.meaning, "Bone of cranium");
  EXPECT_EQ(seg->segments[1].label, "Scalp");
  absl::StatusOr<SegmentationInput> rt =
      ReadRtStruct((out / "rtstruct.dcm").string(), reference);
  ASSERT_TRUE(rt.ok()) << rt.status();
  ASSERT_EQ(rt->segments.size(), 2u);
  EXPECT_EQ(rt->segments[0].number, 1);
  EXPECT_EQ(rt->segments[0].label, "Skull");
  EXPECT_EQ(*rt->segments[0].rgb, (std::array<uint8_t, 3>{255, 250, 220}));
  EXPECT_EQ(rt->segments[1].label, "Scalp");
  EXPECT_EQ(*rt->segments[1].rgb, (std::array<uint8_t, 3>{200, 120, 100}));

  // A SEG names its segments itself: label names are refused, nothing
  // written.
  const CommandResult refused =
      RunCli("fill " + (out / "seg.dcm").string() + " --reference " + kPhantom +
             " --label-names " + names + " --out " + (dir_ / "again").string());
  EXPECT_EQ(refused.exit_code, 1) << refused.out;
  EXPECT_THAT(refused.out,
              HasSubstr("label names are for a label map; a SEG or RTSTRUCT "
                        "names its segments itself"));
  EXPECT_FALSE(fs::exists(dir_ / "again" / "seg.dcm"));
}

// An RTSTRUCT drawn on the phantom: two ROIs (a ring, i.e. a polygon with a
// hole, and a disc), contours on every 3rd slice, growing with the slice.
std::string WritePhantomRtStruct(const fs::path& dir,
                                 const ReferenceSeries& reference) {
  const Grid& g = reference.grid;
  DcmFileFormat file;
  DcmDataset* d = file.getDataset();
  d->putAndInsertString(DCM_SOPClassUID, UID_RTStructureSetStorage);
  d->putAndInsertString(DCM_SOPInstanceUID, "1.2.826.0.1.3680043.2.1125.7");
  d->putAndInsertString(DCM_Modality, "RTSTRUCT");
  d->putAndInsertString(DCM_StructureSetLabel, "test");
  const auto circle = [&](double ci, double cj, double r, int64_t k) {
    std::vector<std::string> values;
    for (int n = 0; n < 120; ++n) {
      const double t = 2 * std::numbers::pi * n / 120;
      const Vec3 p = g.IndexToPhysical(
          {ci + r * std::cos(t), cj + r * std::sin(t), static_cast<double>(k)});
      for (int c = 0; c < 3; ++c) values.push_back(absl::StrCat(p[c]));
    }
    return absl::StrJoin(values, "\\");
  };
  struct Roi {
    int number;
    const char* name;
    const char* colour;
  };
  for (const Roi& roi :
       {Roi{4, "ring", "200\\100\\50"}, Roi{9, "disc", "0\\255\\0"}}) {
    DcmItem* item = nullptr;
    d->findOrCreateSequenceItem(DCM_StructureSetROISequence, item, -2);
    item->putAndInsertString(DCM_ROINumber, std::to_string(roi.number).c_str());
    item->putAndInsertString(DCM_ROIName, roi.name);
    item->putAndInsertString(DCM_ReferencedFrameOfReferenceUID,
                             reference.frame_of_reference_uid.c_str());
    item->putAndInsertString(DCM_ROIGenerationAlgorithm, "MANUAL");
    DcmItem* contours = nullptr;
    d->findOrCreateSequenceItem(DCM_ROIContourSequence, contours, -2);
    contours->putAndInsertString(DCM_ReferencedROINumber,
                                 std::to_string(roi.number).c_str());
    contours->putAndInsertString(DCM_ROIDisplayColor, roi.colour);
    for (int64_t k = 0; k < g.size[2]; k += 3) {
      std::vector<std::string> polygons;
      if (roi.number == 4) {
        polygons = {circle(250.3, 260.6, 60 + 2.1 * k, k),
                    circle(250.3, 260.6, 25 + 0.7 * k, k)};
      } else {
        polygons = {circle(420.2, 140.7, 20 + 1.3 * k, k)};
      }
      for (const std::string& data : polygons) {
        DcmItem* contour = nullptr;
        contours->findOrCreateSequenceItem(DCM_ContourSequence, contour, -2);
        contour->putAndInsertString(DCM_ContourGeometricType, "CLOSED_PLANAR");
        contour->putAndInsertString(DCM_NumberOfContourPoints, "120");
        contour->putAndInsertString(DCM_ContourData, data.c_str());
      }
    }
  }
  const std::string path = (dir / "input-rtstruct.dcm").string();
  EXPECT_TRUE(file.saveFile(path.c_str(), EXS_LittleEndianExplicit).good());
  return path;
}

TEST_F(FillCliTest, RtStructInIsFilledFromItsPolygonsAndWrittenBack) {
  const ReferenceSeries reference = ReferenceOf(kPhantom);
  const std::string input = WritePhantomRtStruct(dir_, reference);
  absl::StatusOr<SegmentationInput> drawn = ReadRtStruct(input, reference);
  ASSERT_TRUE(drawn.ok()) << drawn.status();
  const fs::path out = dir_ / "out";
  const fs::path report = dir_ / "report.json";
  // No --rtstruct: it is the default for RTSTRUCT input.
  const CommandResult r =
      RunCli("fill " + input + " --reference " + kPhantom +
             " --method linear --mesh none --volume nrrd --seg --threads 2 "
             "--quiet --out " +
             out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const std::string seg = (out / "seg.dcm").string();
  const std::string rt = (out / "rtstruct.dcm").string();
  ::interslice::testing::ExpectValidIod({seg, rt});
  absl::StatusOr<Volume<float>> filled =
      ReadVolumeAsFloat((out / "labels.nrrd").string());
  ASSERT_TRUE(filled.ok()) << filled.status();
  const int64_t plane = reference.grid.SliceVoxelCount();
  int64_t labelled = 0;
  for (int64_t n = 0; n < static_cast<int64_t>(filled->data.size()); ++n) {
    labelled += filled->data[n] != 0;
    if ((n / plane) % 3 == 0) {  // key slices exactly as drawn
      ASSERT_EQ(filled->data[n], drawn->labels.data[n]) << n;
    }
  }

  // RTSTRUCT out: ROI numbers, names and colours of the input.
  absl::StatusOr<SegmentationInput> rois = ReadRtStruct(rt, reference);
  ASSERT_TRUE(rois.ok()) << rois.status();
  ASSERT_EQ(rois->segments.size(), 2u);
  EXPECT_EQ(rois->segments[0].number, 4);
  EXPECT_EQ(rois->segments[0].label, "ring");
  EXPECT_EQ(rois->segments[1].number, 9);
  EXPECT_EQ(rois->segments[1].label, "disc");
  ASSERT_TRUE(rois->segments[1].rgb.has_value());
  EXPECT_EQ(*rois->segments[1].rgb, (std::array<uint8_t, 3>{0, 255, 0}));
  const int64_t differ = CountDiffering(rois->labels.data, filled->data);
  std::printf("RTSTRUCT read back: %lld of %lld labelled voxels differ\n",
              static_cast<long long>(differ), static_cast<long long>(labelled));
  EXPECT_LE(differ, labelled / 1000);

  // SEG out: segments 1, 2 = ROIs 4, 9 with their names; exact labels.
  absl::StatusOr<SegmentationInput> segments =
      ReadDicomSegmentation(seg, reference);
  ASSERT_TRUE(segments.ok()) << segments.status();
  ASSERT_EQ(segments->segments.size(), 2u);
  EXPECT_EQ(segments->segments[0].label, "ring");
  EXPECT_EQ(segments->segments[1].label, "disc");
  EXPECT_EQ(
      CountDiffering(segments->labels.data, filled->data, {{1, 4}, {2, 9}}), 0);

  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  EXPECT_EQ(j["input"], "rtstruct");
  // Every drawn key slice of both ROIs took its polygons' distance.
  EXPECT_EQ(j["polygon_key_slices"], 2 * ((reference.grid.size[2] + 2) / 3));
}

// Issue 44: an RTSTRUCT whose contour image references resolve to no image
// of the reference series was matched by position without a word
// ("warnings": []). Made here from an RTSTRUCT the CLI writes (whose
// references do resolve) by pointing them nowhere.
TEST_F(FillCliTest, RtStructImageReferencesNamingNoImageAreAWarning) {
  const std::string labels = (dir_ / "labels.nii.gz").string();
  ASSERT_TRUE(WriteVolume(*truth_, labels).ok());
  const std::string common =
      " --reference " + kPhantom +
      " --method linear --mesh none --volume nrrd --threads 2 --quiet --out ";
  const fs::path written = dir_ / "written";
  CommandResult r = RunCli("fill " + labels + " --key-slices 0-27:3" + common +
                           written.string() + " --rtstruct");
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const std::string resolving = (written / "rtstruct.dcm").string();

  // Every contour's ContourImageSequence > ReferencedSOPInstanceUID
  // rewritten to a UID no image has.
  auto file = ::interslice::testing::LoadDicom(resolving);
  DcmDataset& ds = *file->getDataset();
  int64_t references = 0;
  DcmItem* roi = nullptr;
  for (int n = 0;
       ds.findAndGetSequenceItem(DCM_ROIContourSequence, roi, n).good(); ++n) {
    DcmItem* contour = nullptr;
    for (int c = 0;
         roi->findAndGetSequenceItem(DCM_ContourSequence, contour, c).good();
         ++c) {
      DcmItem* image = nullptr;
      for (int i = 0;
           contour->findAndGetSequenceItem(DCM_ContourImageSequence, image, i)
               .good();
           ++i) {
        const std::string nowhere =
            absl::StrCat("1.2.826.0.1.3680043.2.1125.44.", ++references);
        ASSERT_TRUE(image
                        ->putAndInsertString(DCM_ReferencedSOPInstanceUID,
                                             nowhere.c_str())
                        .good());
      }
    }
  }
  ASSERT_GT(references, 0) << "the CLI's RTSTRUCT references no image";
  const std::string nowhere = (dir_ / "nowhere.dcm").string();
  ASSERT_TRUE(file->saveFile(nowhere.c_str(), EXS_LittleEndianExplicit).good());

  const auto warnings_of = [](const fs::path& report) {
    std::ifstream in(report);
    return nlohmann::json::parse(in)["warnings"];
  };
  // The CLI's own RTSTRUCT: its references resolve, nothing to say.
  r = RunCli("fill " + resolving + common + (dir_ / "resolving").string() +
             " --report " + (dir_ / "resolving.json").string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_EQ(warnings_of(dir_ / "resolving.json"), nlohmann::json::array());
  EXPECT_THAT(r.out, ::testing::Not(HasSubstr("warning")));

  // References pointing nowhere: still filled (by position), with one
  // warning in the report and on stderr that counts them, naming no UID.
  r = RunCli("fill " + nowhere + common + (dir_ / "out").string() +
             " --report " + (dir_ / "report.json").string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const nlohmann::json warnings = warnings_of(dir_ / "report.json");
  ASSERT_EQ(warnings.size(), 1u) << warnings.dump();
  const std::string warning = warnings[0].get<std::string>();
  EXPECT_THAT(warning,
              HasSubstr(absl::StrFormat("%d of the RTSTRUCT's %d contour image "
                                        "references name no image",
                                        references, references)));
  EXPECT_THAT(warning, HasSubstr("by position"));
  EXPECT_THAT(warning, ::testing::Not(HasSubstr("1.2.826")));
  EXPECT_THAT(r.out, HasSubstr("interslice: warning: " + warning));
  // Matched by position, the same labels as from the resolving RTSTRUCT.
  absl::StatusOr<Volume<float>> a =
      ReadVolumeAsFloat((dir_ / "resolving" / "labels.nrrd").string());
  absl::StatusOr<Volume<float>> b =
      ReadVolumeAsFloat((dir_ / "out" / "labels.nrrd").string());
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->data, b->data);
}

TEST_F(FillCliTest, SegOnAFinerGridReferencesADerivedIntensitySeries) {
  const std::string small =
      std::string(::interslice::testing::SourceDir()) + "/tests/data/ct-thick";
  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries({small}, {}, ComputeContext{.threads = 1});
  ASSERT_TRUE(series.ok()) << series.status();
  Volume<uint16_t> labels;
  labels.grid = series->image.grid;
  labels.data.assign(labels.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < labels.grid.size[2]; ++k) {
    for (int64_t j = 100; j < 400; ++j) {
      for (int64_t i = 100; i < 400; ++i) {
        if (series->image.at(i, j, k) >= 300) labels.at(i, j, k) = 1;
      }
    }
  }
  const std::string path = (dir_ / "labels.nrrd").string();
  ASSERT_TRUE(WriteVolume(labels, path).ok());
  const fs::path out = dir_ / "out";
  const CommandResult r =
      RunCli("fill " + path + " --reference " + small +
             " --factor 2 --method linear --mesh none --volume nrrd --seg "
             "--quiet --out " +
             out.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_FALSE(fs::exists(out / "rtstruct.dcm"));  // not by default here
  const std::string seg = (out / "seg.dcm").string();
  ::interslice::testing::ExpectValidIod({seg});
  const ReferenceSeries derived =
      ReferenceOf((out / "series-intensity").string());
  absl::StatusOr<Volume<float>> filled =
      ReadVolumeAsFloat((out / "labels.nrrd").string());
  ASSERT_TRUE(filled.ok()) << filled.status();
  ASSERT_EQ(derived.grid.size, filled->grid.size);
  EXPECT_EQ(derived.frame_of_reference_uid,
            ReferenceOf(small).frame_of_reference_uid);
  absl::StatusOr<SegmentationInput> back = ReadDicomSegmentation(seg, derived);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(CountDiffering(back->labels.data, filled->data), 0);
}

}  // namespace
}  // namespace interslice

namespace interslice {
namespace {

// Previews of a fill: each label outlined in its segment colour, the PNGs
// and a valid Secondary Capture series in the reference's study; a fill of
// one label previews too.
TEST_F(FillCliTest, PreviewsOutlineEachLabelInItsColour) {
  const std::string labels = (dir_ / "labels.nii.gz").string();
  ASSERT_TRUE(WriteVolume(*truth_, labels).ok());
  const fs::path out = dir_ / "out";
  const fs::path report = dir_ / "report.json";
  const CommandResult r =
      RunCli("fill " + labels + " --reference " + kPhantom +
             " --key-slices 0-27:4 --method linear --seg --previews png,dicom "
             "--mesh none --volume none --threads 2 --out " +
             out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  for (const char* name :
       {"axial.png", "coronal.png", "sagittal.png", "3d-front.png"}) {
    EXPECT_TRUE(fs::exists(out / "previews" / name)) << name;
  }
  std::vector<std::string> dicom;
  for (int n = 1; n <= 4; ++n) {
    dicom.push_back(
        (out / "previews-dicom" / absl::StrFormat("IM%05d.dcm", n)).string());
  }
  ::interslice::testing::ExpectValidIod(dicom);
  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  EXPECT_TRUE(j["stages"].contains("preview"));
  EXPECT_TRUE(j["previews"]["notes"].empty()) << j["previews"];

  auto seg = ::interslice::testing::LoadDicom((out / "seg.dcm").string());
  auto axial = ::interslice::testing::LoadDicom(dicom[0]);
  DcmDataset& ds = *axial->getDataset();
  EXPECT_EQ(::interslice::testing::GetString(ds, DCM_StudyInstanceUID),
            ::interslice::testing::GetString(*seg->getDataset(),
                                             DCM_StudyInstanceUID));
  EXPECT_THAT(::interslice::testing::GetString(ds, DCM_ImageComments),
              HasSubstr("axial"));
  // Both labels' colours are drawn (a 1.5 pixel line covers some pixels
  // whole, which then hold the exact colour).
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  const Uint8* pixels = nullptr;
  ASSERT_TRUE(ds.findAndGetUint8Array(DCM_PixelData, pixels).good());
  for (int label : {1, 2}) {
    const std::array<uint8_t, 3> rgb = SegmentRgb(DefaultLabelSegment(label));
    int exact = 0;
    for (size_t p = 0; p < static_cast<size_t>(rows) * columns; ++p) {
      exact += pixels[3 * p] == rgb[0] && pixels[3 * p + 1] == rgb[1] &&
               pixels[3 * p + 2] == rgb[2];
    }
    EXPECT_GT(exact, 50) << "label " << label;
  }

  // One label only (the soft tissue, as label 1): previews too, no note.
  Volume<uint16_t> one = *truth_;
  for (uint16_t& v : one.data) v = v == 2 ? 1 : 0;
  const std::string one_path = (dir_ / "one.nii.gz").string();
  ASSERT_TRUE(WriteVolume(one, one_path).ok());
  const CommandResult single =
      RunCli("fill " + one_path + " --reference " + kPhantom +
             " --key-slices 0-27:4 --method linear --mesh none --volume none "
             "--threads 2 --out " +
             (dir_ / "one").string());
  ASSERT_EQ(single.exit_code, 0) << single.out;
  EXPECT_TRUE(fs::exists(dir_ / "one" / "previews" / "3d-front.png"));
  EXPECT_THAT(single.out, ::testing::Not(HasSubstr("warning")));
}

}  // namespace
}  // namespace interslice
