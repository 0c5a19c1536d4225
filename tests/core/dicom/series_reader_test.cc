#include "core/dicom/series_reader.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcddirif.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
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

const fs::path kThick = fs::path(INTERSLICE_TEST_DATA_DIR) / "ct-thick";
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
class TempDir {
 public:
  TempDir() {
    static std::atomic<int> counter{0};
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    path_ = fs::temp_directory_path() /
            (std::string("interslice_dicom_") + info->name() + "_" +
             std::to_string(::getpid()) + "_" + std::to_string(counter++));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  const fs::path& path() const { return path_; }
  std::string str() const { return path_.string(); }

 private:
  fs::path path_;
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
  const fs::path dir =
      fs::path(INTERSLICE_SOURCE_DIR) / "data" / "ct-head-phantom-thick";
  if (!fs::exists(dir)) GTEST_SKIP() << dir << " is absent";
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

TEST(ReadDicomSeriesTest, MissingSliceIsNonUniformSpacing) {
  const auto result =
      Read({(kThick / "I10.dcm").string(), (kThick / "I20.dcm").string(),
            (kThick / "I40.dcm").string()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("non-uniform slice spacing (5.000 .. 10.000 mm)"),
                    HasSubstr("missing slices?")));
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

TEST(ReadDicomSeriesTest, GantryTiltIsUnimplemented) {
  TempDir dir;
  // Each 5 mm step also moves 5 * tan(20 degrees) mm along y.
  for (int k = 0; k < 4; ++k) {
    CopyEdited(
        kThickNames[k], dir.path() / kThickNames[k], [k](DcmDataset& ds) {
          const double y = -1.85 + k * 5.0 * std::tan(20.0 * M_PI / 180.0);
          const std::string ipp = "-115.5\\" + std::to_string(y) + "\\" +
                                  std::to_string(696.21 + 5 * k);
          ds.putAndInsertString(DCM_ImagePositionPatient, ipp.c_str());
        });
  }
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(result.status().message(),
              HasSubstr("gantry tilt of 20.0 degrees"));
}

TEST(ReadDicomSeriesTest, MultiFrameIsUnimplemented) {
  TempDir dir;
  CopyEdited("I10.dcm", dir.path() / "multi.dcm", [](DcmDataset& ds) {
    ds.putAndInsertString(DCM_NumberOfFrames, "2");
  });
  const auto result = Read({dir.str()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("multi-frame"), HasSubstr("multi.dcm")));
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
  Synthetic a;  // 8-bit unsigned, MONOCHROME1 (no inversion), no rescale
  a.bits_allocated = a.bits_stored = 8;
  a.high_bit = 7;
  a.photometric = "MONOCHROME1";
  a.x = 10;
  for (int n = 0; n < 12; ++n) a.raw.push_back(n * 20);
  Synthetic b;  // 32-bit signed with its own slope and intercept
  b.bits_allocated = b.bits_stored = 32;
  b.high_bit = 31;
  b.pixel_representation = 1;
  b.slope = "0.5";
  b.intercept = "100";
  b.x = 13;  // position -13 along the normal: before a (-10)
  for (int n = 0; n < 12; ++n) {
    b.raw.push_back(static_cast<uint32_t>((n - 6) * 100000));
  }
  TempDir dir;
  const std::string uid = NewUid();
  WriteSynthetic(a, uid, dir.path() / "a.dcm");
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
    EXPECT_EQ(series->image.data[12 + n], n * 20.0f) << n;
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

TEST(ReadDicomSeriesTest, UndecodableTransferSyntaxIsNamed) {
  const fs::path path =
      fs::path(INTERSLICE_TEST_DATA_DIR) / "codecs" / "jpeg_2000.dcm";
  const auto result = Read({path.string()});
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(result.status().message(),
              AllOf(HasSubstr("JPEG 2000"), HasSubstr("jpeg_2000.dcm")));
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

}  // namespace
}  // namespace interslice
