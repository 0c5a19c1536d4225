// The bounded scan every received instance passes before DCMTK parses it
// (server/node/dataset_scan.h): real files pass in every transfer syntax
// the listener accepts; hostile encodings fail with a message naming what
// and where, within the limits.
#include "server/node/dataset_scan.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcrleerg.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/server/net/dimse/raw_pdu.h"
#include "tests/testing/paths.h"

namespace interslice::server::node {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";
constexpr char kExplicitLe[] = "1.2.840.10008.1.2.1";
constexpr char kImplicitLe[] = "1.2.840.10008.1.2";

std::vector<std::string> DicomFilesUnder(const std::string& dir) {
  std::vector<std::string> files;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (e.path().extension() == ".dcm") files.push_back(e.path().string());
  }
  return files;
}

class ScanTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice-scan-" + std::to_string(::getpid()));
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  // The phantom's first slice re-saved in `xfer`.
  std::string Resaved(E_TransferSyntax xfer, const std::string& name) {
    DcmFileFormat ff;
    EXPECT_TRUE(ff.loadFile(DicomFilesUnder(kPhantom).front().c_str()).good());
    EXPECT_TRUE(ff.getDataset()->chooseRepresentation(xfer, nullptr).good());
    const std::string path = (dir_ / name).string();
    EXPECT_TRUE(ff.saveFile(path.c_str(), xfer).good());
    return path;
  }
  fs::path dir_;
};

TEST_F(ScanTest, EveryShippedDicomFilePasses) {
  std::vector<std::string> files = DicomFilesUnder(kPhantom);
  for (const std::string& f : DicomFilesUnder(
           std::string(::interslice::testing::SourceDir()) + "/tests/data")) {
    files.push_back(f);
  }
  ASSERT_GT(files.size(), 28u);
  for (const std::string& f : files) {
    absl::StatusOr<DatasetScanResult> r = ScanPart10File(f);
    ASSERT_TRUE(r.ok()) << f << ": " << r.status();
    EXPECT_GT(r->dataset_offset, 132) << f;
    EXPECT_GT(r->elements, 10) << f;
    EXPECT_LE(r->deepest, 8) << f;
  }
}

TEST_F(ScanTest, OtherTransferSyntaxesPass) {
  DcmRLEEncoderRegistration::registerCodecs();
  for (auto [xfer, name] :
       std::vector<std::pair<E_TransferSyntax, const char*>>{
           {EXS_LittleEndianImplicit, "implicit.dcm"},
           {EXS_BigEndianExplicit, "big.dcm"},
           {EXS_DeflatedLittleEndianExplicit, "deflated.dcm"},
           {EXS_RLELossless, "rle.dcm"}}) {
    const std::string path = Resaved(xfer, name);
    absl::StatusOr<DatasetScanResult> r = ScanPart10File(path);
    ASSERT_TRUE(r.ok()) << name << ": " << r.status();
    EXPECT_EQ(r->transfer_syntax_uid, DcmXfer(xfer).getXferID()) << name;
  }
  DcmRLEEncoderRegistration::cleanup();
}

TEST_F(ScanTest, DeflatedDataSetIsBoundedWhenInflated) {
  const std::string path = Resaved(EXS_DeflatedLittleEndianExplicit, "d.dcm");
  DatasetScanLimits small;
  small.max_inflated_bytes = 100000;  // a phantom slice inflates to 532 KiB
  absl::StatusOr<DatasetScanResult> r = ScanPart10File(path, small);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()),
              HasSubstr("inflates past 100000 bytes"));
  // A large value other than the pixel data (DCMTK would load it into
  // memory): the phantom (pixel data of 512 KiB, no other value above
  // 2160 bytes) passes a 4 KiB value limit, an 8 KiB private value does not.
  DatasetScanLimits values;
  values.max_deflated_value_bytes = 4096;
  EXPECT_TRUE(ScanPart10File(path, values).ok());
  DcmFileFormat ff;
  ASSERT_TRUE(ff.loadFile(path.c_str()).good());
  ASSERT_TRUE(ff.getDataset()
                  ->putAndInsertString(DcmTag(0x0009, 0x0010, EVR_LO), "X")
                  .good());
  const std::string big(8192, 'x');
  ASSERT_TRUE(ff.getDataset()
                  ->putAndInsertUint8Array(
                      DcmTag(0x0009, 0x1001, EVR_OB),
                      reinterpret_cast<const Uint8*>(big.data()), big.size())
                  .good());
  const std::string with_value = (dir_ / "d-value.dcm").string();
  ASSERT_TRUE(
      ff.saveFile(with_value.c_str(), EXS_DeflatedLittleEndianExplicit).good());
  r = ScanPart10File(with_value, values);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()),
              HasSubstr("a value of 8192 bytes in a deflated data set"));
}

// Found by dicom_listener_fuzzer: a deflated stream with a data error after
// an element DCMTK would read with a 4 GiB length (it allocated that much).
// The scan must see what inflate produced before the error, and fail.
TEST_F(ScanTest, DeflatedStreamWithADataErrorFails) {
  std::ifstream in(
      std::string(::interslice::testing::SourceDir()) +
          "/tests/server/net/dimse/fuzz_cases/deflated-data-error.bin",
      std::ios::binary);
  const std::string input((std::istreambuf_iterator<char>(in)),
                          std::istreambuf_iterator<char>());
  ASSERT_GT(input.size(), 2u);
  ASSERT_EQ(input[0] % 2, 1);  // the fuzzer's data-set mode
  ASSERT_EQ(input[1] % 4, 3);  // deflated explicit VR little endian
  absl::StatusOr<DatasetScanResult> r =
      ScanDatasetBytes(input.substr(2), "1.2.840.10008.1.2.1.99");
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
}

// A deflated data set cut short (no end of stream) is not a data set that
// ends early.
TEST_F(ScanTest, DeflatedStreamCutShortFails) {
  const std::string path = Resaved(EXS_DeflatedLittleEndianExplicit, "d.dcm");
  absl::StatusOr<Part10Meta> meta = ReadPart10Meta(path);
  ASSERT_TRUE(meta.ok());
  std::ifstream in(path, std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)),
                    std::istreambuf_iterator<char>());
  bytes = bytes.substr(static_cast<size_t>(meta->dataset_offset));
  ASSERT_TRUE(ScanDatasetBytes(bytes, "1.2.840.10008.1.2.1.99").ok());
  absl::StatusOr<DatasetScanResult> cut = ScanDatasetBytes(
      bytes.substr(0, bytes.size() / 2), "1.2.840.10008.1.2.1.99");
  ASSERT_FALSE(cut.ok());
}

TEST_F(ScanTest, DeepNestingFailsAtTheLimitNotBefore) {
  using interslice::testing::NestedDataset;
  EXPECT_TRUE(ScanDatasetBytes(NestedDataset("1.2.3", 32), kExplicitLe).ok());
  absl::StatusOr<DatasetScanResult> deeper =
      ScanDatasetBytes(NestedDataset("1.2.3", 33), kExplicitLe);
  ASSERT_FALSE(deeper.ok());
  EXPECT_EQ(deeper.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(deeper.status().message()),
              HasSubstr("nesting deeper than 32"));
  // Issue 22's instance: 10,000 levels. The scan itself never recurses.
  absl::StatusOr<DatasetScanResult> hostile =
      ScanDatasetBytes(NestedDataset("1.2.3", 10000), kExplicitLe);
  ASSERT_FALSE(hostile.ok());
  EXPECT_THAT(std::string(hostile.status().message()),
              HasSubstr("nesting deeper"));
}

// Element header helpers for hand-made encodings.
std::string Le(uint32_t v, int bytes) {
  std::string out;
  for (int i = 0; i < bytes; ++i)
    out.push_back(static_cast<char>(v >> (8 * i)));
  return out;
}
std::string ImplicitHeader(uint16_t g, uint16_t e, uint32_t length) {
  return Le(g, 2) + Le(e, 2) + Le(length, 4);
}

TEST_F(ScanTest, NestingCannotHideInImplicitPrivateElements) {
  // A private (odd group) element of defined length is UN to the public
  // dictionary, but DCMTK may read it as a sequence with its private one:
  // a value that starts with an item is scanned as one.
  std::string inner = "";
  for (int i = 0; i < 40; ++i) {
    const std::string item =
        ImplicitHeader(0xFFFE, 0xE000, static_cast<uint32_t>(inner.size())) +
        inner;
    inner = ImplicitHeader(0x0009, 0x1010, static_cast<uint32_t>(item.size())) +
            item;
  }
  absl::StatusOr<DatasetScanResult> r = ScanDatasetBytes(inner, kImplicitLe);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()),
              HasSubstr("nesting deeper than 32"));
}

TEST_F(ScanTest, MalformedEncodingsFail) {
  struct Case {
    const char* what;
    std::string bytes;
    const char* message;
  };
  const std::vector<Case> cases = {
      // PatientName with an undefined length.
      {"undefined length", ImplicitHeader(0x0010, 0x0010, 0xFFFFFFFF),
       "undefined length"},
      // A value longer than the data.
      {"past the end", ImplicitHeader(0x0010, 0x0010, 100) + "ab",
       "past the end"},
      // An item outside a sequence.
      {"stray item", ImplicitHeader(0xFFFE, 0xE000, 0), "misplaced item"},
      // A defined-length sequence whose item overruns it.
      {"item overruns its sequence",
       ImplicitHeader(0x0040, 0xA730, 8) + ImplicitHeader(0xFFFE, 0xE000, 8) +
           ImplicitHeader(0x0010, 0x0010, 0),
       "enclosing"},
      // A sequence of undefined length that never ends.
      {"unterminated", ImplicitHeader(0x0040, 0xA730, 0xFFFFFFFF),
       "unterminated"},
      // Cut inside an element header.
      {"cut short", std::string("\x10\x00\x10", 3), "ends inside"},
  };
  for (const Case& c : cases) {
    absl::StatusOr<DatasetScanResult> r =
        ScanDatasetBytes(c.bytes, kImplicitLe);
    ASSERT_FALSE(r.ok()) << c.what;
    EXPECT_THAT(std::string(r.status().message()), HasSubstr(c.message))
        << c.what;
  }
  // An unknown VR in explicit VR.
  std::string bad_vr = Le(0x0010, 2) + Le(0x0010, 2) + "ZZ" + Le(0, 2);
  absl::StatusOr<DatasetScanResult> r = ScanDatasetBytes(bad_vr, kExplicitLe);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()), HasSubstr("unknown VR"));
}

TEST_F(ScanTest, ElementCountIsBounded) {
  std::string many;
  for (int i = 0; i < 1001; ++i) many += ImplicitHeader(0x0011, 0x0010, 0);
  DatasetScanLimits limits;
  limits.max_elements = 1000;
  absl::StatusOr<DatasetScanResult> r =
      ScanDatasetBytes(many, kImplicitLe, limits);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()),
              HasSubstr("more than 1000 elements"));
  limits.max_elements = 1001;
  EXPECT_TRUE(ScanDatasetBytes(many, kImplicitLe, limits).ok());
}

TEST_F(ScanTest, NotPart10FilesFail) {
  const std::string path = (dir_ / "text.dcm").string();
  std::ofstream(path) << std::string(200, 'x');
  absl::StatusOr<DatasetScanResult> r = ScanPart10File(path);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()), HasSubstr("no DICM prefix"));
  // A Part 10 file cut inside its pixel data.
  const std::string slice = DicomFilesUnder(kPhantom).front();
  const std::string cut = (dir_ / "cut.dcm").string();
  fs::copy_file(slice, cut);
  fs::resize_file(cut, fs::file_size(slice) - 1000);
  r = ScanPart10File(cut);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(std::string(r.status().message()), HasSubstr("past the end"));
}

}  // namespace
}  // namespace interslice::server::node
