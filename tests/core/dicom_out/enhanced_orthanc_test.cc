// A real consumer of the enhanced layout (issue 25): Debian's Orthanc takes
// the Enhanced MR Image (native and RLE) and the Enhanced CT Image into the
// source's study, sees their SOP class, modality and frame count, and
// decodes every frame to the stored values we wrote.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/dicom/pixel_decode.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/enhanced_series.h"
#include "gtest/gtest.h"
#include "tests/core/dicom_out/dicom_test_util.h"
#include "tests/testing/orthanc.h"
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
using testing::LoadDicom;
using testing::Orthanc;

constexpr char kTestRoot[] = "1.2.826.0.1.3680043.10.1234";

class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_enhanced_orthanc_") {}
};

// The source resampled to 1 mm slices over its whole extent (the full
// in-plane grid).
struct Case {
  DicomSeries source;
  Volume<float> intensity;
};

Case LoadCase(const fs::path& path) {
  QuietDicomToolkitLogging();
  Case c;
  auto series = ReadDicomSeries({path.string()}, {}, {});
  EXPECT_TRUE(series.ok()) << series.status();
  if (!series.ok()) return c;
  c.source = *std::move(series);
  Grid grid = c.source.image.grid;
  const double extent = c.source.slices.back().position_along_normal -
                        c.source.slices.front().position_along_normal;
  grid.spacing[2] = 1.0;
  grid.size[2] = static_cast<int64_t>(std::floor(extent)) + 1;
  std::vector<double> positions;
  for (const DicomSliceInfo& s : c.source.slices) {
    positions.push_back(s.position_along_normal);
  }
  auto intensity =
      ResampleSourceSlices(c.source.image, positions, grid, std::nullopt, {});
  EXPECT_TRUE(intensity.ok()) << intensity.status();
  if (intensity.ok()) c.intensity = *std::move(intensity);
  return c;
}

// Writes the enhanced instance of `c` with `options` into `dir`.
std::string WriteEnhanced(const Case& c, const DicomWriteOptions& options,
                          const fs::path& dir, const std::string& name) {
  auto objects =
      PlanDerivedObjects(c.source, c.intensity.grid.size[2], options);
  EXPECT_TRUE(objects.ok()) << objects.status();
  if (!objects.ok()) return "";
  auto identity = PlanEnhancedIntensity(c.source, objects->intensity, options);
  EXPECT_TRUE(identity.ok()) << identity.status();
  if (!identity.ok()) return "";
  const std::string path = (dir / name).string();
  const absl::Status written =
      WriteEnhancedIntensity(c.source, c.intensity, *identity, options, path);
  EXPECT_TRUE(written.ok()) << written;
  return path;
}

// The stored values of frame k of `file` (16 bits), read with DCMTK.
std::vector<uint16_t> StoredFrame(DcmFileFormat& file, size_t k) {
  DcmDataset& ds = *file.getDataset();
  EXPECT_TRUE(
      ds.chooseRepresentation(EXS_LittleEndianExplicit, nullptr).good());
  const Uint16* pixels = nullptr;
  unsigned long count = 0;
  EXPECT_TRUE(ds.findAndGetUint16Array(DCM_PixelData, pixels, &count).good());
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  const size_t plane = static_cast<size_t>(rows) * columns;
  if (pixels == nullptr || count < (k + 1) * plane) return {};
  return std::vector<uint16_t>(pixels + k * plane, pixels + (k + 1) * plane);
}

// Orthanc's decoding of frame k of instance `id` without rescaling, as
// NumPy's .npy (a 16-bit little-endian array): its values as 16 bits.
std::vector<uint16_t> OrthancFrame(const Orthanc& orthanc,
                                   const std::string& id, size_t k) {
  auto npy = orthanc.Get(
      absl::StrCat("/instances/", id, "/frames/", k, "/numpy?rescale=0"));
  EXPECT_TRUE(npy.ok()) << npy.status();
  if (!npy.ok() || npy->size() < 10 || npy->compare(1, 5, "NUMPY") != 0) {
    ADD_FAILURE() << "not a .npy answer";
    return {};
  }
  const size_t header =
      static_cast<uint8_t>((*npy)[8]) | (static_cast<uint8_t>((*npy)[9]) << 8);
  const std::string dict = npy->substr(10, header);
  EXPECT_TRUE(dict.find("'<u2'") != std::string::npos ||
              dict.find("'<i2'") != std::string::npos)
      << dict;
  const std::string data = npy->substr(10 + header);
  std::vector<uint16_t> values(data.size() / 2);
  std::memcpy(values.data(), data.data(), values.size() * 2);
  return values;
}

TEST(EnhancedOrthancTest, OrthancStoresAndDecodesEveryEnhancedFrame) {
  TempDir dir;
  const fs::path data = ::interslice::testing::TestDataDir();
  const Case mr = LoadCase(data / "multiframe" / "siemens-xa10-6_1.dcm");
  const Case ct = LoadCase(data / "ct-thick");
  ASSERT_EQ(mr.source.modality, "MR");
  ASSERT_EQ(ct.source.modality, "CT");
  DicomWriteOptions options;
  options.uid_root = kTestRoot;
  options.derivation_key = "orthanc native";
  DicomWriteOptions rle = options;
  rle.derivation_key = "orthanc rle";
  rle.intensity_encoding = DicomWriteOptions::PixelEncoding::kRleLossless;
  struct Object {
    std::string path;
    const char* sop_class;
    const char* modality;
  };
  const std::vector<Object> objects = {
      {WriteEnhanced(mr, options, dir.path(), "mr.dcm"),
       UID_EnhancedMRImageStorage, "MR"},
      {WriteEnhanced(mr, rle, dir.path(), "mr-rle.dcm"),
       UID_EnhancedMRImageStorage, "MR"},
      {WriteEnhanced(ct, options, dir.path(), "ct.dcm"),
       UID_EnhancedCTImageStorage, "CT"},
  };

  auto orthanc = Orthanc::Start((dir.path() / "orthanc").string(), {});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  auto source = (*orthanc)->Upload(
      (data / "multiframe" / "siemens-xa10-6_1.dcm").string());
  ASSERT_TRUE(source.ok()) << source.status();
  RegisterDicomDecoders();
  for (const Object& object : objects) {
    SCOPED_TRACE(object.path);
    ASSERT_FALSE(object.path.empty());
    auto id = (*orthanc)->Upload(object.path);
    ASSERT_TRUE(id.ok()) << id.status();
    auto tags = (*orthanc)->GetJson(
        absl::StrCat("/instances/", *id, "/simplified-tags"));
    ASSERT_TRUE(tags.ok()) << tags.status();
    EXPECT_EQ((*tags)["SOPClassUID"], object.sop_class);
    EXPECT_EQ((*tags)["Modality"], object.modality);
    auto file = LoadDicom(object.path);
    const std::string frames =
        GetString(*file->getDataset(), DCM_NumberOfFrames);
    EXPECT_EQ((*tags)["NumberOfFrames"], frames);
    auto listed =
        (*orthanc)->GetJson(absl::StrCat("/instances/", *id, "/frames"));
    ASSERT_TRUE(listed.ok()) << listed.status();
    ASSERT_EQ(std::to_string(listed->size()), frames);
    for (size_t k = 0; k < listed->size(); ++k) {
      SCOPED_TRACE(k);
      const std::vector<uint16_t> ours = StoredFrame(*file, k);
      ASSERT_FALSE(ours.empty());
      EXPECT_EQ(OrthancFrame(**orthanc, *id, k), ours);
    }
  }
  // The MR objects are filed in the source's study, as their own series.
  auto study =
      (*orthanc)->GetJson(absl::StrCat("/instances/", *source, "/study"));
  ASSERT_TRUE(study.ok()) << study.status();
  EXPECT_EQ((*study)["Series"].size(), 3u);  // source, native, RLE
}

}  // namespace
}  // namespace interslice
