#include "core/dicom_out/encapsulated_stl.h"

#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/surface/surface.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/core/dicom_out/dicom_test_util.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using testing::GetString;
using ::testing::HasSubstr;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
constexpr char kTestRoot[] = "1.2.826.0.1.3680043.10.1234";

std::string ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

class EncapsulatedStlTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    QuietDicomToolkitLogging();
    auto series = ReadDicomSeries({kThick.string()}, {}, {});
    ASSERT_TRUE(series.ok()) << series.status();
    source_ = new DicomSeries(*std::move(series));
  }
  static void TearDownTestSuite() {
    delete source_;
    source_ = nullptr;
  }
  void SetUp() override {
    // A tetrahedron with an odd number of triangles' worth of bytes
    // (84 + 4 x 50 = 284: even; a fifth triangle makes 334), written by the
    // project's own STL writer.
    Mesh mesh;
    mesh.vertices = {{0, 0, 0}, {10, 0, 0}, {0, 10, 0}, {0, 0, 10}};
    mesh.triangles = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
    stl_ = (dir_.path() / "surface.stl").string();
    ASSERT_TRUE(WriteStl(mesh, stl_).ok());
  }
  static DicomWriteOptions Options() {
    DicomWriteOptions options;
    options.uid_root = kTestRoot;
    options.derivation_key = "stl test job";
    return options;
  }
  static DerivedObjects Plan() {
    auto plan = PlanDerivedObjects(*source_, 10, Options());
    EXPECT_TRUE(plan.ok()) << plan.status();
    return plan.ok() ? *plan : DerivedObjects{};
  }

  static DicomSeries* source_;
  testing::TempDir dir_{"interslice_stl_"};
  std::string stl_;
};

DicomSeries* EncapsulatedStlTest::source_ = nullptr;

TEST_F(EncapsulatedStlTest, PassesDciodvfyAndRoundTripsTheBytes) {
  const DerivedObjects plan = Plan();
  const std::string out = (dir_.path() / kEncapsulatedStlFileName).string();
  ASSERT_TRUE(
      WriteEncapsulatedStl(*source_, stl_, plan.surface_stl, Options(), out)
          .ok());
  testing::ExpectValidIod({out});

  auto file = testing::LoadDicom(out);
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_SOPClassUID), UID_EncapsulatedSTLStorage);
  EXPECT_EQ(GetString(ds, DCM_SOPInstanceUID),
            plan.surface_stl.sop_instance_uids.front());
  EXPECT_EQ(GetString(ds, DCM_SeriesInstanceUID),
            plan.surface_stl.series_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID), source_->study_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_FrameOfReferenceUID),
            source_->frame_of_reference_uid);
  EXPECT_EQ(GetString(ds, DCM_MIMETypeOfEncapsulatedDocument), "model/stl");
  EXPECT_EQ(GetString(ds, DCM_Modality), "M3D");
  // Patient data come from the source, not invented.
  auto src = testing::LoadDicom(source_->slices.front().path);
  EXPECT_EQ(GetString(ds, DCM_PatientID),
            GetString(*src->getDataset(), DCM_PatientID));
  // Every source image is listed as what the mesh was derived from.
  DcmSequenceOfItems* sources = nullptr;
  ASSERT_TRUE(
      ds.findAndGetSequence(DCM_SourceInstanceSequence, sources).good());
  EXPECT_EQ(sources->card(), source_->slices.size());

  // The embedded bytes are the STL file, byte for byte.
  const std::string original = ReadBytes(stl_);
  Uint32 length = 0;
  ASSERT_TRUE(
      ds.findAndGetUint32(DCM_EncapsulatedDocumentLength, length).good());
  ASSERT_EQ(length, original.size());
  const Uint8* bytes = nullptr;
  unsigned long count = 0;
  ASSERT_TRUE(
      ds.findAndGetUint8Array(DCM_EncapsulatedDocument, bytes, &count).good());
  ASSERT_GE(count, original.size());
  EXPECT_EQ(std::string(reinterpret_cast<const char*>(bytes), length),
            original);
}

TEST_F(EncapsulatedStlTest, UidsAreStableAcrossRuns) {
  const DerivedObjects a = Plan(), b = Plan();
  EXPECT_EQ(a.surface_stl.sop_instance_uids, b.surface_stl.sop_instance_uids);
  EXPECT_EQ(a.surface_stl.series_instance_uid,
            b.surface_stl.series_instance_uid);
  EXPECT_NE(a.surface_stl.series_instance_uid,
            a.segmentation.series_instance_uid);
  EXPECT_NE(a.surface_stl.sop_instance_uids, a.segmentation.sop_instance_uids);
  EXPECT_EQ(a.surface_stl.series_number, a.segmentation.series_number + 1);

  const std::string out1 = (dir_.path() / "a.dcm").string();
  const std::string out2 = (dir_.path() / "b.dcm").string();
  ASSERT_TRUE(
      WriteEncapsulatedStl(*source_, stl_, a.surface_stl, Options(), out1)
          .ok());
  ASSERT_TRUE(
      WriteEncapsulatedStl(*source_, stl_, b.surface_stl, Options(), out2)
          .ok());
  EXPECT_EQ(
      GetString(*testing::LoadDicom(out1)->getDataset(), DCM_SOPInstanceUID),
      GetString(*testing::LoadDicom(out2)->getDataset(), DCM_SOPInstanceUID));
}

TEST_F(EncapsulatedStlTest, AsciiOrTruncatedStlIsInvalidArgument) {
  const DerivedObjects plan = Plan();
  const std::string out = (dir_.path() / "out.dcm").string();
  const fs::path ascii = dir_.path() / "ascii.stl";
  std::ofstream(ascii) << "solid x\nfacet normal 0 0 1\nendsolid x\n";
  absl::Status status = WriteEncapsulatedStl(*source_, ascii.string(),
                                             plan.surface_stl, Options(), out);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("ascii.stl"));

  std::string bytes = ReadBytes(stl_);
  bytes.resize(bytes.size() - 7);
  const fs::path truncated = dir_.path() / "truncated.stl";
  std::ofstream(truncated, std::ios::binary) << bytes;
  status = WriteEncapsulatedStl(*source_, truncated.string(), plan.surface_stl,
                                Options(), out);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);

  status = WriteEncapsulatedStl(*source_, (dir_.path() / "none.stl").string(),
                                plan.surface_stl, Options(), out);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(out));
}

}  // namespace
}  // namespace interslice
