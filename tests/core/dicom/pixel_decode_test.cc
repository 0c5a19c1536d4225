// Decoding on its own (core/dicom/pixel_decode.h): chosen frames of one
// scanned file into caller buffers, with each frame's rescale; the checks
// made against the header before and while reading; the decoded-size bound.
#include "core/dicom/pixel_decode.h"

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/dicom_header.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcrleerg.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using dicom_internal::FileHeader;
using dicom_internal::FileKind;
using dicom_internal::ScanFile;
using ::testing::AllOf;
using ::testing::Each;
using ::testing::HasSubstr;
using ::testing::Not;

// Philips enhanced MR: 64 frames of 64 x 64, 12 of 16 bits stored, two
// volumes (magnitude and field map) with different per-frame rescales.
const fs::path kPhilips = fs::path(::interslice::testing::TestDataDir()) /
                          "multiframe" / "philips-enhanced-mr-64frames.dcm";
constexpr int kPhilipsSide = 64;
constexpr int kPhilipsFrames = 64;
constexpr int kPlane = kPhilipsSide * kPhilipsSide;

class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_decode_") {}
};

// Stored values of frame `frame` of the Philips file as DCMTK reads them,
// BitsStored 12 at HighBit 11, unsigned.
std::vector<uint16_t> StoredValues(const fs::path& path, int frame) {
  DcmFileFormat file;
  EXPECT_TRUE(file.loadFile(OFFilename(path.c_str())).good());
  const Uint16* pixels = nullptr;
  unsigned long count = 0;
  EXPECT_TRUE(file.getDataset()
                  ->findAndGetUint16Array(DCM_PixelData, pixels, &count)
                  .good());
  EXPECT_EQ(count, static_cast<unsigned long>(kPlane) * kPhilipsFrames);
  std::vector<uint16_t> out(kPlane);
  for (int i = 0; i < kPlane; ++i) {
    out[i] = pixels[frame * kPlane + i] & 0x0fff;
  }
  return out;
}

// Two frames with different rescales, so that a wrong frame's (or the
// file's) rescale cannot give the expected values.
struct TwoFrames {
  int a = -1, b = -1;
};

TwoFrames FramesWithDifferentRescales(const FileHeader& h) {
  TwoFrames two;
  two.a = 40;
  for (int f = 0; f < static_cast<int>(h.frames.size()); ++f) {
    if (h.frames[f].rescale_slope != h.frames[two.a].rescale_slope) {
      two.b = f;
      break;
    }
  }
  return two;
}

TEST(DecodeDicomFramesTest, DecodesTheAskedFramesWithTheirOwnRescale) {
  const FileHeader h = ScanFile(kPhilips.string());
  ASSERT_TRUE(h.problem.ok()) << h.problem;
  ASSERT_EQ(h.frames.size(), static_cast<size_t>(kPhilipsFrames));
  const TwoFrames two = FramesWithDifferentRescales(h);
  ASSERT_GE(two.b, 0);

  // Into two separate buffers, the later frame first.
  std::vector<float> first(kPlane, -1e30f), second(kPlane, -1e30f);
  ASSERT_TRUE(DecodeDicomFrames(h, {{.frame = two.a, .out = first.data()},
                                    {.frame = two.b, .out = second.data()}})
                  .ok());
  for (const auto& [frame, values] :
       {std::pair{two.a, &first}, std::pair{two.b, &second}}) {
    const std::vector<uint16_t> stored = StoredValues(kPhilips, frame);
    const double slope = h.frames[frame].rescale_slope;
    const double intercept = h.frames[frame].rescale_intercept;
    int differing = 0;
    for (int i = 0; i < kPlane; ++i) {
      const float expected = static_cast<float>(
          static_cast<double>(stored[i]) * slope + intercept);
      if ((*values)[i] != expected) ++differing;
    }
    EXPECT_EQ(differing, 0) << "frame " << frame;
  }
  EXPECT_NE(first, second);
}

TEST(DecodeDicomFramesTest, AnRleCopyDecodesToTheSameValues) {
  static const bool registered = [] {
    DcmRLEEncoderRegistration::registerCodecs();
    return true;
  }();
  (void)registered;
  TempDir dir;
  const fs::path rle = dir.path() / "rle.dcm";
  {
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile(OFFilename(kPhilips.c_str())).good());
    ASSERT_TRUE(file.getDataset()
                    ->chooseRepresentation(EXS_RLELossless, nullptr)
                    .good());
    ASSERT_TRUE(file.saveFile(OFFilename(rle.c_str()), EXS_RLELossless).good());
  }
  const FileHeader native = ScanFile(kPhilips.string());
  const FileHeader encoded = ScanFile(rle.string());
  ASSERT_TRUE(encoded.problem.ok()) << encoded.problem;
  ASSERT_EQ(encoded.transfer_syntax_uid, UID_RLELosslessTransferSyntax);
  const TwoFrames two = FramesWithDifferentRescales(native);
  std::vector<float> want(2 * kPlane), got(2 * kPlane);
  ASSERT_TRUE(DecodeDicomFrames(
                  native, {{two.b, want.data()}, {two.a, want.data() + kPlane}})
                  .ok());
  ASSERT_TRUE(DecodeDicomFrames(
                  encoded, {{two.b, got.data()}, {two.a, got.data() + kPlane}})
                  .ok());
  EXPECT_TRUE(got == want);
}

TEST(DecodeDicomFramesTest, ConcurrentCallsGiveTheSameValues) {
  const FileHeader h = ScanFile(kPhilips.string());
  std::vector<float> alone(kPhilipsFrames * kPlane);
  std::vector<DicomFrameTarget> all;
  for (int f = 0; f < kPhilipsFrames; ++f) {
    all.push_back({f, alone.data() + f * kPlane});
  }
  ASSERT_TRUE(DecodeDicomFrames(h, all).ok());

  std::vector<float> together(kPhilipsFrames * kPlane);
  std::vector<DicomFrameTarget> even, odd;
  for (int f = 0; f < kPhilipsFrames; ++f) {
    (f % 2 == 0 ? even : odd).push_back({f, together.data() + f * kPlane});
  }
  absl::Status even_status, odd_status;
  std::thread worker([&] { even_status = DecodeDicomFrames(h, even); });
  odd_status = DecodeDicomFrames(h, odd);
  worker.join();
  EXPECT_TRUE(even_status.ok()) << even_status;
  EXPECT_TRUE(odd_status.ok()) << odd_status;
  EXPECT_TRUE(together == alone);
}

// A 4 x 3 single-frame CT slice: 16 bits allocated, 12 stored at HighBit
// 11, signed, RescaleSlope 2, RescaleIntercept -5.
void WriteSlice(const fs::path& path, const std::vector<uint16_t>& raw,
                int rows = 3, int columns = 4) {
  DcmFileFormat file;
  DcmDataset& ds = *file.getDataset();
  char uid[100];
  ds.putAndInsertString(DCM_SOPClassUID, UID_CTImageStorage);
  ds.putAndInsertString(DCM_SOPInstanceUID, dcmGenerateUniqueIdentifier(
                                                uid, SITE_INSTANCE_UID_ROOT));
  ds.putAndInsertString(DCM_SeriesInstanceUID, "1.2.3.4");
  ds.putAndInsertString(DCM_Modality, "CT");
  ds.putAndInsertString(DCM_ImagePositionPatient, "0\\0\\0");
  ds.putAndInsertString(DCM_ImageOrientationPatient, "1\\0\\0\\0\\1\\0");
  ds.putAndInsertString(DCM_PixelSpacing, "1\\1");
  ds.putAndInsertUint16(DCM_Rows, rows);
  ds.putAndInsertUint16(DCM_Columns, columns);
  ds.putAndInsertUint16(DCM_SamplesPerPixel, 1);
  ds.putAndInsertString(DCM_PhotometricInterpretation, "MONOCHROME2");
  ds.putAndInsertUint16(DCM_BitsAllocated, 16);
  ds.putAndInsertUint16(DCM_BitsStored, 12);
  ds.putAndInsertUint16(DCM_HighBit, 11);
  ds.putAndInsertUint16(DCM_PixelRepresentation, 1);
  ds.putAndInsertString(DCM_RescaleSlope, "2");
  ds.putAndInsertString(DCM_RescaleIntercept, "-5");
  ds.putAndInsertUint16Array(DCM_PixelData, raw.data(), raw.size());
  ASSERT_TRUE(
      file.saveFile(OFFilename(path.c_str()), EXS_LittleEndianExplicit).good());
}

TEST(DecodeDicomFramesTest, SingleFrameValuesAreStoredTimesSlopePlusIntercept) {
  TempDir dir;
  const fs::path path = dir.path() / "s.dcm";
  // 12-bit two's complement; the top four bits are garbage to be ignored.
  WriteSlice(path, {0x0001, 0x0fff, 0xf800, 0x07ff, 0x0000, 0xa000, 0x0002,
                    0x0800, 0x0003, 0x0004, 0x0005, 0x0006});
  const FileHeader h = ScanFile(path.string());
  ASSERT_TRUE(h.problem.ok()) << h.problem;
  std::vector<float> out(12);
  ASSERT_TRUE(DecodeDicomFrames(h, {{0, out.data()}}).ok());
  // 1, -1, -2048, 2047, 0, 0, 2, -2048, 3, 4, 5, 6 stored.
  EXPECT_EQ(out, (std::vector<float>{-3, -7, -4101, 4089, -5, -5, -1, -4101, 1,
                                     3, 5, 7}));
}

TEST(DecodeDicomFramesTest, BadTargetsAreRefusedBeforeAnythingIsWritten) {
  TempDir dir;
  const fs::path path = dir.path() / "s.dcm";
  WriteSlice(path, std::vector<uint16_t>(12, 1));
  const FileHeader h = ScanFile(path.string());
  std::vector<float> out(12, 42), other(12, 42);
  for (const DicomFrameTarget& bad :
       {DicomFrameTarget{1, out.data()}, DicomFrameTarget{-1, out.data()},
        DicomFrameTarget{0, nullptr}}) {
    const absl::Status status = DecodeDicomFrames(h, {{0, other.data()}, bad});
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(status.message(), HasSubstr("s.dcm: cannot decode frame"));
  }
  EXPECT_THAT(out, Each(42));
  EXPECT_THAT(other, Each(42));
}

TEST(DecodeDicomFramesTest, HeadersThatAreNotUsableImagesAreRefused) {
  TempDir dir;
  const fs::path path = dir.path() / "s.dcm";
  WriteSlice(path, std::vector<uint16_t>(12, 1));
  FileHeader h = ScanFile(path.string());
  std::vector<float> out(12, 42);
  h.problem = absl::UnimplementedError("s.dcm: colour");
  EXPECT_EQ(DecodeDicomFrames(h, {{0, out.data()}}).code(),
            absl::StatusCode::kUnimplemented);
  h.problem = absl::OkStatus();
  h.kind = FileKind::kNotImage;
  EXPECT_EQ(DecodeDicomFrames(h, {{0, out.data()}}).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(out, Each(42));
}

TEST(DecodeDicomFramesTest, AFileThatChangedSinceItsScanIsRefused) {
  TempDir dir;
  const fs::path path = dir.path() / "s.dcm";
  WriteSlice(path, std::vector<uint16_t>(12, 1));
  const FileHeader h = ScanFile(path.string());
  ASSERT_TRUE(h.problem.ok()) << h.problem;
  std::vector<float> out(12);

  // Rewritten as 3 x 4 instead of 4 x 3.
  WriteSlice(path, std::vector<uint16_t>(12, 1), /*rows=*/4, /*columns=*/3);
  absl::Status status = DecodeDicomFrames(h, {{0, out.data()}});
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(status.message(), "s.dcm: Rows/Columns changed while reading");

  // Cut short inside the pixel data.
  WriteSlice(path, std::vector<uint16_t>(12, 1));
  const uintmax_t size = fs::file_size(path);
  fs::resize_file(path, size - 8);
  status = DecodeDicomFrames(h, {{0, out.data()}});
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(),
              AllOf(HasSubstr("s.dcm"), Not(HasSubstr(dir.str()))));
}

TEST(CheckDecodedSizeTest, CountsEveryFrameOfTheFile) {
  const FileHeader h = ScanFile(kPhilips.string());
  const int64_t voxels = int64_t{kPlane} * kPhilipsFrames;
  EXPECT_TRUE(CheckDecodedSize(h, voxels).ok());
  const absl::Status status = CheckDecodedSize(h, voxels - 1);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(status.message(),
            "philips-enhanced-mr-64frames.dcm holds 64 x 64 x 64 = 262144 "
            "voxels in all its frames, more than the limit of 262143 "
            "(max_voxels)");

  TempDir dir;
  WriteSlice(dir.path() / "s.dcm", std::vector<uint16_t>(12, 1));
  const FileHeader single = ScanFile((dir.path() / "s.dcm").string());
  EXPECT_TRUE(CheckDecodedSize(single, 12).ok());
  EXPECT_EQ(CheckDecodedSize(single, 11).message(),
            "s.dcm holds 4 x 3 x 1 = 12 voxels in all its frames, more than "
            "the limit of 11 (max_voxels)");
}

}  // namespace
}  // namespace interslice
