#include "core/dicom_out/preview_series.h"

#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
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

class PreviewSeriesTest : public ::testing::Test {
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
    // Two pictures of different sizes with known pixels.
    for (int n = 0; n < 2; ++n) {
      const int w = n == 0 ? 37 : 64, h = n == 0 ? 21 : 48;
      std::vector<uint8_t>& rgb = pixels_[n];
      rgb.resize(static_cast<size_t>(w) * h * 3);
      for (size_t i = 0; i < rgb.size(); ++i) {
        rgb[i] = static_cast<uint8_t>((i * 7 + n * 3) % 251);
      }
      RgbPicture p;
      p.name = n == 0 ? "axial" : "3d-front";
      p.width = w;
      p.height = h;
      p.rgb = &rgb;
      p.description = n == 0 ? "axial plane, slice k = 2 of 10"
                             : "3D view of the surface from the front";
      p.patient_orientation = n == 0 ? "L\\P" : "L\\F";
      if (n == 0) p.output_slice = 2;
      pictures_.push_back(p);
    }
  }
  static DicomWriteOptions Options() {
    DicomWriteOptions options;
    options.uid_root = kTestRoot;
    options.derivation_key = "preview test job";
    return options;
  }
  static std::vector<std::string> Names() { return {"axial", "3d-front"}; }
  // A 10-slice output grid on the source's geometry.
  static Grid OutputGrid() {
    Grid g = source_->image.grid;
    g.size[2] = 10;
    return g;
  }

  static DicomSeries* source_;
  testing::TempDir dir_{"interslice_previews_"};
  std::vector<uint8_t> pixels_[2];
  std::vector<RgbPicture> pictures_;
};

DicomSeries* PreviewSeriesTest::source_ = nullptr;

TEST_F(PreviewSeriesTest, RgbSecondaryCaptureImagesThatValidate) {
  absl::StatusOr<DerivedObjectIdentity> identity =
      PlanPreviewSeries(*source_, Names(), Options());
  ASSERT_TRUE(identity.ok()) << identity.status();
  const std::string folder = (dir_.path() / "previews-dicom").string();
  absl::StatusOr<std::vector<std::string>> paths = WritePreviewSeries(
      *source_, OutputGrid(), pictures_, *identity, nullptr, Options(), folder);
  ASSERT_TRUE(paths.ok()) << paths.status();
  ASSERT_EQ(paths->size(), 2u);
  EXPECT_EQ(fs::path((*paths)[0]).filename(), "IM00001.dcm");
  testing::ExpectValidIod(*paths);

  auto first_source = testing::LoadDicom(source_->slices[0].path);
  DcmDataset& src = *first_source->getDataset();
  for (size_t n = 0; n < paths->size(); ++n) {
    auto file = testing::LoadDicom((*paths)[n]);
    DcmDataset& ds = *file->getDataset();
    EXPECT_EQ(GetString(ds, DCM_SOPClassUID), UID_SecondaryCaptureImageStorage);
    EXPECT_EQ(GetString(ds, DCM_SOPInstanceUID),
              identity->sop_instance_uids[n]);
    EXPECT_EQ(GetString(ds, DCM_SeriesInstanceUID),
              identity->series_instance_uid);
    EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID), source_->study_instance_uid);
    EXPECT_EQ(GetString(ds, DCM_PatientID), GetString(src, DCM_PatientID));
    EXPECT_EQ(GetString(ds, DCM_BodyPartExamined),
              GetString(src, DCM_BodyPartExamined));
    EXPECT_FALSE(ds.tagExists(DCM_FrameOfReferenceUID));
    EXPECT_FALSE(ds.tagExists(DCM_ImagePositionPatient));
    EXPECT_EQ(GetString(ds, DCM_Modality), "OT");
    EXPECT_EQ(GetString(ds, DCM_PhotometricInterpretation), "RGB");
    EXPECT_EQ(GetString(ds, DCM_BurnedInAnnotation), "YES");
    EXPECT_EQ(GetString(ds, DCM_ImageType), "DERIVED\\SECONDARY");
    EXPECT_EQ(GetString(ds, DCM_InstanceNumber), std::to_string(n + 1));
    EXPECT_EQ(GetString(ds, DCM_PatientOrientation),
              pictures_[n].patient_orientation);
    EXPECT_EQ(GetString(ds, DCM_ImageComments), pictures_[n].description);
    Uint16 value = 99;
    ASSERT_TRUE(ds.findAndGetUint16(DCM_PlanarConfiguration, value).good());
    EXPECT_EQ(value, 0);
    ASSERT_TRUE(ds.findAndGetUint16(DCM_SamplesPerPixel, value).good());
    EXPECT_EQ(value, 3);
    ASSERT_TRUE(ds.findAndGetUint16(DCM_Rows, value).good());
    EXPECT_EQ(value, pictures_[n].height);
    ASSERT_TRUE(ds.findAndGetUint16(DCM_Columns, value).good());
    EXPECT_EQ(value, pictures_[n].width);
    const Uint8* data = nullptr;
    unsigned long count = 0;
    ASSERT_TRUE(ds.findAndGetUint8Array(DCM_PixelData, data, &count).good());
    // Padded to an even length.
    ASSERT_EQ(count, (pixels_[n].size() + 1) / 2 * 2);
    EXPECT_TRUE(std::equal(pixels_[n].begin(), pixels_[n].end(), data));
  }
  // The axial picture shows output slice 2: the source slices nearest to it;
  // the 3D view all of them.
  auto axial = testing::LoadDicom((*paths)[0]);
  auto front = testing::LoadDicom((*paths)[1]);
  DcmSequenceOfItems* sequence = nullptr;
  ASSERT_TRUE(axial->getDataset()
                  ->findAndGetSequence(DCM_SourceImageSequence, sequence)
                  .good());
  EXPECT_GE(sequence->card(), 1u);
  EXPECT_LE(sequence->card(), 2u);
  ASSERT_TRUE(front->getDataset()
                  ->findAndGetSequence(DCM_SourceImageSequence, sequence)
                  .good());
  EXPECT_EQ(sequence->card(), source_->slices.size());
  ASSERT_TRUE(front->getDataset()
                  ->findAndGetSequence(DCM_ReferencedSeriesSequence, sequence)
                  .good());
  EXPECT_EQ(GetString(*sequence->getItem(0), DCM_SeriesInstanceUID),
            source_->series_instance_uid);
}

TEST_F(PreviewSeriesTest, DerivedFromTheIntensitySeriesWhenThereIsOne) {
  absl::StatusOr<DerivedObjects> objects =
      PlanDerivedObjects(*source_, 10, Options());
  ASSERT_TRUE(objects.ok()) << objects.status();
  absl::StatusOr<DerivedObjectIdentity> identity =
      PlanPreviewSeries(*source_, Names(), Options(), &objects->intensity);
  ASSERT_TRUE(identity.ok()) << identity.status();
  const std::string folder = (dir_.path() / "previews-dicom").string();
  absl::StatusOr<std::vector<std::string>> paths =
      WritePreviewSeries(*source_, OutputGrid(), pictures_, *identity,
                         &objects->intensity, Options(), folder);
  ASSERT_TRUE(paths.ok()) << paths.status();
  testing::ExpectValidIod(*paths);
  auto axial = testing::LoadDicom((*paths)[0]);
  DcmSequenceOfItems* sequence = nullptr;
  ASSERT_TRUE(axial->getDataset()
                  ->findAndGetSequence(DCM_SourceImageSequence, sequence)
                  .good());
  ASSERT_EQ(sequence->card(), 1u);
  EXPECT_EQ(GetString(*sequence->getItem(0), DCM_ReferencedSOPInstanceUID),
            objects->intensity.sop_instance_uids[2]);
  ASSERT_TRUE(axial->getDataset()
                  ->findAndGetSequence(DCM_ReferencedSeriesSequence, sequence)
                  .good());
  EXPECT_EQ(GetString(*sequence->getItem(0), DCM_SeriesInstanceUID),
            objects->intensity.series_instance_uid);
  auto front = testing::LoadDicom((*paths)[1]);
  ASSERT_TRUE(front->getDataset()
                  ->findAndGetSequence(DCM_SourceImageSequence, sequence)
                  .good());
  EXPECT_EQ(sequence->card(), 10u);
}

TEST_F(PreviewSeriesTest, IdentityFollowsTheJobsScheme) {
  absl::StatusOr<DerivedObjects> objects =
      PlanDerivedObjects(*source_, 10, Options());
  absl::StatusOr<DerivedObjectIdentity> a =
      PlanPreviewSeries(*source_, Names(), Options());
  absl::StatusOr<DerivedObjectIdentity> b =
      PlanPreviewSeries(*source_, Names(), Options());
  ASSERT_TRUE(objects.ok() && a.ok() && b.ok());
  // Series number: base + 6 (the source's SeriesNumber x 1000).
  EXPECT_EQ(a->series_number, objects->intensity.series_number + 5);
  EXPECT_THAT(a->series_description, ::testing::StartsWith("Previews, from #"));
  // Derived: the same job names them the same, under the root, and never as
  // another object of the job.
  EXPECT_EQ(a->series_instance_uid, b->series_instance_uid);
  EXPECT_EQ(a->sop_instance_uids, b->sop_instance_uids);
  EXPECT_THAT(a->series_instance_uid, ::testing::StartsWith(kTestRoot));
  EXPECT_NE(a->series_instance_uid, objects->intensity.series_instance_uid);
  EXPECT_NE(a->sop_instance_uids[0], a->sop_instance_uids[1]);
  // Another job, other UIDs; random_uids: new ones every time.
  DicomWriteOptions other = Options();
  other.derivation_key = "another job";
  auto c = PlanPreviewSeries(*source_, Names(), other);
  ASSERT_TRUE(c.ok());
  EXPECT_NE(a->series_instance_uid, c->series_instance_uid);
  DicomWriteOptions random = Options();
  random.random_uids = true;
  auto d = PlanPreviewSeries(*source_, Names(), random);
  auto e = PlanPreviewSeries(*source_, Names(), random);
  ASSERT_TRUE(d.ok() && e.ok());
  EXPECT_NE(d->series_instance_uid, e->series_instance_uid);
  // A base that leaves no room for base + 6.
  DicomWriteOptions high = Options();
  high.series_number_base = 2147483647 - 5;
  EXPECT_EQ(PlanPreviewSeries(*source_, Names(), high).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(PlanDerivedObjects(*source_, 10, high).status().code(),
            absl::StatusCode::kInvalidArgument);
  high.series_number_base = 2147483647 - 6;
  EXPECT_TRUE(PlanPreviewSeries(*source_, Names(), high).ok());
  EXPECT_EQ(PlanPreviewSeries(*source_, {"a", "a"}, Options()).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(PreviewSeriesTest, BadPicturesAreRefusedAndLeaveNoFolder) {
  absl::StatusOr<DerivedObjectIdentity> identity =
      PlanPreviewSeries(*source_, Names(), Options());
  ASSERT_TRUE(identity.ok());
  std::vector<RgbPicture> bad = pictures_;
  bad[1].width += 1;  // the pixels no longer fill it
  const std::string folder = (dir_.path() / "previews-dicom").string();
  absl::StatusOr<std::vector<std::string>> paths = WritePreviewSeries(
      *source_, OutputGrid(), bad, *identity, nullptr, Options(), folder);
  EXPECT_EQ(paths.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(paths.status().message(), HasSubstr("3d-front"));
  EXPECT_FALSE(fs::exists(folder));
  // One identity for two pictures.
  DerivedObjectIdentity one = *identity;
  one.sop_instance_uids.pop_back();
  paths = WritePreviewSeries(*source_, OutputGrid(), pictures_, one, nullptr,
                             Options(), folder);
  EXPECT_EQ(paths.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(PreviewSeriesTest, ResampledPlaneEqualsTheFullResamplesCrop) {
  std::vector<double> positions;
  for (const DicomSliceInfo& s : source_->slices) {
    positions.push_back(s.position_along_normal);
  }
  Grid target = source_->image.grid;
  target.spacing[2] /= 3;
  target.size[2] = (source_->image.grid.size[2] - 1) * 3 + 1;
  absl::StatusOr<Volume<float>> full =
      ResampleSourceSlices(source_->image, positions, target, std::nullopt, {});
  ASSERT_TRUE(full.ok()) << full.status();
  for (const VoxelBox box :
       {VoxelBox{{0, 0, 7}, {target.size[0], target.size[1], 8}},
        VoxelBox{{13, 0, 0}, {14, target.size[1], target.size[2]}},
        VoxelBox{{0, 40, 0}, {target.size[0], 41, target.size[2]}}}) {
    absl::StatusOr<Volume<float>> part = ResampleSourceSlicesInBox(
        source_->image, positions, target, box, std::nullopt, {});
    ASSERT_TRUE(part.ok()) << part.status();
    const Volume<float> expected = CropVolume(*full, box);
    EXPECT_EQ(part->grid.size, expected.grid.size);
    EXPECT_EQ(part->data, expected.data);
  }
  EXPECT_EQ(ResampleSourceSlicesInBox(source_->image, positions, target,
                                      {{0, 0, 0}, {1, 1, target.size[2] + 1}},
                                      std::nullopt, {})
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(PreviewSeriesTest, SourceWindowIsTheFirstPair) {
  absl::StatusOr<std::optional<SourceWindow>> window =
      SourceDisplayWindow(*source_);
  ASSERT_TRUE(window.ok()) << window.status();
  auto first = testing::LoadDicom(source_->slices[0].path);
  Float64 center = 0, width = 0;
  ASSERT_TRUE(
      first->getDataset()->findAndGetFloat64(DCM_WindowCenter, center).good());
  ASSERT_TRUE(
      first->getDataset()->findAndGetFloat64(DCM_WindowWidth, width).good());
  ASSERT_TRUE(window->has_value());
  EXPECT_EQ((*window)->center, center);
  EXPECT_EQ((*window)->width, width);
}

}  // namespace
}  // namespace interslice
