#include "core/dicom_out/dicom_writer.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/series_reader.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/temp_dir.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmfg/fginterface.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"
#include "dcmtk/dcmseg/segutils.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::StartsWith;

const fs::path kThick = fs::path(INTERSLICE_TEST_DATA_DIR) / "ct-thick";
constexpr char kDciodvfy[] = "/usr/bin/dciodvfy";
constexpr char kTestRoot[] = "1.2.826.0.1.3680043.10.1234";

// A fresh folder per test, removed afterwards.
class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_dicom_out_") {}
};

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

// The real 4-slice CT (5 mm apart), an output grid through part of it (a
// 64x64 in-plane crop, 1 mm slices over the whole 15 mm), a sphere's signed
// distance and mask on that grid, and the CT resampled onto it.
class DicomWriterTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    // The reader meets tests/data/ct-thick/LICENSE; DCMTK would print a line
    // about it.
    QuietDicomToolkitLogging();
    auto series = ReadDicomSeries({kThick.string()}, {}, {});
    ASSERT_TRUE(series.ok()) << series.status();
    source_ = new DicomSeries(*std::move(series));
    const Grid& in = source_->image.grid;
    Grid grid = CropGrid(in, VoxelBox{{224, 200, 0}, {288, 264, 1}});
    grid.spacing[2] = 1.0;
    grid.size[2] = static_cast<int64_t>(std::lround(
                       (in.size[2] - 1) * in.spacing[2] / grid.spacing[2])) +
                   1;
    grid_ = new Grid(grid);
  }
  static void TearDownTestSuite() {
    delete source_;
    delete grid_;
    source_ = nullptr;
    grid_ = nullptr;
  }

  static Volume<float> Distance() {
    Volume<float> d;
    d.grid = *grid_;
    d.data.resize(grid_->VoxelCount());
    const Vec3 centre = grid_->IndexToPhysical({(grid_->size[0] - 1) / 2.0,
                                                (grid_->size[1] - 1) / 2.0,
                                                (grid_->size[2] - 1) / 2.0});
    for (int64_t k = 0; k < grid_->size[2]; ++k) {
      for (int64_t j = 0; j < grid_->size[1]; ++j) {
        for (int64_t i = 0; i < grid_->size[0]; ++i) {
          const Vec3 p =
              grid_->IndexToPhysical({double(i), double(j), double(k)});
          const double r =
              std::hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]);
          d.at(i, j, k) = static_cast<float>(9.0 - r);  // radius 9 mm
        }
      }
    }
    return d;
  }
  static Volume<uint8_t> Mask(const Volume<float>& distance) {
    Volume<uint8_t> m;
    m.grid = distance.grid;
    m.data.resize(distance.data.size());
    for (size_t i = 0; i < m.data.size(); ++i) m.data[i] = distance.data[i] > 0;
    return m;
  }
  static Volume<float> ToFloat(const Volume<uint8_t>& mask) {
    Volume<float> f;
    f.grid = mask.grid;
    f.data.assign(mask.data.begin(), mask.data.end());
    return f;
  }
  static DicomWriteOptions Options() {
    DicomWriteOptions options;
    options.uid_root = kTestRoot;
    options.series_number = 901;
    return options;
  }

  static DicomSeries* source_;
  static Grid* grid_;
};

DicomSeries* DicomWriterTest::source_ = nullptr;
Grid* DicomWriterTest::grid_ = nullptr;

// dciodvfy's output lines for `path` (it writes to stderr).
std::vector<std::string> Dciodvfy(const std::string& path) {
  std::vector<std::string> lines;
  const std::string command = std::string(kDciodvfy) + " '" + path + "' 2>&1";
  FILE* pipe = ::popen(command.c_str(), "r");
  if (pipe == nullptr) return {"Error - cannot run dciodvfy"};
  char buffer[4096];
  while (std::fgets(buffer, sizeof(buffer), pipe) != nullptr) {
    std::string line(buffer);
    while (!line.empty() && (line.back() == '\n' || line.back() == '\r')) {
      line.pop_back();
    }
    lines.push_back(line);
  }
  ::pclose(pipe);
  return lines;
}

// Runs dciodvfy on every file; fails on any "Error" line, prints each
// distinct warning once.
void ExpectValidIod(const std::vector<std::string>& paths) {
  ASSERT_TRUE(fs::exists(kDciodvfy))
      << "dciodvfy (dicom3tools) missing; run scripts/install-deps.sh";
  std::set<std::string> warnings;
  for (const std::string& path : paths) {
    for (const std::string& line : Dciodvfy(path)) {
      EXPECT_THAT(line, ::testing::Not(HasSubstr("Error")))
          << fs::path(path).filename();
      if (line.find("Warning") != std::string::npos) warnings.insert(line);
    }
  }
  for (const std::string& w : warnings) {
    std::printf("dciodvfy %s: %s\n",
                paths.empty() ? "" : fs::path(paths[0]).filename().c_str(),
                w.c_str());
  }
}

std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  item.findAndGetOFStringArray(tag, value);
  return std::string(value.c_str());
}

std::unique_ptr<DcmFileFormat> Load(const std::string& path) {
  auto file = std::make_unique<DcmFileFormat>();
  EXPECT_TRUE(file->loadFile(OFFilename(path.c_str())).good()) << path;
  return file;
}

void ExpectSameGrid(const Grid& a, const Grid& b) {
  for (int c = 0; c < 3; ++c) {
    EXPECT_EQ(a.size[c], b.size[c]) << c;
    EXPECT_NEAR(a.spacing[c], b.spacing[c], 1e-4) << c;
    EXPECT_NEAR(a.origin[c], b.origin[c], 1e-4) << c;
  }
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(a.direction[i], b.direction[i], 1e-4);
}

TEST_F(DicomWriterTest, EveryOutputPassesDciodvfy) {
  TempDir dir;
  const Volume<float> distance = Distance();
  const Volume<uint8_t> mask = Mask(distance);
  auto intensity = ResampleToGrid(source_->image, *grid_, {});
  ASSERT_TRUE(intensity.ok()) << intensity.status();
  const struct {
    DerivedContent content;
    const Volume<float>* values;
  } cases[] = {{DerivedContent::kMask, nullptr},
               {DerivedContent::kDistance, &distance},
               {DerivedContent::kIntensity, &*intensity}};
  const Volume<float> mask_values = ToFloat(mask);
  for (const auto& c : cases) {
    const std::string out =
        (dir.path() / std::string(DerivedContentName(c.content))).string();
    auto paths =
        WriteDerivedSeries(*source_, c.values ? *c.values : mask_values,
                           c.content, Options(), out);
    ASSERT_TRUE(paths.ok()) << paths.status();
    ASSERT_EQ(paths->size(), static_cast<size_t>(grid_->size[2]));
    SCOPED_TRACE(DerivedContentName(c.content));
    ExpectValidIod(*paths);
  }
  const std::string seg = (dir.path() / "seg.dcm").string();
  ASSERT_TRUE(
      WriteSegmentation(*source_, mask, SegmentDescription(), Options(), seg)
          .ok());
  SCOPED_TRACE("seg");
  ExpectValidIod({seg});
  // Keeps the outputs for inspection when asked to.
  if (const char* keep = std::getenv("INTERSLICE_KEEP_DICOM_OUT")) {
    fs::copy(dir.path(), keep, fs::copy_options::recursive);
  }
}

TEST_F(DicomWriterTest, DerivedSeriesRoundTripsThroughOurReader) {
  TempDir dir;
  const Volume<float> distance = Distance();
  const Volume<float> mask = ToFloat(Mask(distance));
  auto intensity = ResampleToGrid(source_->image, *grid_, {});
  ASSERT_TRUE(intensity.ok()) << intensity.status();

  struct Case {
    DerivedContent content;
    const Volume<float>* values;
    double tolerance;
  };
  // Distance: half the 0.01 mm step (plus float rounding); intensity: half
  // of the source's rescale slope (1 HU).
  const Case cases[] = {{DerivedContent::kMask, &mask, 0.0},
                        {DerivedContent::kDistance, &distance, 0.005 + 1e-5},
                        {DerivedContent::kIntensity, &*intensity, 0.5 + 1e-3}};
  for (const Case& c : cases) {
    SCOPED_TRACE(DerivedContentName(c.content));
    const std::string out =
        (dir.path() / std::string(DerivedContentName(c.content))).string();
    auto paths =
        WriteDerivedSeries(*source_, *c.values, c.content, Options(), out);
    ASSERT_TRUE(paths.ok()) << paths.status();
    auto back = ReadDicomSeries({out}, {}, {});
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectSameGrid(back->image.grid, *grid_);
    ASSERT_EQ(back->image.data.size(), c.values->data.size());
    double worst = 0;
    for (size_t i = 0; i < c.values->data.size(); ++i) {
      worst = std::max(worst, std::abs(double(back->image.data[i]) -
                                       double(c.values->data[i])));
    }
    EXPECT_LE(worst, c.tolerance);
    EXPECT_EQ(back->study_instance_uid, source_->study_instance_uid);
    EXPECT_EQ(back->frame_of_reference_uid, source_->frame_of_reference_uid);
    EXPECT_EQ(back->modality, "CT");
  }
}

TEST_F(DicomWriterTest, IntensityOnSourceSlicesEqualsSource) {
  // Output slices 0, 5, 10, 15 lie on the source slices; linear
  // interpolation must reproduce them exactly there.
  auto intensity = ResampleToGrid(source_->image, *grid_, {});
  ASSERT_TRUE(intensity.ok()) << intensity.status();
  for (int64_t s = 0; s < source_->image.grid.size[2]; ++s) {
    for (int64_t j = 0; j < grid_->size[1]; j += 7) {
      for (int64_t i = 0; i < grid_->size[0]; i += 5) {
        ASSERT_NEAR(intensity->at(i, j, 5 * s),
                    source_->image.at(224 + i, 200 + j, s), 1e-3);
      }
    }
  }
}

TEST_F(DicomWriterTest, SegmentationRoundTripsThroughDcmtk) {
  TempDir dir;
  const Volume<uint8_t> mask = Mask(Distance());
  const std::string path = (dir.path() / "seg.dcm").string();
  SegmentDescription segment;
  segment.label = "Sphere";
  ASSERT_TRUE(WriteSegmentation(*source_, mask, segment, Options(), path).ok());

  DcmSegmentation* raw = nullptr;
  ASSERT_TRUE(DcmSegmentation::loadFile(path.c_str(), raw).good());
  std::unique_ptr<DcmSegmentation> seg(raw);
  ASSERT_EQ(seg->getNumberOfSegments(), 1u);
  OFString label;
  seg->getSegment(1)->getSegmentLabel(label);
  EXPECT_EQ(std::string(label.c_str()), "Sphere");
  OFString code;
  seg->getSegment(1)->getSegmentedPropertyTypeCode().getCodeValue(code);
  EXPECT_EQ(std::string(code.c_str()), "272673000");
  ASSERT_EQ(seg->getNumberOfFrames(), static_cast<size_t>(grid_->size[2]));

  const Uint16 rows = static_cast<Uint16>(grid_->size[1]);
  const Uint16 cols = static_cast<Uint16>(grid_->size[0]);
  for (size_t f = 0; f < seg->getNumberOfFrames(); ++f) {
    SCOPED_TRACE(f);
    FGPlanePosPatient* position = OFstatic_cast(
        FGPlanePosPatient*,
        seg->getFunctionalGroups().get(static_cast<Uint32>(f),
                                       DcmFGTypes::EFG_PLANEPOSPATIENT));
    ASSERT_NE(position, nullptr);
    Float64 x = 0, y = 0, z = 0;
    ASSERT_TRUE(position->getImagePositionPatient(x, y, z).good());
    const Vec3 expected =
        grid_->IndexToPhysical({0, 0, static_cast<double>(f)});
    EXPECT_NEAR(x, expected[0], 1e-4);
    EXPECT_NEAR(y, expected[1], 1e-4);
    EXPECT_NEAR(z, expected[2], 1e-4);

    std::unique_ptr<DcmIODTypes::Frame> frame(
        DcmSegUtils::unpackBinaryFrame(seg->getFrame(f), rows, cols));
    ASSERT_NE(frame, nullptr);
    ASSERT_EQ(frame->length, size_t{rows} * cols);
    int64_t mismatches = 0;
    for (size_t i = 0; i < frame->length; ++i) {
      mismatches +=
          (frame->pixData[i] != 0) != (mask.data[f * frame->length + i] != 0);
    }
    EXPECT_EQ(mismatches, 0);
  }

  // Patient/study copied, references to the source series.
  auto file = Load(path);
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID), source_->study_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_FrameOfReferenceUID),
            source_->frame_of_reference_uid);
  EXPECT_THAT(GetString(ds, DCM_SeriesInstanceUID), StartsWith(kTestRoot));
  EXPECT_THAT(GetString(ds, DCM_SOPInstanceUID), StartsWith(kTestRoot));
  DcmItem* series = nullptr;
  ASSERT_TRUE(ds.findAndGetSequenceItem(DCM_ReferencedSeriesSequence, series, 0)
                  .good());
  EXPECT_EQ(GetString(*series, DCM_SeriesInstanceUID),
            source_->series_instance_uid);
  DcmSequenceOfItems* instances = nullptr;
  ASSERT_TRUE(
      series->findAndGetSequence(DCM_ReferencedInstanceSequence, instances)
          .good());
  EXPECT_EQ(instances->card(), source_->slices.size());
}

// Regression: with default options (no series number) the SEG failed to
// encode, because SeriesNumber is type 1 in the Segmentation Series module.
TEST_F(DicomWriterTest, SegmentationWithDefaultOptionsHasASeriesNumber) {
  TempDir dir;
  const std::string path = (dir.path() / "seg.dcm").string();
  const absl::Status status =
      WriteSegmentation(*source_, Mask(Distance()), SegmentDescription(),
                        DicomWriteOptions(), path);
  ASSERT_TRUE(status.ok()) << status;
  DcmFileFormat file;
  ASSERT_TRUE(file.loadFile(path.c_str()).good());
  OFString number;
  ASSERT_TRUE(
      file.getDataset()->findAndGetOFString(DCM_SeriesNumber, number).good());
  EXPECT_EQ(number, "9001");
}

TEST_F(DicomWriterTest, UidsPositionsAndInstanceNumbers) {
  TempDir dir;
  const Volume<float> mask = ToFloat(Mask(Distance()));
  auto source_file = Load(source_->slices[0].path);
  DcmDataset& src = *source_file->getDataset();

  for (const bool default_root : {false, true}) {
    SCOPED_TRACE(default_root ? "default root" : "given root");
    DicomWriteOptions options = Options();
    if (default_root) options.uid_root.clear();
    const std::string prefix = default_root ? "2.25." : kTestRoot;
    const std::string out =
        (dir.path() / (default_root ? "default" : "given")).string();
    auto paths =
        WriteDerivedSeries(*source_, mask, DerivedContent::kMask, options, out);
    ASSERT_TRUE(paths.ok()) << paths.status();

    std::set<std::string> sop_uids;
    std::string series_uid;
    const Vec3 n = grid_->Axis(2);
    double previous_position = -1e30;
    long previous_number = 0;
    for (size_t k = 0; k < paths->size(); ++k) {
      auto file = Load((*paths)[k]);
      DcmDataset& ds = *file->getDataset();
      const std::string sop = GetString(ds, DCM_SOPInstanceUID);
      EXPECT_THAT(sop, StartsWith(prefix));
      EXPECT_LE(sop.size(), 64u);
      sop_uids.insert(sop);
      EXPECT_EQ(GetString(*file->getMetaInfo(), DCM_MediaStorageSOPInstanceUID),
                sop);
      if (k == 0) series_uid = GetString(ds, DCM_SeriesInstanceUID);
      EXPECT_EQ(GetString(ds, DCM_SeriesInstanceUID), series_uid);
      EXPECT_NE(series_uid, source_->series_instance_uid);
      EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID),
                source_->study_instance_uid);
      EXPECT_EQ(GetString(ds, DCM_FrameOfReferenceUID),
                source_->frame_of_reference_uid);
      // Patient and study modules copied, not invented.
      EXPECT_EQ(GetString(ds, DCM_PatientName),
                GetString(src, DCM_PatientName));
      EXPECT_EQ(GetString(ds, DCM_PatientID), GetString(src, DCM_PatientID));
      EXPECT_EQ(GetString(ds, DCM_StudyDescription),
                GetString(src, DCM_StudyDescription));
      EXPECT_EQ(GetString(ds, DCM_ImageType), "DERIVED\\SECONDARY\\AXIAL");
      EXPECT_EQ(GetString(ds, DCM_SeriesNumber), "901");

      long number = 0;
      ASSERT_TRUE(ds.findAndGetLongInt(DCM_InstanceNumber, number).good());
      EXPECT_EQ(number, static_cast<long>(k + 1));
      EXPECT_GT(number, previous_number);
      previous_number = number;

      Vec3 ipp;
      for (int c = 0; c < 3; ++c) {
        Float64 v = 0;
        ASSERT_TRUE(
            ds.findAndGetFloat64(DCM_ImagePositionPatient, v, c).good());
        ipp[c] = v;
      }
      const Vec3 expected =
          grid_->IndexToPhysical({0, 0, static_cast<double>(k)});
      for (int c = 0; c < 3; ++c) EXPECT_NEAR(ipp[c], expected[c], 1e-4);
      Float64 between = 0, thickness = 0;
      ASSERT_TRUE(
          ds.findAndGetFloat64(DCM_SpacingBetweenSlices, between).good());
      ASSERT_TRUE(ds.findAndGetFloat64(DCM_SliceThickness, thickness).good());
      EXPECT_DOUBLE_EQ(between, grid_->spacing[2]);
      EXPECT_DOUBLE_EQ(thickness, grid_->spacing[2]);
      const double position = Dot(ipp, n);
      if (k > 0) {
        EXPECT_NEAR(position - previous_position, between, 1e-4);
      }
      previous_position = position;

      // Each slice names the source slices it lies on or between.
      DcmSequenceOfItems* sources = nullptr;
      ASSERT_TRUE(
          ds.findAndGetSequence(DCM_SourceImageSequence, sources).good());
      EXPECT_EQ(sources->card(), k % 5 == 0 ? 1u : 2u);
    }
    EXPECT_EQ(sop_uids.size(), paths->size());
    EXPECT_THAT(series_uid, StartsWith(prefix));
  }
}

TEST(GenerateDicomUidTest, DefaultIsUuidUnder225) {
  std::set<std::string> seen;
  for (int i = 0; i < 100; ++i) {
    auto uid = GenerateDicomUid("");
    ASSERT_TRUE(uid.ok());
    EXPECT_THAT(*uid, StartsWith("2.25."));
    EXPECT_LE(uid->size(), 5u + 39u);
    EXPECT_NE(uid->at(5), '0');
    seen.insert(*uid);
  }
  EXPECT_EQ(seen.size(), 100u);
}

TEST(GenerateDicomUidTest, RejectsMalformedRoots) {
  for (const char* root : {"1..2", ".1.2", "1.2.", "1.02", "1.2a",
                           "1.2.3.4.5.6.7.8.9.10.11.12.13.14.15.16.17.18"}) {
    EXPECT_EQ(GenerateDicomUid(root).status().code(),
              absl::StatusCode::kInvalidArgument)
        << root;
  }
  auto uid = GenerateDicomUid("1.2.3");
  ASSERT_TRUE(uid.ok());
  EXPECT_THAT(*uid, StartsWith("1.2.3."));
  EXPECT_LE(uid->size(), 64u);
}

TEST_F(DicomWriterTest, UnwritableFolderIsAClearError) {
  TempDir dir;
  const fs::path blocker = dir.path() / "a_file";
  std::ofstream(blocker) << "x";
  const Volume<float> mask = ToFloat(Mask(Distance()));
  auto paths = WriteDerivedSeries(*source_, mask, DerivedContent::kMask,
                                  Options(), (blocker / "out").string());
  ASSERT_FALSE(paths.ok());
  EXPECT_EQ(paths.status().code(), absl::StatusCode::kInternal);
  EXPECT_THAT(paths.status().message(), HasSubstr("output folder"));

  const absl::Status seg =
      WriteSegmentation(*source_, Mask(Distance()), SegmentDescription(),
                        Options(), (blocker / "seg.dcm").string());
  EXPECT_EQ(seg.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(seg.message(), HasSubstr("seg.dcm"));
  // No temporary files left behind.
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()),
                          fs::directory_iterator()),
            1);
}

TEST_F(DicomWriterTest, GridMismatchIsInvalidArgument) {
  TempDir dir;
  Volume<uint8_t> mask = Mask(Distance());
  // A rotated grid (direction differs from the source's).
  Volume<uint8_t> rotated = mask;
  rotated.grid.direction = {0, 1, 0, 1, 0, 0, 0, 0, -1};
  EXPECT_EQ(WriteSegmentation(*source_, rotated, SegmentDescription(),
                              Options(), (dir.path() / "s.dcm").string())
                .code(),
            absl::StatusCode::kInvalidArgument);
  // Voxel count that does not match the grid.
  Volume<uint8_t> short_mask = mask;
  short_mask.data.pop_back();
  EXPECT_EQ(WriteSegmentation(*source_, short_mask, SegmentDescription(),
                              Options(), (dir.path() / "s.dcm").string())
                .code(),
            absl::StatusCode::kInvalidArgument);
  Volume<float> values = ToFloat(mask);
  values.grid.direction = rotated.grid.direction;
  EXPECT_EQ(WriteDerivedSeries(*source_, values, DerivedContent::kMask,
                               Options(), (dir.path() / "d").string())
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  // Non-finite values.
  Volume<float> nan = Distance();
  nan.data[5] = std::nanf("");
  EXPECT_EQ(WriteDerivedSeries(*source_, nan, DerivedContent::kDistance,
                               Options(), (dir.path() / "n").string())
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  // A malformed UID root.
  DicomWriteOptions bad = Options();
  bad.uid_root = "1.2.x";
  EXPECT_EQ(WriteDerivedSeries(*source_, values, DerivedContent::kMask, bad,
                               (dir.path() / "u").string())
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  // Nothing was written.
  EXPECT_TRUE(fs::is_empty(dir.path()));
}

TEST_F(DicomWriterTest, DistanceSlopeGrowsWithRange) {
  TempDir dir;
  Volume<float> distance = Distance();
  distance.data[0] = -500.0f;  // beyond 327.67 mm: the slope must grow
  auto paths = WriteDerivedSeries(*source_, distance, DerivedContent::kDistance,
                                  Options(), dir.path().string());
  ASSERT_TRUE(paths.ok()) << paths.status();
  auto file = Load(paths->front());
  EXPECT_EQ(GetString(*file->getDataset(), DCM_RescaleSlope), "0.02");
  EXPECT_EQ(GetString(*file->getDataset(), DCM_RescaleIntercept), "0");
  auto back = ReadDicomSeries({dir.path().string()}, {}, {});
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_NEAR(back->image.data[0], -500.0f, 0.01 + 1e-4);
}

TEST_F(DicomWriterTest, MeshConventionNoteNamesFrameAndAxes) {
  const std::string note = MeshConventionNote(*source_);
  EXPECT_THAT(note, HasSubstr("LPS"));
  EXPECT_THAT(note, HasSubstr("millimetres"));
  EXPECT_THAT(note, HasSubstr(source_->frame_of_reference_uid));
}

}  // namespace
}  // namespace interslice

namespace interslice {
namespace {

// The same data presented as an MR series and as a series of another image
// class (PET here), which take the MR Image and Secondary Capture paths.
TEST_F(DicomWriterTest, MrAndOtherSourcesPassDciodvfy) {
  TempDir dir;
  const Volume<float> distance = Distance();
  const Volume<float> mask = ToFloat(Mask(distance));
  struct Case {
    const char* name;
    const char* sop_class;
    const char* modality;
    const char* expected_sop_class;
  };
  const Case cases[] = {
      {"mr", "1.2.840.10008.5.1.4.1.1.4", "MR", "1.2.840.10008.5.1.4.1.1.4"},
      {"pt", "1.2.840.10008.5.1.4.1.1.128", "PT", "1.2.840.10008.5.1.4.1.1.7"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    DicomSeries source = *source_;
    source.sop_class_uid = c.sop_class;
    source.modality = c.modality;
    for (const DerivedContent content :
         {DerivedContent::kMask, DerivedContent::kDistance}) {
      const std::string out =
          (dir.path() / c.name / std::string(DerivedContentName(content)))
              .string();
      auto paths = WriteDerivedSeries(
          source, content == DerivedContent::kMask ? mask : distance, content,
          Options(), out);
      ASSERT_TRUE(paths.ok()) << paths.status();
      ExpectValidIod({paths->front()});
      auto file = Load(paths->front());
      EXPECT_EQ(GetString(*file->getDataset(), DCM_SOPClassUID),
                c.expected_sop_class);
      auto back = ReadDicomSeries({out}, {}, {});
      ASSERT_TRUE(back.ok()) << back.status();
      ExpectSameGrid(back->image.grid, *grid_);
    }
  }
}

}  // namespace
}  // namespace interslice
