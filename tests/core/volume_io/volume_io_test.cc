#include "core/volume_io/volume_io.h"

#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/process.h"
#include "tests/testing/tools.h"

namespace interslice {
namespace {

using ::testing::HasSubstr;

// An oblique orthonormal direction (rotation about (1, 2, 2)/3 by 0.6 rad).
Mat3 ObliqueDirection() {
  const double u[3] = {1.0 / 3, 2.0 / 3, 2.0 / 3};
  const double c = std::cos(0.6), s = std::sin(0.6), t = 1 - c;
  return {t * u[0] * u[0] + c,        t * u[0] * u[1] - s * u[2],
          t * u[0] * u[2] + s * u[1], t * u[0] * u[1] + s * u[2],
          t * u[1] * u[1] + c,        t * u[1] * u[2] - s * u[0],
          t * u[0] * u[2] - s * u[1], t * u[1] * u[2] + s * u[0],
          t * u[2] * u[2] + c};
}

Grid TestGrid() {
  Grid grid;
  grid.size = {7, 5, 4};
  grid.spacing = {0.45, 0.7, 2.5};
  grid.origin = {-120.25, 33.5, -701.75};
  grid.direction = ObliqueDirection();
  return grid;
}

Volume<float> TestVolume() {
  Volume<float> volume;
  volume.grid = TestGrid();
  volume.data.resize(volume.grid.VoxelCount());
  for (size_t n = 0; n < volume.data.size(); ++n) {
    // Distinct, non-representable-in-short values, negative and positive.
    volume.data[n] = static_cast<float>(std::sin(0.37 * n) * 1000.0 + 0.125);
  }
  return volume;
}

class VolumeIoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = std::filesystem::path(::testing::TempDir()) /
           (std::string("volume_io_test_") + info->name());
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  std::string Path(const std::string& name) const { return dir_ / name; }

  std::vector<std::string> DirectoryEntries() const {
    std::vector<std::string> names;
    for (const auto& entry : std::filesystem::directory_iterator(dir_)) {
      names.push_back(entry.path().filename().string());
    }
    std::sort(names.begin(), names.end());
    return names;
  }

  static void ExpectGeometryNear(const Grid& actual, const Grid& expected,
                                 double tolerance) {
    EXPECT_EQ(actual.size, expected.size);
    for (int a = 0; a < 3; ++a) {
      EXPECT_NEAR(actual.spacing[a], expected.spacing[a], tolerance) << a;
      EXPECT_NEAR(actual.origin[a], expected.origin[a],
                  tolerance * std::max(1.0, std::abs(expected.origin[a])))
          << a;
    }
    for (int e = 0; e < 9; ++e) {
      EXPECT_NEAR(actual.direction[e], expected.direction[e], tolerance) << e;
    }
  }

  std::filesystem::path dir_;
};

struct FormatCase {
  const char* name;
  double tolerance;
};

TEST_F(VolumeIoTest, FloatRoundTripKeepsValuesAndGeometry) {
  // NIfTI holds its qform/sform in float32; NRRD prints doubles.
  for (const FormatCase& c :
       {FormatCase{"vol.nii.gz", 1e-4}, FormatCase{"vol.nii", 1e-4},
        FormatCase{"vol.nrrd", 1e-5}}) {
    SCOPED_TRACE(c.name);
    const Volume<float> volume = TestVolume();
    ASSERT_TRUE(WriteVolume(volume, Path(c.name)).ok());
    absl::StatusOr<Volume<float>> read = ReadVolumeAsFloat(Path(c.name));
    ASSERT_TRUE(read.ok()) << read.status();
    EXPECT_EQ(read->data, volume.data);
    ExpectGeometryNear(read->grid, volume.grid, c.tolerance);
  }
  EXPECT_EQ(DirectoryEntries(),
            (std::vector<std::string>{"vol.nii", "vol.nii.gz", "vol.nrrd"}));
}

TEST_F(VolumeIoTest, MirroredDirectionRoundTrips) {
  Volume<float> volume = TestVolume();
  for (int r = 0; r < 3; ++r) volume.grid.direction[3 * r] *= -1;  // det < 0
  for (const FormatCase& c :
       {FormatCase{"m.nii.gz", 1e-4}, FormatCase{"m.nrrd", 1e-5}}) {
    SCOPED_TRACE(c.name);
    ASSERT_TRUE(WriteVolume(volume, Path(c.name)).ok());
    absl::StatusOr<Volume<float>> read = ReadVolumeAsFloat(Path(c.name));
    ASSERT_TRUE(read.ok()) << read.status();
    EXPECT_EQ(read->data, volume.data);
    ExpectGeometryNear(read->grid, volume.grid, c.tolerance);
  }
}

TEST_F(VolumeIoTest, CompressionFollowsTheExtension) {
  Volume<float> volume;
  volume.grid = TestGrid();
  volume.grid.size = {64, 64, 16};
  volume.data.assign(volume.grid.VoxelCount(), 1.0f);  // compresses well
  const size_t raw = volume.data.size() * sizeof(float);
  ASSERT_TRUE(WriteVolume(volume, Path("a.nii.gz")).ok());
  ASSERT_TRUE(WriteVolume(volume, Path("a.nii")).ok());
  ASSERT_TRUE(WriteVolume(volume, Path("a.nrrd")).ok());
  EXPECT_LT(std::filesystem::file_size(Path("a.nii.gz")), raw / 10);
  EXPECT_GE(std::filesystem::file_size(Path("a.nii")), raw);
  // NRRD data are one gzip member of run-length blocks (see volume_io.h):
  // a 4-byte period is not a run, so only Huffman coding applies.
  EXPECT_LT(std::filesystem::file_size(Path("a.nrrd")), raw / 4);
}

TEST_F(VolumeIoTest, Uint8MaskRoundTrip) {
  Volume<uint8_t> mask;
  mask.grid = TestGrid();
  mask.data.resize(mask.grid.VoxelCount());
  for (size_t n = 0; n < mask.data.size(); ++n) {
    mask.data[n] = (n * 7) % 3 == 0 ? 1 : (n % 11 == 0 ? 255 : 0);
  }
  for (const FormatCase& c :
       {FormatCase{"mask.nii.gz", 1e-4}, FormatCase{"mask.nrrd", 1e-5}}) {
    SCOPED_TRACE(c.name);
    ASSERT_TRUE(WriteVolume(mask, Path(c.name)).ok());
    absl::StatusOr<Volume<float>> read = ReadVolumeAsFloat(Path(c.name));
    ASSERT_TRUE(read.ok()) << read.status();
    ASSERT_EQ(read->data.size(), mask.data.size());
    for (size_t n = 0; n < mask.data.size(); ++n) {
      ASSERT_EQ(read->data[n], static_cast<float>(mask.data[n])) << n;
    }
    ExpectGeometryNear(read->grid, mask.grid, c.tolerance);
  }
}

TEST_F(VolumeIoTest, ExtensionIsCaseInsensitiveAndOverwrites) {
  const Volume<float> volume = TestVolume();
  ASSERT_TRUE(WriteVolume(volume, Path("A.NII.GZ")).ok());
  Volume<float> other = volume;
  other.data[0] = 42.0f;
  ASSERT_TRUE(WriteVolume(other, Path("A.NII.GZ")).ok());
  absl::StatusOr<Volume<float>> read = ReadVolumeAsFloat(Path("A.NII.GZ"));
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(read->data, other.data);
  EXPECT_EQ(DirectoryEntries(), std::vector<std::string>{"A.NII.GZ"});
}

TEST_F(VolumeIoTest, UnknownExtensionIsInvalid) {
  const Volume<float> volume = TestVolume();
  for (const char* name : {"vol.mha", "vol", "vol.gz", ".nii"}) {
    const absl::Status status = WriteVolume(volume, Path(name));
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << name;
    EXPECT_THAT(status.message(), HasSubstr(Path(name)));
    EXPECT_EQ(ReadVolumeAsFloat(Path(name)).status().code(),
              absl::StatusCode::kInvalidArgument)
        << name;
  }
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(VolumeIoTest, UnwritablePathIsInternalAndNamesIt) {
  const Volume<float> volume = TestVolume();
  for (const char* name : {"missing/vol.nii.gz", "missing/vol.nrrd"}) {
    const absl::Status status = WriteVolume(volume, Path(name));
    EXPECT_EQ(status.code(), absl::StatusCode::kInternal) << name;
    EXPECT_THAT(status.message(), HasSubstr(Path(name)));
  }
  EXPECT_TRUE(DirectoryEntries().empty());
}

// A missing directory is found before ITK is handed the path: ITK's NRRD
// writer leaks its state when nrrdSave fails (LeakSanitizer reported it in
// the test above) and NIfTI prints "** ERROR" to stderr.
TEST_F(VolumeIoTest, UnwritablePathNeverReachesItk) {
  const Volume<float> volume = TestVolume();
  for (const char* name :
       {"missing/vol.nii.gz", "missing/vol.nii", "missing/vol.nrrd"}) {
    ::testing::internal::CaptureStderr();
    const absl::Status status = WriteVolume(volume, Path(name));
    const std::string err = ::testing::internal::GetCapturedStderr();
    EXPECT_EQ(status.code(), absl::StatusCode::kInternal) << name;
    EXPECT_THAT(status.message(), HasSubstr("No such file or directory"));
    EXPECT_EQ(err, "") << name;
  }
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(VolumeIoTest, RenameFailureLeavesNoTemporary) {
  // The target is a non-empty directory, so the final rename fails.
  std::filesystem::create_directories(Path("vol.nrrd/sub"));
  const absl::Status status = WriteVolume(TestVolume(), Path("vol.nrrd"));
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(status.message(), HasSubstr(Path("vol.nrrd")));
  EXPECT_EQ(DirectoryEntries(), std::vector<std::string>{"vol.nrrd"});
}

TEST_F(VolumeIoTest, RejectsInconsistentVolumes) {
  Volume<float> volume = TestVolume();
  volume.data.pop_back();
  EXPECT_EQ(WriteVolume(volume, Path("v.nrrd")).code(),
            absl::StatusCode::kInvalidArgument);
  Volume<float> bad_grid = TestVolume();
  bad_grid.grid.spacing[1] = 0;
  EXPECT_EQ(WriteVolume(bad_grid, Path("v.nrrd")).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(DirectoryEntries().empty());
}

std::string FileBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), {});
}

// A gzip file through zlib's gzread (as ITK reads).
std::string GunzipFile(const std::string& path) {
  gzFile in = gzopen(path.c_str(), "rb");
  if (in == nullptr) return "";
  std::string bytes;
  char buffer[1 << 16];
  int n;
  while ((n = gzread(in, buffer, sizeof(buffer))) > 0) bytes.append(buffer, n);
  gzclose(in);
  return bytes;
}

// Larger than one 4 MiB compression block, so the file holds blocks
// deflated in parallel, with float noise like a distance field.
Volume<float> LargeVolume() {
  Volume<float> volume;
  volume.grid = TestGrid();
  volume.grid.size = {160, 150, 61};
  volume.data.resize(volume.grid.VoxelCount());
  for (size_t n = 0; n < volume.data.size(); ++n) {
    volume.data[n] = static_cast<float>(std::sin(0.001 * n) * 80.0 + 1e-3 * n);
  }
  return volume;
}

TEST_F(VolumeIoTest, ParallelNiftiGzipIsItksNiftiGzipped) {
  const Volume<float> volume = LargeVolume();
  ASSERT_TRUE(WriteVolume(volume, Path("v.nii.gz"), {.threads = 2}).ok());
  ASSERT_TRUE(WriteVolume(volume, Path("v.nii")).ok());  // ITK's own writer
  const std::string nii = FileBytes(Path("v.nii"));
  ASSERT_EQ(nii.size(), 352 + volume.data.size() * sizeof(float));
  // Same header (geometry, dims) and voxels as ITK writes them.
  EXPECT_TRUE(GunzipFile(Path("v.nii.gz")) == nii);
  absl::StatusOr<Volume<float>> read = ReadVolumeAsFloat(Path("v.nii.gz"));
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_TRUE(read->data == volume.data);
  ExpectGeometryNear(read->grid, volume.grid, 1e-4);
  // Compressed.
  EXPECT_LT(std::filesystem::file_size(Path("v.nii.gz")), nii.size());
}

TEST_F(VolumeIoTest, ParallelNrrdGzipReadsBackThroughItk) {
  const Volume<float> volume = LargeVolume();
  ASSERT_TRUE(WriteVolume(volume, Path("v.nrrd"), {.threads = 2}).ok());
  const std::string bytes = FileBytes(Path("v.nrrd"));
  const size_t end = bytes.find("\n\n");
  ASSERT_NE(end, std::string::npos);
  const std::string header = bytes.substr(0, end + 2);
  EXPECT_THAT(header, HasSubstr("\nsizes: 160 150 61\n"));
  EXPECT_THAT(header, HasSubstr("\nencoding: gzip\n"));
  EXPECT_THAT(header, HasSubstr("\ntype: float\n"));
  absl::StatusOr<Volume<float>> read = ReadVolumeAsFloat(Path("v.nrrd"));
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_TRUE(read->data == volume.data);
  ExpectGeometryNear(read->grid, volume.grid, 1e-5);
  // One gzip member: a single inflate (as pynrrd reads) gets all the data.
  {
    const std::string compressed = bytes.substr(end + 2);
    z_stream z{};
    ASSERT_EQ(inflateInit2(&z, 16 + MAX_WBITS), Z_OK);
    std::string out(volume.data.size() * sizeof(float) + 1, '\0');
    z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(compressed.data()));
    z.avail_in = static_cast<uInt>(compressed.size());
    z.next_out = reinterpret_cast<Bytef*>(out.data());
    z.avail_out = static_cast<uInt>(out.size());
    EXPECT_EQ(inflate(&z, Z_FINISH), Z_STREAM_END);
    EXPECT_EQ(z.avail_in, 0u);  // nothing after the one member
    EXPECT_EQ(z.total_out, volume.data.size() * sizeof(float));
    inflateEnd(&z);
  }

  Volume<uint8_t> mask;
  mask.grid = volume.grid;
  mask.data.resize(volume.data.size());
  for (size_t n = 0; n < mask.data.size(); ++n) {
    mask.data[n] = volume.data[n] >= 0 ? 1 : 0;
  }
  ASSERT_TRUE(WriteVolume(mask, Path("m.nrrd"), {.threads = 2}).ok());
  EXPECT_THAT(FileBytes(Path("m.nrrd")), HasSubstr("\ntype: unsigned char\n"));
  read = ReadVolumeAsFloat(Path("m.nrrd"));
  ASSERT_TRUE(read.ok()) << read.status();
  for (size_t n = 0; n < mask.data.size(); n += 997) {
    ASSERT_EQ(read->data[n], mask.data[n]) << n;
  }
}

// Readers other than ITK: gzip(1) checks every member's CRC and length;
// Python's gzip module (what nibabel uses) reads all members.
TEST_F(VolumeIoTest, MultiMemberGzipPassesGzipAndPython) {
  const std::string gzip = testing::RequireTool("gzip");
  const std::string python3 = testing::RequireTool("python3");
  ASSERT_FALSE(gzip.empty() || python3.empty());
  const Volume<float> volume = LargeVolume();
  ASSERT_TRUE(WriteVolume(volume, Path("v.nii.gz"), {.threads = 2}).ok());
  ASSERT_TRUE(WriteVolume(volume, Path("v.nii")).ok());
  const testing::CommandResult test =
      testing::RunCommand({gzip, "-t", Path("v.nii.gz")});
  EXPECT_EQ(test.exit_code, 0) << test.err;
  const testing::CommandResult python = testing::RunCommand(
      {python3, "-c",
       "import gzip,sys; a=gzip.open(sys.argv[1]).read(); "
       "b=open(sys.argv[2],'rb').read(); print(len(a), a==b)",
       Path("v.nii.gz"), Path("v.nii")});
  EXPECT_EQ(python.exit_code, 0) << python.err;
  EXPECT_EQ(python.out, absl::StrCat(352 + volume.data.size() * 4, " True\n"));
}

TEST_F(VolumeIoTest, CancelledWriteLeavesNothing) {
  CancellationToken token;
  token.Cancel();
  const absl::Status status =
      WriteVolume(LargeVolume(), Path("v.nii.gz"), {.cancel = &token});
  EXPECT_EQ(status.code(), absl::StatusCode::kCancelled);
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(VolumeIoTest, NiftiAxisLimitIsInvalidArgument) {
  Volume<uint8_t> mask;
  mask.grid = TestGrid();
  mask.grid.size = {40000, 2, 1};
  mask.data.assign(mask.grid.VoxelCount(), 0);
  const absl::Status status = WriteVolume(mask, Path("wide.nii.gz"));
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("32767"));
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(VolumeIoTest, ReadErrors) {
  EXPECT_EQ(ReadVolumeAsFloat(Path("absent.nii.gz")).status().code(),
            absl::StatusCode::kNotFound);
  {
    std::FILE* f = std::fopen(Path("junk.nrrd").c_str(), "wb");
    ASSERT_NE(f, nullptr);
    std::fputs("this is not a NRRD file\n", f);
    std::fclose(f);
  }
  const absl::StatusOr<Volume<float>> read =
      ReadVolumeAsFloat(Path("junk.nrrd"));
  EXPECT_EQ(read.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(read.status().message(), HasSubstr(Path("junk.nrrd")));
}

}  // namespace
}  // namespace interslice
