// Corrupt JPEG 2000 pixel data is an INVALID_ARGUMENT naming the file, never
// a crash, whether CheckJpeg2000Codestream refuses it or GDCM's codec (with
// libopenjp2) fails on it. Under LeakSanitizer (scripts/test-sanitizers.sh)
// the truncated codestream also runs GDCM 3.0's opj_decode error path, which
// leaks libopenjp2's image (suppressed and explained in
// tools/sanitizers/lsan.supp): any other leak on that path fails the test.
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include "absl/status/status.h"
#include "core/dicom/series_reader.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const fs::path kJpeg2000 =
    fs::path(::interslice::testing::TestDataDir()) / "codecs" / "jpeg_2000.dcm";

std::string ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

void WriteBytes(const fs::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

// The test file with its one JPEG 2000 codestream (the pixel data fragment
// that starts with the SOC and SIZ markers) replaced by `codestream`; the
// fragment length is rewritten, so the DICOM structure stays valid.
std::string WithCodestream(std::string file, std::string codestream) {
  const size_t soc = file.find(std::string("\xff\x4f\xff\x51", 4));
  if (soc == std::string::npos || soc < 8) return "";
  const size_t item = soc - 8;
  if (file.compare(item, 4, std::string("\xfe\xff\x00\xe0", 4)) != 0) {
    return "";
  }
  uint32_t length;
  std::memcpy(&length, file.data() + item + 4, 4);  // little endian
  if (codestream.size() % 2 != 0) codestream.push_back('\0');
  const uint32_t new_length = static_cast<uint32_t>(codestream.size());
  std::string out = file.substr(0, item + 4);
  out.append(reinterpret_cast<const char*>(&new_length), 4);
  out += codestream;
  out += file.substr(soc + length);
  return out;
}

std::string Codestream(const std::string& file) {
  const size_t soc = file.find(std::string("\xff\x4f\xff\x51", 4));
  uint32_t length;
  std::memcpy(&length, file.data() + soc - 4, 4);
  return file.substr(soc, length);
}

class CorruptJpeg2000Test : public ::testing::Test {
 protected:
  void ExpectInvalid(const std::string& name, const std::string& codestream) {
    const std::string bytes = WithCodestream(original_, codestream);
    ASSERT_FALSE(bytes.empty());
    const fs::path path = dir_.path() / name;
    WriteBytes(path, bytes);
    const auto series = ReadDicomSeries({path.string()}, {}, {});
    EXPECT_EQ(series.status().code(), absl::StatusCode::kInvalidArgument)
        << series.status();
    EXPECT_THAT(series.status().message(), HasSubstr(name));
  }

  const std::string original_ = ReadBytes(kJpeg2000);
  const std::string codestream_ = Codestream(original_);
  testing::TempDir dir_{"interslice_j2k_"};
};

TEST_F(CorruptJpeg2000Test, UnchangedCopyDecodes) {
  const fs::path path = dir_.path() / "copy.dcm";
  WriteBytes(path, WithCodestream(original_, codestream_));
  const auto series = ReadDicomSeries({path.string()}, {}, {});
  ASSERT_TRUE(series.ok()) << series.status();
  EXPECT_EQ(series->image.grid.size, (Index3{512, 512, 1}));
}

// Refused by CheckJpeg2000Codestream: GDCM never sees it.
TEST_F(CorruptJpeg2000Test, ZeroedCodestream) {
  ExpectInvalid("zeros.dcm", std::string(codestream_.size(), '\0'));
}

// A valid main header: GDCM's codec fails on it (opj_decode finds no tile).
TEST_F(CorruptJpeg2000Test, MainHeaderWithoutTiles) {
  const size_t sot = codestream_.find(std::string("\xff\x90", 2));
  ASSERT_NE(sot, std::string::npos);
  ExpectInvalid("header-only.dcm",
                codestream_.substr(0, sot) + std::string("\xff\xd9", 2));
}

// GDCM's JPEG2000Codec::DecodeByStreamsCommon fails on this (opj_decode) and
// leaks the opj_image_t it got from opj_read_header.
TEST_F(CorruptJpeg2000Test, TruncatedCodestream) {
  ExpectInvalid("truncated.dcm", codestream_.substr(0, codestream_.size() / 2));
}

}  // namespace
}  // namespace interslice
