#include "core/dicom/series_reader.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcddirif.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcrleerg.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmjpeg/djencode.h"
#include "dcmtk/dcmjpls/djencode.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::AllOf;
using ::testing::HasSubstr;
using ::testing::Not;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
const std::vector<std::string> kThickNames = {"I10.dcm", "I20.dcm", "I30.dcm",
                                              "I40.dcm"};
// From `dcmdump tests/data/ct-thick/I10.dcm` (and I20..I40).
constexpr double kPixelSpacing = 0.451171875;
constexpr double kFirstZ = 696.21;
constexpr double kSliceStep = 5.0;
constexpr double kIntercept = -1024;
constexpr double kSlope = 1;
constexpr int kSize = 512;

// A fresh folder per test, removed afterwards.
class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_dicom_") {}
};

void CopyThick(const fs::path& dir, const std::vector<std::string>& names) {
  for (const std::string& name : names) {
    fs::copy_file(kThick / name, dir / name);
  }
}

std::unique_ptr<DcmFileFormat> Load(const fs::path& path) {
  auto file = std::make_unique<DcmFileFormat>();
  EXPECT_TRUE(file->loadFile(OFFilename(path.c_str())).good()) << path;
  EXPECT_TRUE(file->loadAllDataIntoMemory().good());
  return file;
}

void Save(DcmFileFormat& file, const fs::path& path,
          E_TransferSyntax xfer = EXS_LittleEndianExplicit) {
  const OFCondition cond = file.saveFile(OFFilename(path.c_str()), xfer);
  ASSERT_TRUE(cond.good()) << cond.text();
}

std::string NewUid() {
  char uid[100];
  return dcmGenerateUniqueIdentifier(uid, SITE_INSTANCE_UID_ROOT);
}

// Copies a vendored slice to `dst` after `edit` changed its dataset; the copy
// gets its own SOPInstanceUID.
void CopyEdited(const std::string& name, const fs::path& dst,
                const std::function<void(DcmDataset&)>& edit) {
  auto file = Load(kThick / name);
  DcmDataset& ds = *file->getDataset();
  ASSERT_TRUE(
      ds.putAndInsertString(DCM_SOPInstanceUID, NewUid().c_str()).good());
  edit(ds);
  Save(*file, dst);
}

void WriteText(const fs::path& path, const std::string& text) {
  std::ofstream(path, std::ios::binary) << text;
}

absl::StatusOr<DicomSeries> Read(const std::vector<std::string>& paths,
                                 DicomReadOptions options = {}) {
  return ReadDicomSeries(paths, options, ComputeContext{});
}

// The stored value of pixel (i, j) as DCMTK reads it, masked to BitsStored
// (12 bits, unsigned in these files).
double RawHu(const fs::path& path, int i, int j) {
  auto file = Load(path);
  const Uint16* pixels = nullptr;
  EXPECT_TRUE(
      file->getDataset()->findAndGetUint16Array(DCM_PixelData, pixels).good());
  return (pixels[j * kSize + i] & 0x0fff) * kSlope + kIntercept;
}

TEST(ReadDicomSeriesTest, SortsShuffledFilesAlongTheNormal) {
  const std::vector<std::string> shuffled = {
      (kThick / "I30.dcm").string(), (kThick / "I10.dcm").string(),
      (kThick / "I40.dcm").string(), (kThick / "I20.dcm").string()};
  const auto series = Read(shuffled);
  ASSERT_TRUE(series.ok()) << series.status();
  ASSERT_EQ(series->slices.size(), 4u);
  for (int k = 0; k < 4; ++k) {
    EXPECT_EQ(fs::path(series->slices[k].path).filename(), kThickNames[k]);
    EXPECT_NEAR(series->slices[k].position_along_normal,
                kFirstZ + kSliceStep * k, 1e-9);
    EXPECT_NEAR(series->slices[k].image_position[2], kFirstZ + kSliceStep * k,
                1e-9);
    EXPECT_EQ(series->slices[k].rescale_slope, kSlope);
    EXPECT_EQ(series->slices[k].rescale_intercept, kIntercept);
  }
  EXPECT_EQ(series->slices[0].sop_instance_uid,
            "1.3.46.670589.33.1.1945709553237662531.30446478581090029189");
  EXPECT_EQ(series->modality, "CT");
  EXPECT_EQ(series->series_instance_uid,
            "1.3.46.670589.33.1.6002432791750815306.26862469513794233732");
  EXPECT_EQ(series->study_instance_uid,
            "1.3.46.670589.33.1.27492712521914879309.27169771283235650014");
  EXPECT_EQ(series->frame_of_reference_uid,
            "1.3.46.670589.33.1.28113183791790987842.26931358731677349446");
  EXPECT_EQ(series->sop_class_uid, UID_CTImageStorage);
  EXPECT_EQ(series->skipped_files, 0);
}

TEST(ReadDicomSeriesTest, GridMatchesTheHeaders) {
  const auto series = Read({kThick.string()});
  ASSERT_TRUE(series.ok()) << series.status();
  const Grid& grid = series->image.grid;
  EXPECT_EQ(grid.size, (Index3{kSize, kSize, 4}));
  EXPECT_NEAR(grid.spacing[0], kPixelSpacing, 1e-12);
  EXPECT_NEAR(grid.spacing[1], kPixelSpacing, 1e-12);
  EXPECT_NEAR(grid.spacing[2], kSliceStep, 1e-9);
  // ImagePositionPatient of I10: -115.5\-1.85\696.21; orientation 1\0\0\0\1\0.
  EXPECT_NEAR(grid.origin[0], -115.5, 1e-12);
  EXPECT_NEAR(grid.origin[1], -1.85, 1e-12);
  EXPECT_NEAR(grid.origin[2], kFirstZ, 1e-12);
  for (int c = 0; c < 9; ++c) {
    EXPECT_NEAR(grid.direction[c], kIdentityDirection[c], 1e-12) << c;
  }
  EXPECT_EQ(series->image.data.size(), size_t{kSize} * kSize * 4);
  // The folder also holds the LICENSE file.
  EXPECT_EQ(series->skipped_files, 1);
}

TEST(ReadDicomSeriesTest, VoxelsAreStoredValueTimesSlopePlusIntercept) {
  const auto series = Read({kThick.string()});
  ASSERT_TRUE(series.ok()) << series.status();
  const Volume<float>& image = series->image;
  // Air in a corner of the first slice (stored 26 per dcmdump).
  EXPECT_EQ(image.at(0, 0, 0), 26 * kSlope + kIntercept);
  EXPECT_NEAR(image.at(0, 0, 0), -1000, 30);
  EXPECT_NEAR(image.at(kSize - 1, kSize - 1, 3), -1000, 50);
  // Skull in I20 (column 329, row 256) and soft tissue at the centre.
  EXPECT_EQ(image.at(329, 256, 1), RawHu(kThick / "I20.dcm", 329, 256));
  EXPECT_GT(image.at(329, 256, 1), 300);
  EXPECT_EQ(image.at(256, 256, 1), RawHu(kThick / "I20.dcm", 256, 256));
  // Rows and columns are not swapped: (i=14, j=256) is bone, (256, 14) air.
  EXPECT_EQ(image.at(14, 256, 1), RawHu(kThick / "I20.dcm", 14, 256));
  EXPECT_EQ(image.at(256, 14, 1), RawHu(kThick / "I20.dcm", 256, 14));
  // Every voxel of the last slice.
  auto file = Load(kThick / "I40.dcm");
  const Uint16* pixels = nullptr;
  ASSERT_TRUE(
      file->getDataset()->findAndGetUint16Array(DCM_PixelData, pixels).good());
  for (int j = 0; j < kSize; ++j) {
    for (int i = 0; i < kSize; ++i) {
      ASSERT_EQ(image.at(i, j, 3),
                (pixels[j * kSize + i] & 0x0fff) * kSlope + kIntercept)
          << i << "," << j;
    }
  }
}

TEST(ReadDicomSeriesTest, ReadsTheFullThickSeries) {
  const fs::path dir = fs::path(::interslice::testing::SourceDir()) / "data" /
                       "ct-head-phantom-thick";
  // The shipped phantom is part of the repository: absent is a broken
  // checkout, not a reason to skip.
  ASSERT_TRUE(fs::is_directory(dir)) << dir << " is absent";
  const auto series = Read({dir.string()});
  ASSERT_TRUE(series.ok()) << series.status();
  ASSERT_EQ(series->image.grid.size, (Index3{kSize, kSize, 28}));
  EXPECT_NEAR(series->image.grid.spacing[2], 5.0, 1e-9);
  // dcmdump: ImagePositionPatient z from 696.21 (I10) to 831.21 (I280).
  EXPECT_NEAR(series->slices.front().position_along_normal, 696.21, 1e-9);
  EXPECT_NEAR(series->slices.back().position_along_normal, 831.21, 1e-9);
  EXPECT_EQ(fs::path(series->slices.front().path).filename(), "I10.dcm");
  EXPECT_EQ(fs::path(series->slices.back().path).filename(), "I280.dcm");
  EXPECT_EQ(series->skipped_files, 2);  // LICENSE, README.md
}

TEST(ReadDicomSeriesTest, ReadsSubfoldersAndIgnoresDuplicatePaths) {
  TempDir dir;
  fs::create_directories(dir.path() / "a" / "b");
  CopyThick(dir.path() / "a", {"I10.dcm", "I20.dcm"});
  CopyThick(dir.path() / "a" / "b", {"I30.dcm", "I40.dcm"});
  const auto series =
      Read({dir.str(), (dir.path() / "a" / "I10.dcm").string()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size[2], 4);
}

TEST(ReadDicomSeriesTest, EmptyFolderIsNotFound) {
  TempDir dir;
  EXPECT_EQ(Read({dir.str()}).status().code(), absl::StatusCode::kNotFound);
}

TEST(ReadDicomSeriesTest, MissingPathIsNotFound) {
  TempDir dir;
  const auto result = Read({(dir.path() / "nope").string()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(result.status().message(), HasSubstr("nope"));
}

TEST(ReadDicomSeriesTest, SeveralSeriesNeedAChoice) {
  TempDir dir;
  CopyThick(dir.path(), kThickNames);
  const std::string other_uid = NewUid();
  CopyEdited("I10.dcm", dir.path() / "other.dcm", [&](DcmDataset& ds) {
    ds.putAndInsertString(DCM_SeriesInstanceUID, other_uid.c_str());
  });
  const std::string thick_uid =
      "1.3.46.670589.33.1.6002432791750815306.26862469513794233732";

  const auto unchosen = Read({dir.str()});
  EXPECT_EQ(unchosen.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(unchosen.status().message(),
              AllOf(HasSubstr(thick_uid + " (CT, 4 images)"),
                    HasSubstr(other_uid + " (CT, 1 image)"),
                    HasSubstr("--series-uid")));

  DicomReadOptions options;
  options.series_instance_uid = thick_uid;
  const auto thick = Read({dir.str()}, options);
  ASSERT_TRUE(thick.ok()) << thick.status();
  EXPECT_EQ(thick->image.grid.size[2], 4);
  EXPECT_EQ(thick->skipped_files, 1);

  // A single slice takes its spacing from SliceThickness (5).
  options.series_instance_uid = other_uid;
  const auto other = Read({dir.str()}, options);
  ASSERT_TRUE(other.ok()) << other.status();
  EXPECT_EQ(other->image.grid.size[2], 1);
  EXPECT_EQ(other->series_instance_uid, other_uid);
  EXPECT_NEAR(other->image.grid.spacing[2], 5.0, 1e-12);
  EXPECT_EQ(other->skipped_files, 4);

  options.series_instance_uid = "1.2.3.4";
  const auto absent = Read({dir.str()}, options);
  EXPECT_EQ(absent.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(
      absent.status().message(),
      AllOf(HasSubstr("1.2.3.4"), HasSubstr(thick_uid), HasSubstr(other_uid)));
}

TEST(ListDicomSeriesTest, ListsEachImageSeries) {
  TempDir dir;
  CopyThick(dir.path(), kThickNames);
  const std::string other_uid = NewUid();
  CopyEdited("I10.dcm", dir.path() / "other.dcm", [&](DcmDataset& ds) {
    ds.putAndInsertString(DCM_SeriesInstanceUID, other_uid.c_str());
  });
  WriteText(dir.path() / "notes.txt", "not DICOM");
  const auto list = ListDicomSeries({dir.str()});
  ASSERT_TRUE(list.ok()) << list.status();
  ASSERT_EQ(list->size(), 2u);
  int64_t total = 0;
  for (const DicomSeriesSummary& s : *list) {
    EXPECT_EQ(s.modality, "CT");
    EXPECT_EQ(s.image_count, s.series_instance_uid == other_uid ? 1 : 4);
    total += s.image_count;
  }
  EXPECT_EQ(total, 5);
}

TEST(ReadDicomSeriesTest, InconsistentRowsColumnsNameTheFile) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I30.dcm", "I40.dcm"});
  // I20 at 256 x 256 with pixel data to match.
  CopyEdited("I20.dcm", dir.path() / "odd.dcm", [](DcmDataset& ds) {
    ds.putAndInsertUint16(DCM_Rows, 256);
    ds.putAndInsertUint16(DCM_Columns, 256);
    std::vector<Uint16> pixels(256 * 256, 1024);
    ds.putAndInsertUint16Array(DCM_PixelData, pixels.data(), pixels.size());
  });
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("Rows/Columns"), HasSubstr("odd.dcm")));
  // The copy alone is a valid one-slice series.
  EXPECT_TRUE(Read({(dir.path() / "odd.dcm").string()}).ok());
}

TEST(ReadDicomSeriesTest, InconsistentSpacingAndOrientationNameTheFile) {
  {
    TempDir dir;
    CopyThick(dir.path(), {"I10.dcm", "I30.dcm", "I40.dcm"});
    CopyEdited("I20.dcm", dir.path() / "odd.dcm", [](DcmDataset& ds) {
      ds.putAndInsertString(DCM_PixelSpacing, "0.5\\0.5");
    });
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(result.status().message(),
                AllOf(HasSubstr("PixelSpacing"), HasSubstr("odd.dcm")));
  }
  {
    TempDir dir;
    CopyThick(dir.path(), {"I10.dcm", "I30.dcm", "I40.dcm"});
    CopyEdited("I20.dcm", dir.path() / "odd.dcm", [](DcmDataset& ds) {
      ds.putAndInsertString(DCM_ImageOrientationPatient,
                            "0.9998\\0.02\\0\\-0.02\\0.9998\\0");
    });
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(
        result.status().message(),
        AllOf(HasSubstr("ImageOrientationPatient"), HasSubstr("odd.dcm")));
  }
  {
    // Within tolerance (1e-5 relative) it is fine.
    TempDir dir;
    CopyThick(dir.path(), {"I10.dcm", "I30.dcm", "I40.dcm"});
    CopyEdited("I20.dcm", dir.path() / "odd.dcm", [](DcmDataset& ds) {
      ds.putAndInsertString(DCM_PixelSpacing, "0.451175\\0.451175");
    });
    EXPECT_TRUE(Read({dir.str()}).ok());
  }
}

TEST(ReadDicomSeriesTest, NonImagesAreSkipped) {
  TempDir dir;
  CopyThick(dir.path(), kThickNames);
  WriteText(dir.path() / "notes.txt", "just some text\n");
  WriteText(dir.path() / "empty", "");
  // Same series, no pixel data (like a report or a presentation state).
  CopyEdited("I10.dcm", dir.path() / "nopixels.dcm",
             [](DcmDataset& ds) { delete ds.remove(DCM_PixelData); });
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size[2], 4);
  EXPECT_EQ(series->skipped_files, 3);

  for (const std::string& name : kThickNames) fs::remove(dir.path() / name);
  const auto none = Read({dir.str()});
  EXPECT_EQ(none.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(none.status().message(), HasSubstr("3 file(s) skipped"));
  const auto list = ListDicomSeries({dir.str()});
  ASSERT_TRUE(list.ok());
  EXPECT_TRUE(list->empty());
}

TEST(ReadDicomSeriesTest, DicomDirIsSkipped) {
  TempDir dir;
  // File IDs in a DICOMDIR are upper case, at most 8 characters.
  for (int k = 0; k < 4; ++k) {
    fs::copy_file(kThick / kThickNames[k],
                  dir.path() / ("IMG" + std::to_string(k + 1)));
  }
  {
    DicomDirInterface dicomdir;
    dicomdir.enableInventMode();
    const std::string dicomdir_path = (dir.path() / "DICOMDIR").string();
    ASSERT_TRUE(dicomdir
                    .createNewDicomDir(DicomDirInterface::AP_GeneralPurpose,
                                       OFFilename(dicomdir_path.c_str()),
                                       "TESTSET")
                    .good());
    for (int k = 1; k <= 4; ++k) {
      const std::string name = "IMG" + std::to_string(k);
      const OFCondition cond = dicomdir.addDicomFile(
          OFFilename(name.c_str()), OFFilename(dir.str().c_str()));
      ASSERT_TRUE(cond.good()) << cond.text();
    }
    ASSERT_TRUE(dicomdir.writeDicomDir().good());
  }
  ASSERT_TRUE(fs::exists(dir.path() / "DICOMDIR"));
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size[2], 4);
  EXPECT_EQ(series->skipped_files, 1);

  // Recognised as a DICOMDIR, not merely as an object without pixels.
  for (int k = 1; k <= 4; ++k) {
    fs::remove(dir.path() / ("IMG" + std::to_string(k)));
  }
  const auto none = Read({dir.str()});
  EXPECT_EQ(none.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(none.status().message(), HasSubstr("1 DICOMDIR"));
}

TEST(ReadDicomSeriesTest, TruncatedFileIsAnErrorNamingIt) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I30.dcm", "I40.dcm"});
  {
    std::ifstream in(kThick / "I20.dcm", std::ios::binary);
    std::string bytes(20000, '\0');
    in.read(bytes.data(), bytes.size());
    WriteText(dir.path() / "I20.dcm", bytes);
  }
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("I20.dcm"), Not(HasSubstr(dir.str()))));
  // Listing does not read pixel data; the broken file still counts.
  const auto list = ListDicomSeries({dir.str()});
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->size(), 1u);
  EXPECT_EQ((*list)[0].image_count, 4);
}

TEST(ReadDicomSeriesTest, HostileSizeIsRejectedBeforeAllocating) {
  TempDir dir;
  // 60000 x 60000 claimed, 512 x 512 x 2 bytes present.
  CopyEdited("I10.dcm", dir.path() / "huge.dcm", [](DcmDataset& ds) {
    ds.putAndInsertUint16(DCM_Rows, 60000);
    ds.putAndInsertUint16(DCM_Columns, 60000);
  });
  for (const int64_t max_voxels : {int64_t{1} << 31, int64_t{1} << 40}) {
    DicomReadOptions options;
    options.max_voxels = max_voxels;
    const auto result = Read({dir.str()}, options);
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(result.status().message(),
                AllOf(HasSubstr("huge.dcm"), HasSubstr("too short")));
  }
  // Also inside a series of good slices.
  CopyThick(dir.path(), {"I20.dcm", "I30.dcm"});
  EXPECT_EQ(Read({dir.str()}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(ReadDicomSeriesTest, MaxVoxelsIsEnforced) {
  DicomReadOptions options;
  options.max_voxels = int64_t{kSize} * kSize * 4 - 1;
  const auto result = Read({kThick.string()}, options);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(), HasSubstr("max_voxels"));
  options.max_voxels = int64_t{kSize} * kSize * 4;
  EXPECT_TRUE(Read({kThick.string()}, options).ok());
}

TEST(ReadDicomSeriesTest, MissingSliceIsAcceptedAndReported) {
  const auto series =
      Read({(kThick / "I10.dcm").string(), (kThick / "I20.dcm").string(),
            (kThick / "I40.dcm").string()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_FALSE(series->uniform_spacing);
  EXPECT_NEAR(series->min_gap_mm, 5.0, 1e-9);
  EXPECT_NEAR(series->max_gap_mm, 10.0, 1e-9);
  ASSERT_EQ(series->slices.size(), 3u);
  // True positions, not the grid's (median) spacing.
  EXPECT_NEAR(series->slices[2].position_along_normal, kFirstZ + 15, 1e-9);
  EXPECT_NEAR(series->image.grid.spacing[2], 7.5, 1e-9);  // median of 5, 10
  // The thick series itself is uniform.
  const auto uniform = Read({kThick.string()});
  ASSERT_TRUE(uniform.ok());
  EXPECT_TRUE(uniform->uniform_spacing);
  EXPECT_NEAR(uniform->min_gap_mm, 5.0, 1e-9);
  EXPECT_NEAR(uniform->max_gap_mm, 5.0, 1e-9);
}
TEST(ReadDicomSeriesTest, DuplicatePositionIsAnError) {
  TempDir dir;
  CopyThick(dir.path(), kThickNames);
  CopyEdited("I20.dcm", dir.path() / "dup.dcm", [](DcmDataset&) {});
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("same slice position"), HasSubstr("I20.dcm"),
                    HasSubstr("dup.dcm")));
}

// A vertical cylinder (axis along patient z through x = 3, y = -4, radius
// 20 mm) imaged by a tilted gantry: the image planes are tilted by `tilt`
// about the x axis and successive slices move along z (the table), as a
// real tilted CT does. Voxel = 1000 inside, 0 outside, sampled at each
// pixel's true patient position.
void WriteTiltedCylinder(const fs::path& dir, double tilt_degrees, int slices) {
  const double t = tilt_degrees * M_PI / 180;
  const int n = 96;
  const double ps = 1.0;  // mm
  const std::string uid = NewUid();
  const Vec3 col = {0, std::cos(t), -std::sin(t)};
  for (int k = 0; k < slices; ++k) {
    const Vec3 ipp = {-48, -48, 4.0 * k};  // 4 mm table steps
    DcmFileFormat file;
    DcmDataset& ds = *file.getDataset();
    ds.putAndInsertString(DCM_SOPClassUID, UID_CTImageStorage);
    ds.putAndInsertString(DCM_SOPInstanceUID, NewUid().c_str());
    ds.putAndInsertString(DCM_SeriesInstanceUID, uid.c_str());
    ds.putAndInsertString(DCM_Modality, "CT");
    char text[200];
    std::snprintf(text, sizeof(text), "%.10f\\%.10f\\%.10f", ipp[0], ipp[1],
                  ipp[2]);
    ds.putAndInsertString(DCM_ImagePositionPatient, text);
    std::snprintf(text, sizeof(text), "1\\0\\0\\0\\%.10f\\%.10f", col[1],
                  col[2]);
    ds.putAndInsertString(DCM_ImageOrientationPatient, text);
    ds.putAndInsertString(DCM_PixelSpacing, "1\\1");
    ds.putAndInsertUint16(DCM_Rows, n);
    ds.putAndInsertUint16(DCM_Columns, n);
    ds.putAndInsertUint16(DCM_SamplesPerPixel, 1);
    ds.putAndInsertString(DCM_PhotometricInterpretation, "MONOCHROME2");
    ds.putAndInsertUint16(DCM_BitsAllocated, 16);
    ds.putAndInsertUint16(DCM_BitsStored, 16);
    ds.putAndInsertUint16(DCM_HighBit, 15);
    ds.putAndInsertUint16(DCM_PixelRepresentation, 0);
    std::vector<Uint16> pixels(n * n);
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        const double x = ipp[0] + i * ps;
        const double y = ipp[1] + j * ps * col[1];
        pixels[j * n + i] =
            std::hypot(x - 3, y + 4) < 20 ? Uint16{1000} : Uint16{0};
      }
    }
    ds.putAndInsertUint16Array(DCM_PixelData, pixels.data(), pixels.size());
    Save(file, dir / ("t" + std::to_string(k) + ".dcm"));
  }
}

TEST(ReadDicomSeriesTest, GantryTiltIsResampledToTrueGeometry) {
  TempDir dir;
  WriteTiltedCylinder(dir.path(), 20.0, 6);
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_NEAR(series->gantry_tilt_degrees, 20.0, 1e-6);
  const Grid& grid = series->image.grid;
  // Steps of 4 mm along z are 4 cos(20 deg) along the normal.
  EXPECT_NEAR(grid.spacing[2], 4.0 * std::cos(20.0 * M_PI / 180), 1e-6);
  EXPECT_TRUE(series->uniform_spacing);
  // In every slice the cylinder's centre, mapped through the grid, is on
  // the vertical axis x = 3, y = -4. Without the resampling it would drift
  // by 4 sin(20 deg) = 1.37 mm in y per slice.
  for (int64_t k = 0; k < grid.size[2]; ++k) {
    double sum_i = 0, sum_j = 0, count = 0;
    for (int64_t j = 0; j < grid.size[1]; ++j) {
      for (int64_t i = 0; i < grid.size[0]; ++i) {
        const double w = series->image.at(i, j, k) / 1000.0;
        sum_i += w * i;
        sum_j += w * j;
        count += w;
      }
    }
    ASSERT_GT(count, 0) << k;
    const Vec3 centre =
        grid.IndexToPhysical({sum_i / count, sum_j / count, double(k)});
    EXPECT_NEAR(centre[0], 3.0, 0.05) << k;
    EXPECT_NEAR(centre[1], -4.0, 0.1) << k;
  }
  // Slice 0 is untouched; the padding is the minimum (0).
  EXPECT_EQ(series->image.at(0, 0, 0), 0.0f);
}

TEST(ReadDicomSeriesTest, RealTiltedSeriesIsResampled) {
  // Three slices of the phantom scanned with gantry tilt -18.5 degrees
  // (header: GantryDetectorTilt -18.5, IOP 1\0\0\0\0.9483237\-0.3173047,
  // IPP z steps of 2.5 mm).
  const fs::path dir =
      fs::path(::interslice::testing::TestDataDir()) / "ct-tilt";
  const auto series = Read({dir.string()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_NEAR(series->gantry_tilt_degrees, 18.5, 0.05);
  const Grid& grid = series->image.grid;
  EXPECT_EQ(grid.size, (Index3{512, 512, 3}));
  EXPECT_NEAR(grid.spacing[2], 2.5 * 0.9483237, 1e-5);
  const Vec3 normal = grid.Axis(2);
  EXPECT_NEAR(normal[1], 0.3173047, 1e-6);
  EXPECT_NEAR(normal[2], 0.9483237, 1e-6);
  EXPECT_NEAR(grid.origin[2], 742.345191756896, 1e-9);
  // Slice k now lies on the plane through the origin shifted along n, and
  // its in-plane content was moved by the in-plane offset of its IPP:
  // -2.5 * 0.3173047 mm along the column direction per slice.
  const double shift_rows = -2.5 * 0.3173047 / 0.482421875;  // per slice
  auto raw = [&](const std::string& name, int i, int j) {
    auto file = Load(dir / name);
    const Uint16* pixels = nullptr;
    EXPECT_TRUE(file->getDataset()
                    ->findAndGetUint16Array(DCM_PixelData, pixels)
                    .good());
    Sint16 value = static_cast<Sint16>(pixels[j * 512 + i]);
    return double(value);
  };
  auto file = Load(dir / "I30.dcm");
  double slope = 1, intercept = 0;
  file->getDataset()->findAndGetFloat64(DCM_RescaleSlope, slope);
  file->getDataset()->findAndGetFloat64(DCM_RescaleIntercept, intercept);
  // new(i, j) = old(i, j - shift): for slice 2, j - 2 * shift_rows.
  const int i = 256, j = 200;
  const double y = j - 2 * shift_rows;
  const int y0 = static_cast<int>(std::floor(y));
  const double ty = y - y0;
  const double expected =
      ((1 - ty) * raw("I30.dcm", i, y0) + ty * raw("I30.dcm", i, y0 + 1)) *
          slope +
      intercept;
  EXPECT_NEAR(series->image.at(i, j, 2), expected, 1e-2);
  EXPECT_NE(series->image.at(i, j, 2),
            raw("I30.dcm", i, j) * slope + intercept);
}
TEST(ReadDicomSeriesTest, OldStyleMultiFrameWithoutGeometryIsSkipped) {
  TempDir dir;
  CopyEdited("I10.dcm", dir.path() / "multi.dcm", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_NumberOfFrames, "2");
  });
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kNotFound);
}

const fs::path kMultiframe =
    fs::path(::interslice::testing::TestDataDir()) / "multiframe";

TEST(ReadDicomSeriesTest, PhilipsEnhancedHoldsTwoVolumes) {
  // 64 frames of 64 x 64: 32 positions (4 mm apart) x {magnitude, B0 field
  // map}, one StackID, one temporal position (see dcmdump).
  const std::string path =
      (kMultiframe / "philips-enhanced-mr-64frames.dcm").string();
  const auto both = Read({path});
  EXPECT_EQ(both.status().code(), absl::StatusCode::kFailedPrecondition);
  const std::string magnitude =
      "stack 1, temporal position 1, frame type ORIGINAL\\PRIMARY\\T1\\M "
      "(MAGNITUDE)";
  EXPECT_THAT(
      both.status().message(),
      AllOf(HasSubstr("2 volumes"), HasSubstr(magnitude + "\" (32 slices)"),
            HasSubstr("FIELD_MAP (REAL)\" (32 slices)")));
  DicomReadOptions options;
  options.volume = magnitude;
  const auto series = Read({path}, options);
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size, (Index3{64, 64, 32}));
  EXPECT_NEAR(series->image.grid.spacing[0], 4.0, 1e-12);
  EXPECT_NEAR(series->image.grid.spacing[2], 4.0, 1e-4);
  EXPECT_TRUE(series->uniform_spacing);
  EXPECT_EQ(series->volume, magnitude);
  EXPECT_EQ(series->modality, "MR");
  // Frame positions come from PlanePositionSequence, not from the private
  // Philips copy (which is 2 mm off): first frame at z = -38.354590835260.
  EXPECT_NEAR(series->image.grid.origin[0], -127.24297738075, 1e-9);
  EXPECT_NEAR(series->image.grid.origin[2], -38.354590835260, 1e-9);
  // Per-frame rescale of the magnitude frames.
  ASSERT_EQ(series->slices.size(), 32u);
  EXPECT_NEAR(series->slices[0].rescale_slope, 1.27985347985347, 1e-12);
  EXPECT_EQ(series->slices[5].frame, 5);
  // Voxels: stored value of frame 6 times its slope.
  auto file = Load(path);
  const Uint16* pixels = nullptr;
  ASSERT_TRUE(
      file->getDataset()->findAndGetUint16Array(DCM_PixelData, pixels).good());
  const int frame = series->slices[5].frame;
  for (int p : {0, 1000, 2080, 4095}) {
    EXPECT_FLOAT_EQ(
        series->image.data[5 * 4096 + p],
        static_cast<float>(pixels[frame * 4096 + p] * 1.27985347985347));
  }
  // The field map frames have their own rescale (slope 0.2442, -500).
  options.volume =
      "stack 1, temporal position 1, frame type "
      "ORIGINAL\\PRIMARY\\T1\\FIELD_MAP (REAL)";
  const auto map = Read({path}, options);
  ASSERT_TRUE(map.ok()) << map.status();
  EXPECT_NEAR(map->slices[0].rescale_intercept, -500, 1e-12);
  EXPECT_EQ(map->slices[0].frame, 32);
  options.volume = "nope";
  EXPECT_EQ(Read({path}, options).status().code(),
            absl::StatusCode::kFailedPrecondition);
}

TEST(ReadDicomSeriesTest, SiemensXaTemporalPositionsAreVolumes) {
  // Three files of one series, 6 frames each at the same 6 positions
  // (2.4 mm apart), TemporalPositionIndex 1, 2 and 4.
  TempDir dir;
  for (const char* name : {"siemens-xa10-6_1.dcm", "siemens-xa10-6_2.dcm",
                           "siemens-xa10-6_4.dcm"}) {
    fs::copy_file(kMultiframe / name, dir.path() / name);
  }
  const auto all = Read({dir.str()});
  EXPECT_EQ(all.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(all.status().message(),
              AllOf(HasSubstr("3 volumes"), HasSubstr("temporal position 1,"),
                    HasSubstr("temporal position 2,"),
                    HasSubstr("temporal position 4,")));
  // One file is one volume.
  const auto one = Read({(kMultiframe / "siemens-xa10-6_2.dcm").string()});
  ASSERT_TRUE(one.ok()) << one.status();
  EXPECT_EQ(one->image.grid.size, (Index3{64, 64, 6}));
  EXPECT_NEAR(one->image.grid.spacing[2], 2.4, 1e-3);
  EXPECT_NEAR(one->slices.front().position_along_normal, -5.40356, 1e-3);
  // Or choose one volume of the series by its name.
  DicomReadOptions options;
  options.volume =
      "stack 1, temporal position 4, frame type ORIGINAL\\PRIMARY\\M\\NONE "
      "(MAGNITUDE)";
  const auto fourth = Read({dir.str()}, options);
  ASSERT_TRUE(fourth.ok()) << fourth.status();
  EXPECT_EQ(fourth->image.grid.size[2], 6);
  EXPECT_EQ(fs::path(fourth->slices[0].path).filename(),
            "siemens-xa10-6_4.dcm");
  EXPECT_EQ(fourth->skipped_files, 2);
}

TEST(ReadDicomSeriesTest, MultiFrameClaimingMoreFramesThanItHoldsIsAnError) {
  TempDir dir;
  auto file = Load(kMultiframe / "siemens-xa10-6_1.dcm");
  DcmDataset& ds = *file->getDataset();
  ds.putAndInsertString(DCM_NumberOfFrames, "6000000");
  Save(*file, dir.path() / "many.dcm");
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(), HasSubstr("many.dcm"));
}
// A synthetic 4 x 3 slice with the given pixel module and raw sample words
// (little-endian, BitsAllocated wide).
struct Synthetic {
  int bits_allocated = 16;
  int bits_stored = 16;
  int high_bit = 15;
  int pixel_representation = 0;
  int samples_per_pixel = 1;
  std::string photometric = "MONOCHROME2";
  std::string slope, intercept;  // empty: absent
  // ImagePositionPatient x; the slice normal is (-1, 0, 0) (see below).
  double x = 10;
  std::vector<uint32_t> raw;  // 12 samples (x samples_per_pixel)
};

void WriteSynthetic(const Synthetic& s, const std::string& series_uid,
                    const fs::path& path) {
  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  ds.putAndInsertString(DCM_SOPClassUID, UID_CTImageStorage);
  ds.putAndInsertString(DCM_SOPInstanceUID, NewUid().c_str());
  ds.putAndInsertString(DCM_SeriesInstanceUID, series_uid.c_str());
  ds.putAndInsertString(DCM_Modality, "CT");
  const std::string ipp = std::to_string(s.x) + "\\20\\30";
  ds.putAndInsertString(DCM_ImagePositionPatient, ipp.c_str());
  // Rows along +y, columns along -z (sagittal): normal = (-1, 0, 0).
  ds.putAndInsertString(DCM_ImageOrientationPatient, "0\\1\\0\\0\\0\\-1");
  ds.putAndInsertString(DCM_PixelSpacing, "2\\0.5");
  ds.putAndInsertUint16(DCM_Rows, 3);
  ds.putAndInsertUint16(DCM_Columns, 4);
  ds.putAndInsertUint16(DCM_SamplesPerPixel, s.samples_per_pixel);
  ds.putAndInsertString(DCM_PhotometricInterpretation, s.photometric.c_str());
  ds.putAndInsertUint16(DCM_BitsAllocated, s.bits_allocated);
  ds.putAndInsertUint16(DCM_BitsStored, s.bits_stored);
  ds.putAndInsertUint16(DCM_HighBit, s.high_bit);
  ds.putAndInsertUint16(DCM_PixelRepresentation, s.pixel_representation);
  if (!s.slope.empty()) {
    ds.putAndInsertString(DCM_RescaleSlope, s.slope.c_str());
  }
  if (!s.intercept.empty()) {
    ds.putAndInsertString(DCM_RescaleIntercept, s.intercept.c_str());
  }
  std::vector<Uint8> bytes;
  for (uint32_t v : s.raw) {
    for (int b = 0; b < s.bits_allocated / 8; ++b) {
      bytes.push_back(static_cast<Uint8>(v >> (8 * b)));
    }
  }
  if (s.bits_allocated == 8) {
    ds.putAndInsertUint8Array(DCM_PixelData, bytes.data(), bytes.size());
  } else {
    std::vector<Uint16> words(bytes.size() / 2);
    for (size_t w = 0; w < words.size(); ++w) {
      words[w] = static_cast<Uint16>(bytes[2 * w] | bytes[2 * w + 1] << 8);
    }
    ds.putAndInsertUint16Array(DCM_PixelData, words.data(), words.size());
  }
  Save(file, path);
}

std::vector<float> ReadSynthetic(const std::vector<Synthetic>& slices) {
  TempDir dir;
  const std::string uid = NewUid();
  for (size_t k = 0; k < slices.size(); ++k) {
    WriteSynthetic(slices[k], uid,
                   dir.path() / ("s" + std::to_string(k) + ".dcm"));
  }
  const auto series = Read({dir.str()});
  EXPECT_TRUE(series.ok()) << series.status();
  if (!series.ok()) return {};
  return series->image.data;
}

TEST(ReadDicomSeriesTest, SignedBitsStoredAreMaskedAndSignExtended) {
  Synthetic s;
  s.bits_stored = 12;
  s.high_bit = 11;
  s.pixel_representation = 1;
  s.slope = "2";
  s.intercept = "-10";
  // 12-bit two's complement with garbage (overlay bits) in bits 12..15.
  const std::vector<int> stored = {-2048, -1, 0, 1, 2047,  -100,
                                   100,   -7, 7, 0, -2048, 2047};
  for (size_t n = 0; n < stored.size(); ++n) {
    s.raw.push_back((static_cast<uint32_t>(stored[n]) & 0x0fff) |
                    (n % 2 == 0 ? 0xa000u : 0x5000u));
  }
  const std::vector<float> values = ReadSynthetic({s});
  ASSERT_EQ(values.size(), stored.size());
  for (size_t n = 0; n < stored.size(); ++n) {
    EXPECT_EQ(values[n], stored[n] * 2.0f - 10) << n;
  }
}

TEST(ReadDicomSeriesTest, HighBitBelowTheTopShiftsTheStoredBits) {
  Synthetic s;
  s.bits_stored = 12;
  s.high_bit = 15;  // stored in bits 4..15
  s.raw.assign(12, 0);
  for (int n = 0; n < 12; ++n) s.raw[n] = (n * 300u) << 4 | 0x000f;
  const std::vector<float> values = ReadSynthetic({s});
  ASSERT_EQ(values.size(), 12u);
  for (int n = 0; n < 12; ++n) EXPECT_EQ(values[n], n * 300.0f) << n;
}

TEST(ReadDicomSeriesTest, EightAndThirtyTwoBitsAndPerSliceRescale) {
  // 8-bit unsigned, MONOCHROME1 (no inversion); one slice without rescale,
  // one with its own.
  Synthetic a;
  a.bits_allocated = a.bits_stored = 8;
  a.high_bit = 7;
  a.photometric = "MONOCHROME1";
  a.x = 10;
  for (int n = 0; n < 12; ++n) a.raw.push_back(n * 20);
  Synthetic a2 = a;
  a2.x = 13;  // position -13 along the normal: before a (-10)
  a2.slope = "3";
  a2.intercept = "-1";
  const std::vector<float> eight = ReadSynthetic({a, a2});
  ASSERT_EQ(eight.size(), 24u);
  for (int n = 0; n < 12; ++n) {
    EXPECT_EQ(eight[n], n * 20.0f * 3 - 1) << n;
    EXPECT_EQ(eight[12 + n], n * 20.0f) << n;
  }

  Synthetic b;  // 32-bit signed with its own slope and intercept
  b.bits_allocated = b.bits_stored = 32;
  b.high_bit = 31;
  b.pixel_representation = 1;
  b.slope = "0.5";
  b.intercept = "100";
  b.x = 13;
  for (int n = 0; n < 12; ++n) {
    b.raw.push_back(static_cast<uint32_t>((n - 6) * 100000));
  }
  Synthetic b2 = b;
  b2.x = 10;
  b2.slope = "1";
  b2.intercept = "0";
  TempDir dir;
  const std::string uid = NewUid();
  WriteSynthetic(b2, uid, dir.path() / "a.dcm");
  WriteSynthetic(b, uid, dir.path() / "b.dcm");
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  const Grid& grid = series->image.grid;
  EXPECT_EQ(grid.size, (Index3{4, 3, 2}));
  // PixelSpacing 2\0.5: 2 mm between rows (j), 0.5 mm between columns (i).
  EXPECT_EQ(grid.spacing[0], 0.5);
  EXPECT_EQ(grid.spacing[1], 2.0);
  EXPECT_NEAR(grid.spacing[2], 3.0, 1e-12);
  EXPECT_EQ(fs::path(series->slices[0].path).filename(), "b.dcm");
  EXPECT_NEAR(series->slices[0].position_along_normal, -13, 1e-12);
  EXPECT_EQ(grid.origin, (Vec3{13, 20, 30}));
  const Mat3 expected_direction = {0, 0, -1, 1, 0, 0, 0, -1, 0};
  for (int c = 0; c < 9; ++c) {
    EXPECT_NEAR(grid.direction[c], expected_direction[c], 1e-12) << c;
  }
  for (int n = 0; n < 12; ++n) {
    EXPECT_EQ(series->image.data[n], (n - 6) * 100000 * 0.5f + 100) << n;
    EXPECT_EQ(series->image.data[12 + n], (n - 6) * 100000.0f) << n;
  }
}

TEST(ReadDicomSeriesTest, ColourIsUnimplemented) {
  Synthetic s;
  s.bits_allocated = s.bits_stored = 8;
  s.high_bit = 7;
  s.samples_per_pixel = 3;
  s.photometric = "RGB";
  s.raw.assign(36, 7);
  TempDir dir;
  WriteSynthetic(s, NewUid(), dir.path() / "rgb.dcm");
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("SamplesPerPixel"), HasSubstr("rgb.dcm")));
}

TEST(ReadDicomSeriesTest, EncodedCopiesReadTheSameAsTheOriginal) {
  static const bool registered = [] {
    DJEncoderRegistration::registerCodecs();
    DJLSEncoderRegistration::registerCodecs();
    DcmRLEEncoderRegistration::registerCodecs();
    return true;
  }();
  (void)registered;
  // Reading decodes with the decoders ReadDicomSeries registers itself.
  const auto original = Read({kThick.string()});
  ASSERT_TRUE(original.ok()) << original.status();
  for (const E_TransferSyntax xfer :
       {EXS_LittleEndianImplicit, EXS_BigEndianExplicit,
        EXS_DeflatedLittleEndianExplicit, EXS_RLELossless, EXS_JPEGProcess14SV1,
        EXS_JPEGLSLossless}) {
    SCOPED_TRACE(DcmXfer(xfer).getXferName());
    TempDir dir;
    for (const std::string& name : kThickNames) {
      auto file = Load(kThick / name);
      ASSERT_TRUE(
          file->getDataset()->chooseRepresentation(xfer, nullptr).good());
      ASSERT_TRUE(file->getDataset()->canWriteXfer(xfer));
      Save(*file, dir.path() / name, xfer);
    }
    auto check = Load(dir.path() / "I10.dcm");
    ASSERT_EQ(check->getDataset()->getOriginalXfer(), xfer);
    const auto copy = Read({dir.str()});
    ASSERT_TRUE(copy.ok()) << copy.status();
    EXPECT_EQ(copy->image.grid.size, original->image.grid.size);
    EXPECT_TRUE(copy->image.data == original->image.data);
  }
}

TEST(ReadDicomSeriesTest, JpegTwoThousandDecodesThroughGdcm) {
  const fs::path path = fs::path(::interslice::testing::TestDataDir()) /
                        "codecs" / "jpeg_2000.dcm";
  const auto series = Read({path.string()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size, (Index3{512, 512, 1}));
  const auto [lo, hi] =
      std::minmax_element(series->image.data.begin(), series->image.data.end());
  EXPECT_LT(*lo, -500);  // air in HU
  EXPECT_GT(*hi, 300);   // bone
}

// One Siemens MR slice in 9 transfer syntaxes with identical pixels
// (neurolabusc/dcm_qa_ts): explicit LE (1), implicit LE (2), explicit BE
// (3), RLE (4), JPEG lossless SV1 (5, 6), JPEG-LS lossless (7, 8), JPEG 2000
// lossless (9).
TEST(ReadDicomSeriesTest, AllTransferSyntaxesDecodeToTheSameVoxels) {
  const fs::path dir =
      fs::path(::interslice::testing::TestDataDir()) / "transfer-syntaxes";
  const auto reference = Read({(dir / "1.dcm").string()});
  ASSERT_TRUE(reference.ok()) << reference.status();
  EXPECT_EQ(reference->image.grid.size, (Index3{384, 384, 1}));
  EXPECT_GT(*std::max_element(reference->image.data.begin(),
                              reference->image.data.end()),
            0);
  for (int f = 2; f <= 9; ++f) {
    const std::string name = std::to_string(f) + ".dcm";
    SCOPED_TRACE(name);
    const auto copy = Read({(dir / name).string()});
    ASSERT_TRUE(copy.ok()) << copy.status();
    EXPECT_EQ(copy->image.grid.size, reference->image.grid.size);
    EXPECT_TRUE(copy->image.data == reference->image.data);
  }
}

TEST(ReadDicomSeriesTest, UndecodableTransferSyntaxIsNamed) {
  static const bool registered = [] {
    DJLSEncoderRegistration::registerCodecs();
    return true;
  }();
  (void)registered;
  TempDir dir;
  auto file = Load(kThick / "I10.dcm");
  ASSERT_TRUE(file->getDataset()
                  ->chooseRepresentation(EXS_JPEGLSLossless, nullptr)
                  .good());
  const fs::path path = dir.path() / "j2kpart2.dcm";
  Save(*file, path, EXS_JPEGLSLossless);
  // Relabel as JPEG 2000 Part 2 (same UID length), which neither DCMTK nor
  // the GDCM fallback decodes.
  std::string bytes;
  {
    std::ifstream in(path, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), {});
  }
  const std::string from = "1.2.840.10008.1.2.4.80";
  const std::string to = "1.2.840.10008.1.2.4.92";
  const size_t at = bytes.find(from);
  ASSERT_NE(at, std::string::npos);
  bytes.replace(at, from.size(), to);
  WriteText(path, bytes);
  const auto result = Read({path.string()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("JPEG 2000 Part 2"), HasSubstr(to),
                    HasSubstr("j2kpart2.dcm")));
}
TEST(ReadDicomSeriesTest, ThreadCountDoesNotChangeTheResult) {
  ComputeContext one;
  one.threads = 1;
  ComputeContext two;
  two.threads = 2;
  const auto a = ReadDicomSeries({kThick.string()}, {}, one);
  const auto b = ReadDicomSeries({kThick.string()}, {}, two);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_TRUE(a->image.data == b->image.data);
}

TEST(ReadDicomSeriesTest, ReportsProgressAndHonoursCancellation) {
  std::vector<double> fractions;
  ComputeContext context;
  context.progress = [&](const ProgressEvent& e) {
    EXPECT_EQ(e.stage, "read");
    fractions.push_back(e.fraction);
  };
  ASSERT_TRUE(ReadDicomSeries({kThick.string()}, {}, context).ok());
  ASSERT_FALSE(fractions.empty());
  EXPECT_TRUE(std::is_sorted(fractions.begin(), fractions.end()));
  EXPECT_DOUBLE_EQ(fractions.back(), 1.0);

  CancellationToken token;
  token.Cancel();
  ComputeContext cancelled;
  cancelled.cancel = &token;
  EXPECT_EQ(ReadDicomSeries({kThick.string()}, {}, cancelled).status().code(),
            absl::StatusCode::kCancelled);
}

TEST(ReadDicomSeriesTest, MissingOrEmptySopUidsAndPrivateTagsAreFine) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I20.dcm"});
  CopyEdited("I30.dcm", dir.path() / "I30.dcm", [](DcmDataset& ds) {
    delete ds.remove(DCM_SOPClassUID);
    delete ds.remove(DCM_SOPInstanceUID);
  });
  CopyEdited("I40.dcm", dir.path() / "I40.dcm", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_SOPInstanceUID, "");
    ds.putAndInsertString(DCM_SOPClassUID, "");
    // A private block with a value and a private sequence.
    ds.putAndInsertString(DcmTag(0x0029, 0x0010, EVR_LO), "ACME 1.0");
    ds.putAndInsertString(DcmTag(0x0029, 0x1010, EVR_LO), "private value");
    DcmItem* item = nullptr;
    ds.findOrCreateSequenceItem(DcmTag(0x0029, 0x1020, EVR_SQ), item, -2);
    ASSERT_NE(item, nullptr);
    item->putAndInsertString(DcmTag(0x0029, 0x0010, EVR_LO), "ACME 1.0");
    item->putAndInsertUint16(DcmTag(0x0029, 0x1030, EVR_US), 7);
  });
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size[2], 4);
  EXPECT_EQ(series->slices[2].sop_instance_uid, "");
  EXPECT_EQ(series->slices[3].sop_instance_uid, "");
}

TEST(ReadDicomSeriesTest, SecondaryCapturesAndOtherModalitiesDoNotBreakIt) {
  TempDir dir;
  CopyThick(dir.path(), kThickNames);
  // A screenshot in the same series: secondary capture with its own size
  // and no geometry.
  CopyEdited("I10.dcm", dir.path() / "sc.dcm", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_SOPClassUID, UID_SecondaryCaptureImageStorage);
    ds.putAndInsertString(DCM_Modality, "OT");
    delete ds.remove(DCM_ImagePositionPatient);
    delete ds.remove(DCM_ImageOrientationPatient);
    ds.putAndInsertUint16(DCM_Rows, 8);
    ds.putAndInsertUint16(DCM_Columns, 8);
    std::vector<Uint16> pixels(64, 1);
    ds.putAndInsertUint16Array(DCM_PixelData, pixels.data(), pixels.size());
  });
  // A secondary capture in the same series that does carry a position (a
  // reformatted view at another size): still not a slice of the stack.
  CopyEdited("I20.dcm", dir.path() / "sc_geometry.dcm", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_SOPClassUID, UID_SecondaryCaptureImageStorage);
    ds.putAndInsertUint16(DCM_Rows, 8);
    ds.putAndInsertUint16(DCM_Columns, 8);
    std::vector<Uint16> pixels(64, 1);
    ds.putAndInsertUint16Array(DCM_PixelData, pixels.data(), pixels.size());
  });
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size, (Index3{kSize, kSize, 4}));
  EXPECT_EQ(series->skipped_files, 2);
  // An MR series in the same folder is another series to choose from.
  const std::string mr_uid = NewUid();
  CopyEdited("I10.dcm", dir.path() / "mr.dcm", [&](DcmDataset& ds) {
    ds.putAndInsertString(DCM_SOPClassUID, UID_MRImageStorage);
    ds.putAndInsertString(DCM_Modality, "MR");
    ds.putAndInsertString(DCM_SeriesInstanceUID, mr_uid.c_str());
  });
  const auto mixed = Read({dir.str()});
  EXPECT_EQ(mixed.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(mixed.status().message(),
              AllOf(HasSubstr("(MR, 1 image)"), HasSubstr("(CT, 4 images)")));
  DicomReadOptions options;
  options.series_instance_uid = series->series_instance_uid;
  const auto chosen = Read({dir.str()}, options);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  EXPECT_EQ(chosen->image.grid.size[2], 4);
}

// A DICOM file, explicit VR little endian, whose data set is Modality, then
// `depth` nested sequences (undefined lengths) and then SeriesInstanceUID.
// Written byte by byte: DCMTK's own writer recurses too.
void WriteDeeplyNested(const fs::path& path, int depth, bool implicit) {
  std::string out(128, '\0');
  out += "DICM";
  auto u16 = [&](uint16_t v) {
    out += static_cast<char>(v & 0xff);
    out += static_cast<char>(v >> 8);
  };
  auto u32 = [&](uint32_t v) {
    u16(v & 0xffff);
    u16(v >> 16);
  };
  auto short_element = [&](uint16_t g, uint16_t e, const char* vr,
                           const std::string& value, bool explicit_vr) {
    u16(g);
    u16(e);
    if (explicit_vr) {
      out += vr;
      u16(static_cast<uint16_t>(value.size()));
    } else {
      u32(static_cast<uint32_t>(value.size()));
    }
    out += value;
  };
  const std::string syntax = implicit
                                 ? std::string("1.2.840.10008.1.2") + '\0'
                                 : std::string("1.2.840.10008.1.2.1") + '\0';
  std::string meta;
  std::swap(out, meta);
  short_element(0x0002, 0x0010, "UI", syntax, true);
  std::string meta_body;
  std::swap(out, meta_body);
  out = meta;
  short_element(0x0002, 0x0000, "UL", std::string(4, '\0'), true);
  const uint32_t length = static_cast<uint32_t>(meta_body.size());
  std::memcpy(&out[out.size() - 4], &length, 4);
  out += meta_body;
  short_element(0x0008, 0x0060, "CS", "CT", !implicit);
  for (int d = 0; d < depth; ++d) {
    u16(0x0008);
    u16(0x1115);  // ReferencedSeriesSequence
    if (!implicit) {
      out += "SQ";
      u16(0);
    }
    u32(0xffffffff);
    u16(0xfffe);
    u16(0xe000);
    u32(0xffffffff);
  }
  for (int d = 0; d < depth; ++d) {
    u16(0xfffe);
    u16(0xe00d);
    u32(0);
    u16(0xfffe);
    u16(0xe0dd);
    u32(0);
  }
  short_element(0x0020, 0x000e, "UI", std::string("1.2.3.4") + '\0', !implicit);
  WriteText(path, out);
}

TEST(ReadDicomSeriesTest, DeeplyNestedSequencesAreRefusedWithoutCrashing) {
  for (const bool implicit : {false, true}) {
    SCOPED_TRACE(implicit ? "implicit VR" : "explicit VR");
    TempDir dir;
    CopyThick(dir.path(), kThickNames);
    // DCMTK 3.6.7 itself (dcmdump) dies of a stack overflow on this file.
    WriteDeeplyNested(dir.path() / "deep.dcm", 10000, implicit);
    const auto series = Read({dir.str()});
    ASSERT_TRUE(series.ok()) << series.status();
    EXPECT_EQ(series->image.grid.size[2], 4);
    EXPECT_EQ(series->skipped_files, 1);
    const auto alone = Read({(dir.path() / "deep.dcm").string()});
    EXPECT_EQ(alone.status().code(), absl::StatusCode::kNotFound);
    EXPECT_THAT(alone.status().message(),
                AllOf(HasSubstr("deep.dcm"), HasSubstr("nested more than")));
  }
}

TEST(ReadDicomSeriesTest, ModeratelyNestedSequencesAreRead) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I20.dcm"});
  // 100 levels, below the limit, written by DCMTK into a real slice.
  CopyEdited("I30.dcm", dir.path() / "I30.dcm", [](DcmDataset& ds) {
    DcmItem* item = &ds;
    for (int d = 0; d < 100; ++d) {
      DcmItem* child = nullptr;
      ASSERT_TRUE(item->findOrCreateSequenceItem(DCM_ReferencedSeriesSequence,
                                                 child, -2)
                      .good());
      item = child;
    }
  });
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size[2], 3);
}

TEST(ReadDicomSeriesTest, TruncatedPixelDataIsAnErrorNamingTheFile) {
  static const bool registered = [] {
    DJLSEncoderRegistration::registerCodecs();
    return true;
  }();
  (void)registered;
  for (const bool encapsulated : {false, true}) {
    SCOPED_TRACE(encapsulated ? "JPEG-LS" : "native");
    TempDir dir;
    CopyThick(dir.path(), {"I10.dcm", "I30.dcm"});
    auto file = Load(kThick / "I20.dcm");
    const E_TransferSyntax xfer =
        encapsulated ? EXS_JPEGLSLossless : EXS_LittleEndianExplicit;
    ASSERT_TRUE(file->getDataset()->chooseRepresentation(xfer, nullptr).good());
    const fs::path path = dir.path() / "cut.dcm";
    Save(*file, path, xfer);
    // Cut off the last third of the file: inside the pixel data.
    const auto size = fs::file_size(path);
    fs::resize_file(path, size - size / 3);
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(result.status().message(), HasSubstr("cut.dcm"));
  }
}

TEST(DecodableTransferSyntaxesTest, ListsWhatTheReaderDecodes) {
  std::set<std::string> uids;
  for (const TransferSyntaxInfo& t : DecodableTransferSyntaxes()) {
    EXPECT_FALSE(t.name.empty()) << t.uid;
    uids.insert(t.uid);
  }
  for (const char* uid : {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1",
                          "1.2.840.10008.1.2.2", "1.2.840.10008.1.2.1.99",
                          "1.2.840.10008.1.2.4.50", "1.2.840.10008.1.2.4.70",
                          "1.2.840.10008.1.2.4.80", "1.2.840.10008.1.2.5",
                          "1.2.840.10008.1.2.4.90", "1.2.840.10008.1.2.4.91"}) {
    EXPECT_TRUE(uids.count(uid)) << uid;
  }
}

// ---- Hardening: attributes validated before decoding, consistency, and
// anonymised exports ------------------------------------------------------

// Copies `src` to `dst` after `edit` changed the file (data set and meta
// header), keeping the transfer syntax and, with EWM_dontUpdateMeta, the
// meta header as edited.
void EditFile(const fs::path& src, const fs::path& dst,
              const std::function<void(DcmFileFormat&)>& edit,
              E_FileWriteMode mode = EWM_fileformat) {
  auto file = Load(src);
  edit(*file);
  const OFCondition cond =
      file->saveFile(OFFilename(dst.c_str()), EXS_Unknown, EET_UndefinedLength,
                     EGL_recalcGL, EPD_noChange, 0, 0, mode);
  ASSERT_TRUE(cond.good()) << cond.text();
}

void EditDataset(const fs::path& src, const fs::path& dst,
                 const std::function<void(DcmDataset&)>& edit) {
  EditFile(src, dst, [&](DcmFileFormat& f) { edit(*f.getDataset()); });
}

const fs::path kJpeg2000Ct =
    fs::path(::interslice::testing::TestDataDir()) / "codecs" / "jpeg_2000.dcm";
// An MR slice in JPEG 2000 (GDCM takes another rescale path for MR).
const fs::path kJpeg2000Mr = fs::path(::interslice::testing::TestDataDir()) /
                             "transfer-syntaxes" / "9.dcm";

// Two slices of a JPEG 2000 file, 5 mm apart along the normal, after `edit`.
void WriteJpeg2000Pair(const fs::path& src, const fs::path& dir,
                       const std::function<void(DcmDataset&)>& edit) {
  for (int k = 0; k < 2; ++k) {
    EditDataset(
        src, dir / ("j" + std::to_string(k) + ".dcm"), [&](DcmDataset& ds) {
          double ipp[3], iop[6];
          for (int c = 0; c < 3; ++c) {
            ds.findAndGetFloat64(DCM_ImagePositionPatient, ipp[c], c);
          }
          for (int c = 0; c < 6; ++c) {
            ds.findAndGetFloat64(DCM_ImageOrientationPatient, iop[c], c);
          }
          const double n[3] = {iop[1] * iop[5] - iop[2] * iop[4],
                               iop[2] * iop[3] - iop[0] * iop[5],
                               iop[0] * iop[4] - iop[1] * iop[3]};
          char text[200];
          std::snprintf(text, sizeof(text), "%.6f\\%.6f\\%.6f",
                        ipp[0] + 5 * k * n[0], ipp[1] + 5 * k * n[1],
                        ipp[2] + 5 * k * n[2]);
          ds.putAndInsertString(DCM_ImagePositionPatient, text);
          ds.putAndInsertString(DCM_SOPInstanceUID, NewUid().c_str());
          edit(ds);
        });
  }
}

// GDCM aborted the whole process (gdcmImageHelper.cxx:1214, assertion
// 'interceptslope[1] != 0.') on an MR JPEG 2000 slice with an empty
// RescaleSlope; for CT it silently used 1.
TEST(HardeningTest, EmptyRescaleSlopeOnJpeg2000IsRefusedBeforeDecoding) {
  for (const fs::path& src : {kJpeg2000Mr, kJpeg2000Ct}) {
    TempDir dir;
    WriteJpeg2000Pair(src, dir.path(), [](DcmDataset& ds) {
      ds.putAndInsertString(DCM_RescaleSlope, "");
    });
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument)
        << src;
    EXPECT_THAT(result.status().message(),
                AllOf(HasSubstr("j0.dcm"), HasSubstr("RescaleSlope"),
                      HasSubstr("empty")));
  }
}

TEST(HardeningTest, RescaleValuesMustBeOneFiniteNumberAndSlopeNotZero) {
  struct Case {
    DcmTagKey tag;
    const char* value;
    const char* attribute;
    const char* why;
  };
  const Case cases[] = {
      {DCM_RescaleSlope, "", "RescaleSlope", "empty"},
      {DCM_RescaleSlope, "abc", "RescaleSlope", "not one finite number"},
      {DCM_RescaleSlope, "0", "RescaleSlope", "is 0"},
      {DCM_RescaleSlope, "-0.0", "RescaleSlope", "is 0"},
      {DCM_RescaleSlope, "1e999", "RescaleSlope", "not one finite number"},
      {DCM_RescaleSlope, "1\\2", "RescaleSlope", "not one finite number"},
      {DCM_RescaleIntercept, "", "RescaleIntercept", "empty"},
      {DCM_RescaleIntercept, "x", "RescaleIntercept", "not one finite number"},
  };
  for (const Case& c : cases) {
    TempDir dir;
    CopyThick(dir.path(), {"I10.dcm", "I20.dcm", "I40.dcm"});
    CopyEdited("I30.dcm", dir.path() / "I30.dcm",
               [&](DcmDataset& ds) { ds.putAndInsertString(c.tag, c.value); });
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument)
        << c.attribute << " '" << c.value << "'";
    EXPECT_THAT(
        result.status().message(),
        AllOf(HasSubstr("I30.dcm"), HasSubstr(c.attribute), HasSubstr(c.why)))
        << c.value;
  }
}

// Task: a slice with RescaleSlope 0 was read (every voxel = intercept).
TEST(HardeningTest, SliceWithRescaleSlopeZeroIsAnError) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I20.dcm", "I40.dcm"});
  CopyEdited("I30.dcm", dir.path() / "I30.dcm", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_RescaleSlope, "0");
  });
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("I30.dcm"), HasSubstr("RescaleSlope")));
}

TEST(HardeningTest, FrameWithRescaleSlopeZeroIsNamedWithItsFrame) {
  TempDir dir;
  const fs::path src = fs::path(::interslice::testing::TestDataDir()) /
                       "multiframe" / "philips-enhanced-mr-64frames.dcm";
  EditDataset(src, dir.path() / "enhanced.dcm", [](DcmDataset& ds) {
    DcmItem* frame = nullptr;
    ASSERT_TRUE(ds.findAndGetSequenceItem(DCM_PerFrameFunctionalGroupsSequence,
                                          frame, 4)
                    .good());
    DcmItem* transform = nullptr;
    ASSERT_TRUE(frame
                    ->findAndGetSequenceItem(
                        DCM_PixelValueTransformationSequence, transform, 0)
                    .good());
    transform->putAndInsertString(DCM_RescaleSlope, "0");
  });
  DicomReadOptions options;
  options.volume = "anything";
  const auto result = Read({dir.str()}, options);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("enhanced.dcm frame 5"),
                    HasSubstr("RescaleSlope (0028,1053) is 0")));
}

// A slice of another frame of reference is read (the geometry is one stack:
// see ReadDicomSeriesTest.SlicesEachWithTheirOwnFrameOfReference...) with a
// note, and refused with strict_frame_of_reference.
TEST(HardeningTest, SliceOfAnotherFrameOfReferenceIsAnErrorWhenStrict) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I20.dcm", "I40.dcm"});
  const std::string other = NewUid();
  CopyEdited("I30.dcm", dir.path() / "I30.dcm", [&](DcmDataset& ds) {
    ds.putAndInsertString(DCM_FrameOfReferenceUID, other.c_str());
  });
  DicomReadOptions strict;
  strict.strict_frame_of_reference = true;
  const auto result = Read({dir.str()}, strict);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("FrameOfReferenceUID"), HasSubstr("I30.dcm"),
                    HasSubstr("3 of the 4 slices"), Not(HasSubstr(other)),
                    Not(HasSubstr("1.3.46.670589"))));
  const auto read = Read({dir.str()});
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_THAT(read->warnings,
              ::testing::ElementsAre(HasSubstr(
                  "FrameOfReferenceUID not the same on every slice (2 "
                  "different UIDs among the 4 slices)")));
}

TEST(HardeningTest,
     SliceWithoutTheFrameOfReferenceOfTheOthersIsAnErrorWhenStrict) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I20.dcm", "I40.dcm"});
  CopyEdited("I30.dcm", dir.path() / "I30.dcm",
             [](DcmDataset& ds) { delete ds.remove(DCM_FrameOfReferenceUID); });
  DicomReadOptions strict;
  strict.strict_frame_of_reference = true;
  const auto result = Read({dir.str()}, strict);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(), AllOf(HasSubstr("FrameOfReferenceUID"),
                                               HasSubstr("I30.dcm has none")));
  const auto read = Read({dir.str()});
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_THAT(read->warnings,
              ::testing::ElementsAre(
                  HasSubstr("FrameOfReferenceUID not the same on every slice "
                            "(1 UID among the 4 slices, 1 without one)")));
}

TEST(HardeningTest, SliceOfAnotherModalityIsAnError) {
  TempDir dir;
  CopyThick(dir.path(), {"I10.dcm", "I20.dcm", "I40.dcm"});
  CopyEdited("I30.dcm", dir.path() / "I30.dcm",
             [](DcmDataset& ds) { ds.putAndInsertString(DCM_Modality, "MR"); });
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("Modality"), HasSubstr("I30.dcm has MR"),
                    HasSubstr("have CT")));
}

TEST(HardeningTest, SliceWithOtherBitsStoredIsAnError) {
  // The three first slices with BitsStored 16, the last with 8.
  std::vector<Synthetic> slices(4);
  for (int k = 0; k < 4; ++k) {
    slices[k].x = 10 + k;
    slices[k].raw.assign(12, 100);
  }
  slices[3].bits_stored = 8;
  slices[3].high_bit = 7;
  TempDir dir;
  const std::string uid = NewUid();
  for (int k = 0; k < 4; ++k) {
    WriteSynthetic(slices[k], uid,
                   dir.path() / ("s" + std::to_string(k) + ".dcm"));
  }
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("BitsStored"), HasSubstr("s3.dcm has 8"),
                    HasSubstr("3 of the 4 slices"), HasSubstr("have 16")));
}

TEST(HardeningTest, SliceWithOtherPixelRepresentationIsAnError) {
  std::vector<Synthetic> slices(3);
  TempDir dir;
  const std::string uid = NewUid();
  for (int k = 0; k < 3; ++k) {
    slices[k].x = 10 + k;
    slices[k].raw.assign(12, 100);
    slices[k].pixel_representation = k == 0 ? 1 : 0;
    WriteSynthetic(slices[k], uid,
                   dir.path() / ("s" + std::to_string(k) + ".dcm"));
  }
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("PixelRepresentation"),
                    HasSubstr("s0.dcm has 1 (signed)"),
                    HasSubstr("have 0 (unsigned)")));
}

// GDCM sized its output buffer from Rows/Columns and wrote the codestream's
// samples into it (heap overflow when the codestream is larger, an assert
// abort when it is smaller); the codestream is now checked first.
TEST(HardeningTest, Jpeg2000CodestreamOfAnotherSizeIsRefused) {
  for (int size : {256, 1024}) {
    TempDir dir;
    WriteJpeg2000Pair(kJpeg2000Ct, dir.path(), [&](DcmDataset& ds) {
      ds.putAndInsertUint16(DCM_Rows, size);
      ds.putAndInsertUint16(DCM_Columns, size);
    });
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument)
        << size;
    EXPECT_THAT(result.status().message(),
                AllOf(HasSubstr("j0.dcm"), HasSubstr("512 x 512"),
                      HasSubstr("Columns x Rows")));
  }
}

// The codestream holds 16-bit samples; GDCM wrote them as such into a
// buffer sized for 8 bits per sample.
TEST(HardeningTest, Jpeg2000PrecisionMustFitBitsAllocated) {
  TempDir dir;
  WriteJpeg2000Pair(kJpeg2000Ct, dir.path(), [](DcmDataset& ds) {
    ds.putAndInsertUint16(DCM_BitsAllocated, 8);
    ds.putAndInsertUint16(DCM_BitsStored, 8);
    ds.putAndInsertUint16(DCM_HighBit, 7);
    delete ds.remove(DCM_PixelPaddingValue);
  });
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("j0.dcm"), HasSubstr("16-bit samples"),
                    HasSubstr("BitsAllocated 8")));
}

TEST(HardeningTest, Jpeg2000PairStillDecodes) {
  TempDir dir;
  WriteJpeg2000Pair(kJpeg2000Ct, dir.path(), [](DcmDataset&) {});
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  const auto single = Read({kJpeg2000Ct.string()});
  ASSERT_TRUE(single.ok()) << single.status();
  ASSERT_EQ(series->image.grid.size, (Index3{512, 512, 2}));
  EXPECT_NEAR(series->image.grid.spacing[2], 5, 1e-4);
  const size_t plane = 512 * 512;
  for (size_t i = 0; i < plane; ++i) {
    ASSERT_EQ(series->image.data[i], single->image.data[i]) << i;
    ASSERT_EQ(series->image.data[plane + i], single->image.data[i]) << i;
  }
}

// ---- Anonymised exports ---------------------------------------------------

// Copies of the thick slices with the UIDs an anonymiser blanks: removed on
// odd slices, emptied on even ones; the meta header keeps its
// MediaStorageSOPClassUID unless `keep_meta_class` is false.
void WriteAnonymised(const fs::path& dir, bool keep_meta_class,
                     const std::function<void(DcmDataset&)>& edit = {}) {
  for (size_t k = 0; k < kThickNames.size(); ++k) {
    EditFile(
        kThick / kThickNames[k], dir / kThickNames[k],
        [&](DcmFileFormat& f) {
          DcmDataset& ds = *f.getDataset();
          for (const DcmTagKey& tag :
               {DCM_SOPClassUID, DCM_SOPInstanceUID, DCM_SeriesInstanceUID,
                DCM_StudyInstanceUID}) {
            if (k % 2 == 1) {
              delete ds.remove(tag);
            } else {
              ds.putAndInsertString(tag, "");
            }
          }
          DcmMetaInfo& meta = *f.getMetaInfo();
          meta.putAndInsertString(DCM_MediaStorageSOPInstanceUID, "");
          if (!keep_meta_class) {
            delete meta.remove(DCM_MediaStorageSOPClassUID);
          }
          if (edit) edit(ds);
        },
        EWM_dontUpdateMeta);
  }
}

void ExpectSameVolume(const DicomSeries& a, const DicomSeries& b) {
  EXPECT_EQ(a.image.grid.size, b.image.grid.size);
  EXPECT_EQ(a.image.grid.spacing, b.image.grid.spacing);
  EXPECT_EQ(a.image.grid.origin, b.image.grid.origin);
  EXPECT_EQ(a.image.grid.direction, b.image.grid.direction);
  EXPECT_TRUE(a.image.data == b.image.data);
  ASSERT_EQ(a.slices.size(), b.slices.size());
  for (size_t k = 0; k < a.slices.size(); ++k) {
    EXPECT_EQ(fs::path(a.slices[k].path).filename(),
              fs::path(b.slices[k].path).filename());
  }
}

TEST(AnonymisedTest, SeriesWithoutUidsIsReadFromTheMetaHeaderAndGeometry) {
  TempDir dir;
  WriteAnonymised(dir.path(), /*keep_meta_class=*/true);
  const auto original = Read({kThick.string()});
  ASSERT_TRUE(original.ok()) << original.status();
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  ExpectSameVolume(*series, *original);
  EXPECT_EQ(series->sop_class_uid, UID_CTImageStorage);
  EXPECT_EQ(series->series_instance_uid, "");
  EXPECT_EQ(series->study_instance_uid, "");
  EXPECT_EQ(series->frame_of_reference_uid, original->frame_of_reference_uid);
  EXPECT_THAT(
      series->notes,
      ::testing::UnorderedElementsAre(
          "SeriesInstanceUID missing on 4 files: series grouped by frame of "
          "reference, modality, series number, orientation, size and pixel "
          "spacing",
          "SOPClassUID missing on 4 files: taken from the file meta header "
          "(MediaStorageSOPClassUID)",
          "SOPInstanceUID missing on 4 files",
          "StudyInstanceUID missing on 4 files"));
  for (const std::string& note : series->notes) {
    EXPECT_THAT(note, Not(HasSubstr("1.")));  // no UID in a note
  }
  EXPECT_TRUE(original->notes.empty());
}

TEST(AnonymisedTest, FilesWithoutAnySopClassAreReadByTheirGeometry) {
  TempDir dir;
  WriteAnonymised(dir.path(), /*keep_meta_class=*/false, [](DcmDataset& ds) {
    delete ds.remove(DCM_FrameOfReferenceUID);
    delete ds.remove(DCM_SeriesNumber);
  });
  const auto original = Read({kThick.string()});
  ASSERT_TRUE(original.ok()) << original.status();
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  ExpectSameVolume(*series, *original);
  EXPECT_EQ(series->sop_class_uid, "");
  EXPECT_THAT(series->notes,
              ::testing::IsSupersetOf(
                  {"SeriesInstanceUID missing on 4 files: series grouped by "
                   "modality, orientation, size and pixel spacing",
                   "SOPClassUID missing on 4 files, also in the file meta "
                   "header: read as image slices by their geometry",
                   "FrameOfReferenceUID missing on 4 files"}));
}

TEST(AnonymisedTest, TwoSeriesWithoutUidsStayTwoAndCanBeChosen) {
  TempDir dir;
  fs::create_directories(dir.path() / "axial");
  fs::create_directories(dir.path() / "coronal");
  WriteAnonymised(dir.path() / "axial", true);
  // The same slices as a coronal series (another orientation), as another
  // reconstruction of the same acquisition would be.
  WriteAnonymised(dir.path() / "coronal", true, [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_ImageOrientationPatient, "1\\0\\0\\0\\0\\-1");
    // Slices along the coronal normal (0, 1, 0).
    Float64 z = 0;
    ds.findAndGetFloat64(DCM_ImagePositionPatient, z, 2);
    const std::string position = "-115.5\\" + std::to_string(z) + "\\100";
    ds.putAndInsertString(DCM_ImagePositionPatient, position.c_str());
  });
  const auto both = Read({dir.str()});
  EXPECT_EQ(both.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(both.status().message(),
              AllOf(HasSubstr("2 image series"), HasSubstr("no-uid-1"),
                    HasSubstr("no-uid-2"), HasSubstr("4 images")));
  const auto listed = ListDicomSeries({dir.str()});
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->size(), 2u);
  std::set<std::string> orientations;
  for (const DicomSeriesSummary& summary : *listed) {
    DicomReadOptions options;
    options.series_instance_uid = summary.series_instance_uid;
    const auto series = Read({dir.str()}, options);
    ASSERT_TRUE(series.ok()) << series.status();
    EXPECT_EQ(series->slices.size(), 4u);
    const fs::path folder = fs::path(series->slices[0].path).parent_path();
    orientations.insert(folder.filename().string());
    for (const DicomSliceInfo& slice : series->slices) {
      EXPECT_EQ(fs::path(slice.path).parent_path(), folder);
    }
  }
  EXPECT_EQ(orientations, (std::set<std::string>{"axial", "coronal"}));
}

TEST(AnonymisedTest, SameSeriesWithDifferentlyFormattedNumbersStaysOne) {
  TempDir dir;
  WriteAnonymised(dir.path(), true, [](DcmDataset& ds) {
    OFString position;
    ds.findAndGetOFStringArray(DCM_ImagePositionPatient, position);
    // I10 and I30 write orientation and spacing with other digits.
    if (position.find("696.21") != OFString_npos ||
        position.find("706.21") != OFString_npos) {
      ds.putAndInsertString(DCM_ImageOrientationPatient,
                            "1.000000\\0.0\\-0.0\\0\\1.0\\0.000000");
      ds.putAndInsertString(DCM_PixelSpacing, "0.451171875000\\0.4511718750");
    }
  });
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->slices.size(), 4u);
}

// ImagePositionPatient of a vendored slice, as stored.
std::string PositionOf(const std::string& name) {
  auto file = Load(kThick / name);
  OFString value;
  EXPECT_TRUE(file->getDataset()
                  ->findAndGetOFStringArray(DCM_ImagePositionPatient, value)
                  .good());
  return value.c_str();
}

// Issue 42: a 1 mm chest CT whose anonymiser gave each of its 138 slices its
// own FrameOfReferenceUID was refused ("inconsistent FrameOfReferenceUID:
// ... from 1 of the 138 slices"), although it has one SeriesInstanceUID and
// its geometry is one stack. Here the 4 slices of ct-thick, each with a
// FrameOfReferenceUID of its own; the UIDs given, by file name.
std::map<std::string, std::string> WriteOwnFramesOfReference(
    const fs::path& dir,
    const std::function<void(const std::string&, DcmDataset&)>& edit =
        nullptr) {
  std::map<std::string, std::string> uids;
  for (const std::string& name : kThickNames) {
    uids[name] = NewUid();
    CopyEdited(name, dir / name, [&](DcmDataset& ds) {
      ASSERT_TRUE(
          ds.putAndInsertString(DCM_FrameOfReferenceUID, uids[name].c_str())
              .good());
      if (edit) edit(name, ds);
    });
  }
  return uids;
}

TEST(ReadDicomSeriesTest,
     SlicesEachWithTheirOwnFrameOfReferenceAreOneStackWithANote) {
  TempDir dir;
  const std::map<std::string, std::string> uids =
      WriteOwnFramesOfReference(dir.path());
  const auto original = Read({kThick.string()});
  ASSERT_TRUE(original.ok()) << original.status();
  const auto series = Read({dir.str()});
  ASSERT_TRUE(series.ok()) << series.status();
  ExpectSameVolume(*series, *original);
  // The outputs' Frame of Reference (core/dicom_out takes this one): the
  // first slice's along the normal.
  const std::string first = fs::path(series->slices[0].path).filename();
  EXPECT_EQ(series->frame_of_reference_uid, uids.at(first));
  const std::string note =
      "FrameOfReferenceUID not the same on every slice (4 different UIDs "
      "among the 4 slices): read as one stack because the geometry was "
      "checked (same orientation, Rows/Columns and PixelSpacing, distinct "
      "positions along one slice normal); the outputs use the first slice's "
      "(k = 0)";
  EXPECT_THAT(series->notes, ::testing::ElementsAre(note));
  EXPECT_THAT(series->warnings, ::testing::ElementsAre(note));
  EXPECT_TRUE(original->warnings.empty());
  EXPECT_TRUE(original->notes.empty());
}

TEST(ReadDicomSeriesTest,
     SlicesEachWithTheirOwnFrameOfReferenceAreRefusedWhenStrict) {
  TempDir dir;
  const std::map<std::string, std::string> uids =
      WriteOwnFramesOfReference(dir.path());
  DicomReadOptions strict;
  strict.strict_frame_of_reference = true;
  const auto result = Read({dir.str()}, strict);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  // All 4 differ: not "a different one from 1 of the 4 slices".
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("inconsistent FrameOfReferenceUID: each of the "
                              "4 slices has a different one (e.g. I10.dcm and "
                              "I20.dcm differ)"),
                    Not(HasSubstr("1 of the 4"))));
  for (const auto& [name, uid] : uids) {
    EXPECT_THAT(result.status().message(), Not(HasSubstr(uid)));
  }
}

// What makes differing Frames of Reference acceptable is one stack's
// geometry: slices that are not one stack are still refused, and the error
// says that the UIDs differ too.
TEST(ReadDicomSeriesTest,
     SlicesEachWithTheirOwnFrameOfReferenceButNotOneStackAreRefused) {
  struct Case {
    std::string what;
    std::function<void(DcmDataset&)> edit_i40;
    std::string message;
  };
  const std::vector<Case> cases = {
      {"another orientation",
       [](DcmDataset& ds) {
         ds.putAndInsertString(DCM_ImageOrientationPatient,
                               "1\\0\\0\\0\\0\\-1");
       },
       "inconsistent ImageOrientationPatient: I40.dcm differs from I10.dcm"},
      {"another pixel spacing",
       [](DcmDataset& ds) {
         ds.putAndInsertString(DCM_PixelSpacing, "0.5\\0.5");
       },
       "inconsistent PixelSpacing: I40.dcm"},
      {"the position of another slice",
       [](DcmDataset& ds) {
         ds.putAndInsertString(DCM_ImagePositionPatient,
                               PositionOf("I30.dcm").c_str());
       },
       "at the same slice position"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    TempDir dir;
    WriteOwnFramesOfReference(dir.path(),
                              [&](const std::string& name, DcmDataset& ds) {
                                if (name == "I40.dcm") c.edit_i40(ds);
                              });
    const auto result = Read({dir.str()});
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(result.status().message(),
                AllOf(HasSubstr(c.message),
                      HasSubstr("the slices' FrameOfReferenceUIDs differ as "
                                "well (4 different UIDs), which is accepted "
                                "only when the geometry is one stack")));
  }
}

}  // namespace
}  // namespace interslice
