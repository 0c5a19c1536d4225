#include "core/dicom_out/dicom_writer.h"

#include <unistd.h>

#include <algorithm>
#include <array>
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
#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/label_segmentation.h"
#include "core/dicom_out/preview_series.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/core/dicom_out/dicom_test_util.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcvrus.h"
#include "dcmtk/dcmfg/fgderimg.h"
#include "dcmtk/dcmfg/fginterface.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmiod/cielabutil.h"
#include "dcmtk/dcmseg/segdoc.h"
#include "dcmtk/dcmseg/segment.h"
#include "dcmtk/dcmseg/segutils.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::StartsWith;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
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
    options.series_number_base = 900;
    options.derivation_key = "test job";
    return options;
  }
  static DerivedObjects Plan(const DicomWriteOptions& options = Options()) {
    auto objects = PlanDerivedObjects(*source_, grid_->size[2], options);
    EXPECT_TRUE(objects.ok()) << objects.status();
    return objects.ok() ? *objects : DerivedObjects{};
  }
  // The source CT on the output grid (cropped in-plane like grid_).
  static Volume<float> Intensity() {
    Volume<float> cropped =
        CropVolume(source_->image, VoxelBox{{224, 200, 0}, {288, 264, 4}});
    std::vector<double> positions;
    for (const DicomSliceInfo& s : source_->slices) {
      positions.push_back(s.position_along_normal);
    }
    auto intensity =
        ResampleSourceSlices(cropped, positions, *grid_, std::nullopt, {});
    EXPECT_TRUE(intensity.ok()) << intensity.status();
    return intensity.ok() ? *intensity : Volume<float>{};
  }

  static DicomSeries* source_;
  static Grid* grid_;
};

DicomSeries* DicomWriterTest::source_ = nullptr;
Grid* DicomWriterTest::grid_ = nullptr;

using testing::DciodvfyErrors;
using testing::ExpectValidIod;
using testing::GetString;
std::unique_ptr<DcmFileFormat> Load(const std::string& path) {
  return testing::LoadDicom(path);
}

void ExpectSameGrid(const Grid& a, const Grid& b) {
  for (int c = 0; c < 3; ++c) {
    EXPECT_EQ(a.size[c], b.size[c]) << c;
    EXPECT_NEAR(a.spacing[c], b.spacing[c], 1e-4) << c;
    EXPECT_NEAR(a.origin[c], b.origin[c], 1e-4) << c;
  }
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(a.direction[i], b.direction[i], 1e-4);
}

TEST_F(DicomWriterTest, IntensitySeriesAndSegPassDciodvfy) {
  TempDir dir;
  const DerivedObjects objects = Plan();
  const std::string out = (dir.path() / "intensity").string();
  auto paths = WriteIntensitySeries(*source_, Intensity(), objects.intensity,
                                    Options(), out);
  ASSERT_TRUE(paths.ok()) << paths.status();
  ASSERT_EQ(paths->size(), static_cast<size_t>(grid_->size[2]));
  {
    SCOPED_TRACE("intensity");
    ExpectValidIod(*paths);
  }
  const std::string seg = (dir.path() / "seg.dcm").string();
  const absl::Status written = WriteSegmentation(
      *source_, Mask(Distance()), objects.segmentation, objects.intensity,
      SegmentDescription(), Options(), seg);
  ASSERT_TRUE(written.ok()) << written;
  SCOPED_TRACE("seg");
  ExpectValidIod({seg});
}

TEST_F(DicomWriterTest, IntensitySeriesRoundTripsThroughOurReader) {
  TempDir dir;
  const Volume<float> intensity = Intensity();
  const std::string out = (dir.path() / "intensity").string();
  const DerivedObjects objects = Plan();
  auto paths = WriteIntensitySeries(*source_, intensity, objects.intensity,
                                    Options(), out);
  ASSERT_TRUE(paths.ok()) << paths.status();
  auto back = ReadDicomSeries({out}, {}, {});
  ASSERT_TRUE(back.ok()) << back.status();
  ExpectSameGrid(back->image.grid, *grid_);
  ASSERT_EQ(back->image.data.size(), intensity.data.size());
  double worst = 0;
  for (size_t i = 0; i < intensity.data.size(); ++i) {
    worst = std::max(worst, std::abs(double(back->image.data[i]) -
                                     double(intensity.data[i])));
  }
  // Half of the source's rescale slope (1 HU), plus float rounding.
  EXPECT_LE(worst, 0.5 + 1e-3);
  EXPECT_EQ(back->study_instance_uid, source_->study_instance_uid);
  EXPECT_EQ(back->frame_of_reference_uid, source_->frame_of_reference_uid);
  EXPECT_EQ(back->series_instance_uid, objects.intensity.series_instance_uid);
  EXPECT_EQ(back->modality, "CT");
  for (size_t k = 0; k < back->slices.size(); ++k) {
    EXPECT_EQ(back->slices[k].sop_instance_uid,
              objects.intensity.sop_instance_uids[k]);
  }
}

// The RLE Lossless option: each instance is encapsulated RLE, passes
// dciodvfy, is smaller, and decodes to exactly the native instance's stored
// values (and the rest of the dataset is the same).
TEST_F(DicomWriterTest, RleIntensitySeriesDecodesToTheNativePixels) {
  TempDir dir;
  const Volume<float> intensity = Intensity();
  const DerivedObjects objects = Plan();
  auto native = WriteIntensitySeries(*source_, intensity, objects.intensity,
                                     Options(), (dir.path() / "n").string());
  ASSERT_TRUE(native.ok()) << native.status();
  DicomWriteOptions rle_options = Options();
  rle_options.intensity_encoding =
      DicomWriteOptions::PixelEncoding::kRleLossless;
  auto rle = WriteIntensitySeries(*source_, intensity, objects.intensity,
                                  rle_options, (dir.path() / "r").string());
  ASSERT_TRUE(rle.ok()) << rle.status();
  ASSERT_EQ(rle->size(), native->size());
  {
    SCOPED_TRACE("rle intensity");
    ExpectValidIod(*rle);
  }
  RegisterDicomDecoders();  // DCMTK's RLE decoder, to compare the pixels
  uintmax_t native_bytes = 0, rle_bytes = 0;
  for (size_t k = 0; k < rle->size(); ++k) {
    SCOPED_TRACE(k);
    native_bytes += fs::file_size((*native)[k]);
    rle_bytes += fs::file_size((*rle)[k]);
    auto a = Load((*native)[k]);
    auto b = Load((*rle)[k]);
    EXPECT_EQ(GetString(*b->getMetaInfo(), DCM_TransferSyntaxUID),
              UID_RLELosslessTransferSyntax);
    EXPECT_EQ(b->getDataset()->getOriginalXfer(), EXS_RLELossless);
    EXPECT_EQ(GetString(*a->getMetaInfo(), DCM_TransferSyntaxUID),
              UID_LittleEndianExplicitTransferSyntax);
    EXPECT_EQ(GetString(*b->getDataset(), DCM_SOPInstanceUID),
              GetString(*a->getDataset(), DCM_SOPInstanceUID));
    ASSERT_TRUE(b->getDataset()
                    ->chooseRepresentation(EXS_LittleEndianExplicit, nullptr)
                    .good());
    const Uint16* pa = nullptr;
    const Uint16* pb = nullptr;
    unsigned long na = 0, nb = 0;
    ASSERT_TRUE(
        a->getDataset()->findAndGetUint16Array(DCM_PixelData, pa, &na).good());
    ASSERT_TRUE(
        b->getDataset()->findAndGetUint16Array(DCM_PixelData, pb, &nb).good());
    ASSERT_EQ(na, nb);
    ASSERT_EQ(na, static_cast<unsigned long>(grid_->size[0] * grid_->size[1]));
    EXPECT_TRUE(std::equal(pa, pa + na, pb));
    for (const DcmTagKey& tag :
         {DCM_Rows, DCM_Columns, DCM_BitsAllocated, DCM_BitsStored,
          DCM_PixelRepresentation, DCM_RescaleSlope, DCM_RescaleIntercept,
          DCM_ImagePositionPatient, DCM_InstanceNumber}) {
      EXPECT_EQ(GetString(*b->getDataset(), tag),
                GetString(*a->getDataset(), tag))
          << DcmTag(tag).getTagName();
    }
  }
  EXPECT_LT(rle_bytes, native_bytes);
}

TEST_F(DicomWriterTest, IntensitySeriesKeepsWindowsAndPixelPadding) {
  TempDir dir;
  // A source whose first slice has two windows with explanations and a
  // PixelPaddingValue, as scanners write them.
  const fs::path copy = dir.path() / "source";
  fs::create_directories(copy);
  DicomSeries source = *source_;
  for (size_t s = 0; s < source.slices.size(); ++s) {
    const fs::path to = copy / fs::path(source.slices[s].path).filename();
    fs::copy_file(source.slices[s].path, to);
    source.slices[s].path = to.string();
  }
  {
    auto file = Load(source.slices[0].path);
    DcmDataset& ds = *file->getDataset();
    ds.putAndInsertString(DCM_WindowCenter, "40\\400");
    ds.putAndInsertString(DCM_WindowWidth, "80\\2000");
    ds.putAndInsertString(DCM_WindowCenterWidthExplanation, "BRAIN\\BONE");
    auto* padding = new DcmUnsignedShort(DcmTag(DCM_PixelPaddingValue, EVR_US));
    padding->putUint16(0);  // stored 0 = -1024 HU with intercept -1024
    ds.insert(padding, OFTrue);
    // Saving over the file it was loaded from: read the pixel data first.
    ASSERT_TRUE(file->loadAllDataIntoMemory().good());
    ASSERT_TRUE(file->saveFile(source.slices[0].path.c_str()).good());
  }
  auto padding_value = SourcePixelPadding(source);
  ASSERT_TRUE(padding_value.ok()) << padding_value.status();
  ASSERT_TRUE(padding_value->has_value());
  EXPECT_FLOAT_EQ(**padding_value,
                  static_cast<float>(source.slices[0].rescale_intercept));

  const DerivedObjects objects = Plan();
  const std::string out = (dir.path() / "intensity").string();
  auto paths = WriteIntensitySeries(source, Intensity(), objects.intensity,
                                    Options(), out);
  ASSERT_TRUE(paths.ok()) << paths.status();
  auto file = Load(paths->front());
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_WindowCenter), "40\\400");
  EXPECT_EQ(GetString(ds, DCM_WindowWidth), "80\\2000");
  EXPECT_EQ(GetString(ds, DCM_WindowCenterWidthExplanation), "BRAIN\\BONE");
  Uint16 stored_padding = 1;
  ASSERT_TRUE(
      ds.findAndGetUint16(DCM_PixelPaddingValue, stored_padding).good());
  EXPECT_EQ(stored_padding, 0);
  ExpectValidIod({paths->front()});
}

TEST_F(DicomWriterTest, SegFramesReferenceTheIntensitySeriesImageByImage) {
  TempDir dir;
  const Volume<uint8_t> mask = Mask(Distance());
  const std::string path = (dir.path() / "seg.dcm").string();
  SegmentDescription segment;
  segment.label = "Sphere";
  const DerivedObjects objects = Plan();
  ASSERT_TRUE(WriteSegmentation(*source_, mask, objects.segmentation,
                                objects.intensity, segment, Options(), path)
                  .ok());

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

    // Frame f derives from image f of the intensity series, and only it.
    FGDerivationImage* derivation = OFstatic_cast(
        FGDerivationImage*,
        seg->getFunctionalGroups().get(static_cast<Uint32>(f),
                                       DcmFGTypes::EFG_DERIVATIONIMAGE));
    ASSERT_NE(derivation, nullptr);
    ASSERT_EQ(derivation->getDerivationImageItems().size(), 1u);
    OFVector<SourceImageItem*>& sources =
        derivation->getDerivationImageItems()[0]->getSourceImageItems();
    ASSERT_EQ(sources.size(), 1u);
    OFString referenced;
    sources[0]->getImageSOPInstanceReference().getReferencedSOPInstanceUID(
        referenced);
    EXPECT_EQ(std::string(referenced.c_str()),
              objects.intensity.sop_instance_uids[f]);

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

  // Patient/study copied; the referenced series is the intensity series.
  auto file = Load(path);
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID), source_->study_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_FrameOfReferenceUID),
            source_->frame_of_reference_uid);
  EXPECT_EQ(GetString(ds, DCM_SeriesInstanceUID),
            objects.segmentation.series_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_SOPInstanceUID),
            objects.segmentation.sop_instance_uids[0]);
  EXPECT_EQ(GetString(ds, DCM_SeriesNumber), "903");
  DcmItem* series = nullptr;
  ASSERT_TRUE(ds.findAndGetSequenceItem(DCM_ReferencedSeriesSequence, series, 0)
                  .good());
  EXPECT_EQ(GetString(*series, DCM_SeriesInstanceUID),
            objects.intensity.series_instance_uid);
  DcmSequenceOfItems* instances = nullptr;
  ASSERT_TRUE(
      series->findAndGetSequence(DCM_ReferencedInstanceSequence, instances)
          .good());
  EXPECT_EQ(instances->card(), static_cast<unsigned long>(grid_->size[2]));
  DcmItem* dimension = nullptr;
  ASSERT_TRUE(
      ds.findAndGetSequenceItem(DCM_DimensionOrganizationSequence, dimension, 0)
          .good());
  EXPECT_EQ(GetString(*dimension, DCM_DimensionOrganizationUID),
            objects.segmentation.dimension_organization_uid);
}

TEST_F(DicomWriterTest, IntensityUidsPositionsAndInstanceNumbers) {
  TempDir dir;
  auto source_file = Load(source_->slices[0].path);
  DcmDataset& src = *source_file->getDataset();
  const DerivedObjects objects = Plan();
  const std::string out = (dir.path() / "intensity").string();
  auto paths = WriteIntensitySeries(*source_, Intensity(), objects.intensity,
                                    Options(), out);
  ASSERT_TRUE(paths.ok()) << paths.status();

  const Vec3 n = grid_->Axis(2);
  double previous_position = -1e30;
  for (size_t k = 0; k < paths->size(); ++k) {
    auto file = Load((*paths)[k]);
    DcmDataset& ds = *file->getDataset();
    const std::string sop = GetString(ds, DCM_SOPInstanceUID);
    EXPECT_EQ(sop, objects.intensity.sop_instance_uids[k]);
    EXPECT_THAT(sop, StartsWith(kTestRoot));
    EXPECT_EQ(GetString(*file->getMetaInfo(), DCM_MediaStorageSOPInstanceUID),
              sop);
    EXPECT_EQ(GetString(ds, DCM_SeriesInstanceUID),
              objects.intensity.series_instance_uid);
    EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID), source_->study_instance_uid);
    EXPECT_EQ(GetString(ds, DCM_FrameOfReferenceUID),
              source_->frame_of_reference_uid);
    // Patient and study modules copied, not invented.
    EXPECT_EQ(GetString(ds, DCM_PatientName), GetString(src, DCM_PatientName));
    EXPECT_EQ(GetString(ds, DCM_PatientID), GetString(src, DCM_PatientID));
    EXPECT_EQ(GetString(ds, DCM_StudyDescription),
              GetString(src, DCM_StudyDescription));
    EXPECT_EQ(GetString(ds, DCM_ImageType), "DERIVED\\SECONDARY\\AXIAL");
    EXPECT_EQ(GetString(ds, DCM_SeriesNumber), "901");
    // The object, then the source series as the study lists it.
    EXPECT_EQ(GetString(ds, DCM_SeriesDescription),
              "Interpolated, from #" + GetString(src, DCM_SeriesNumber) + " " +
                  GetString(src, DCM_SeriesDescription));
    EXPECT_EQ(GetString(ds, DCM_RescaleType), "HU");

    long number = 0;
    ASSERT_TRUE(ds.findAndGetLongInt(DCM_InstanceNumber, number).good());
    EXPECT_EQ(number, static_cast<long>(k + 1));
    Vec3 ipp;
    for (int c = 0; c < 3; ++c) {
      Float64 v = 0;
      ASSERT_TRUE(ds.findAndGetFloat64(DCM_ImagePositionPatient, v, c).good());
      ipp[c] = v;
    }
    const Vec3 expected =
        grid_->IndexToPhysical({0, 0, static_cast<double>(k)});
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(ipp[c], expected[c], 1e-4);
    Float64 between = 0, thickness = 0;
    ASSERT_TRUE(ds.findAndGetFloat64(DCM_SpacingBetweenSlices, between).good());
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
    ASSERT_TRUE(ds.findAndGetSequence(DCM_SourceImageSequence, sources).good());
    EXPECT_EQ(sources->card(), k % 5 == 0 ? 1u : 2u);
  }
}

// A morph series says so, and each slice between two source slices also
// names their outer neighbours (the morph's value tangents come from them).
TEST_F(DicomWriterTest, MorphIntensitySeriesNamesItsMethodAndFourSources) {
  TempDir dir;
  DicomWriteOptions options = Options();
  options.intensity_interpolation =
      DicomWriteOptions::IntensityInterpolation::kMorph;
  const DerivedObjects objects = Plan(options);
  auto paths = WriteIntensitySeries(*source_, Intensity(), objects.intensity,
                                    options, (dir.path() / "morph").string());
  ASSERT_TRUE(paths.ok()) << paths.status();
  ASSERT_EQ(paths->size(), 16u);  // 4 source slices, 5 output slices apart
  for (size_t k = 0; k < paths->size(); ++k) {
    auto file = Load((*paths)[k]);
    DcmDataset& ds = *file->getDataset();
    EXPECT_THAT(GetString(ds, DCM_DerivationDescription),
                HasSubstr("carried along the motion"));
    DcmSequenceOfItems* sources = nullptr;
    ASSERT_TRUE(ds.findAndGetSequence(DCM_SourceImageSequence, sources).good());
    // On a source slice: that one; between s and s+1: s, s+1 and those of
    // s-1 and s+2 that exist (4 slices: gaps 0 and 2 have 3, gap 1 has 4).
    const size_t gap = k / 5;
    const size_t expected = k % 5 == 0 ? 1 : (gap == 1 ? 4 : 3);
    EXPECT_EQ(sources->card(), expected) << "slice " << k;
  }
  // The linear series says it is linear.
  auto linear = WriteIntensitySeries(*source_, Intensity(), objects.intensity,
                                     Options(), (dir.path() / "lin").string());
  ASSERT_TRUE(linear.ok()) << linear.status();
  auto file = Load(linear->at(2));
  EXPECT_THAT(GetString(*file->getDataset(), DCM_DerivationDescription),
              HasSubstr("linearly interpolated"));
}

// ResampleSourceSlices places values by the true slice positions: a field
// that is linear along the normal is reproduced exactly however uneven the
// gaps (the old resampling used the median gap and squeezed the anatomy).
TEST(ResampleSourceSlicesTest, UnevenGapsArePlacedByTruePosition) {
  const std::vector<double> positions = {10.0, 14.2, 15.3, 22.7};
  Volume<float> image;
  image.grid.size = {3, 2, 4};
  image.grid.spacing = {0.5, 0.5, 4.0};  // z spacing: deliberately wrong
  image.grid.origin = {-20, 30, 10};
  image.data.resize(24);
  for (int64_t k = 0; k < 4; ++k) {
    for (int64_t i = 0; i < 6; ++i) {
      image.data[k * 6 + i] = static_cast<float>(3 * positions[k] + i);
    }
  }
  Grid target = image.grid;
  target.spacing[2] = 0.5;
  target.size[2] = 28;  // up to 23.5: beyond half a spacing of 22.7
  auto out = ResampleSourceSlices(image, positions, target, std::nullopt, {});
  ASSERT_TRUE(out.ok()) << out.status();
  for (int64_t k = 0; k < target.size[2]; ++k) {
    const double p = 10.0 + 0.5 * k;
    for (int64_t i = 0; i < 6; ++i) {
      SCOPED_TRACE(::testing::Message() << "k=" << k << " i=" << i);
      const float got = out->data[k * 6 + i];
      if (p <= 22.7) {
        EXPECT_NEAR(got, 3 * p + i, 1e-3);
      } else if (p - 22.7 <= 0.25 + 1e-9) {
        EXPECT_NEAR(got, 3 * 22.7 + i, 1e-3);  // the last slice, held
      } else {
        EXPECT_EQ(got, 30.0f);  // outside: the minimum (3 * 10 + 0)
      }
    }
  }
}

TEST(ResampleSourceSlicesTest, PaddingNeverBleedsIntoTheAnatomy) {
  const std::vector<double> positions = {0.0, 5.0};
  Volume<float> image;
  image.grid.size = {2, 1, 2};
  image.grid.spacing = {1, 1, 5};
  image.data = {-3024.0f, 100.0f,  // slice 0: padding, tissue
                50.0f, 200.0f};    // slice 1: tissue, tissue
  Grid target = image.grid;
  target.spacing[2] = 1;
  target.size[2] = 7;  // 0..6 mm: node 6 is beyond the last slice's reach
  auto out = ResampleSourceSlices(image, positions, target, -3024.0f, {});
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ(out->data[0], -3024.0f);  // on slice 0
  EXPECT_EQ(out->data[2], -3024.0f);  // blended with a padding pixel
  EXPECT_NEAR(out->data[3], 0.8f * 100 + 0.2f * 200, 1e-3);
  EXPECT_EQ(out->data[10], 50.0f);     // on slice 1
  EXPECT_EQ(out->data[12], -3024.0f);  // outside: padding, not the minimum
  EXPECT_EQ(out->data[13], -3024.0f);
}

TEST(ResampleSourceSlicesTest, MismatchedGridsAndPositionsAreInvalid) {
  Volume<float> image;
  image.grid.size = {2, 2, 2};
  image.data.assign(8, 0.0f);
  Grid target = image.grid;
  EXPECT_EQ(ResampleSourceSlices(image, {0, 1, 2}, target, std::nullopt, {})
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ResampleSourceSlices(image, {1, 0}, target, std::nullopt, {})
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  Grid shifted = target;
  shifted.origin[0] += 0.5;  // off the in-plane lattice
  EXPECT_EQ(ResampleSourceSlices(image, {0, 1}, shifted, std::nullopt, {})
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  Grid wider = target;
  wider.size[0] = 3;
  EXPECT_EQ(ResampleSourceSlices(image, {0, 1}, wider, std::nullopt, {})
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
}

// Without `drop_media_uid` DCMTK keeps the file meta header up to date
// with the data set; with it the meta header loses its
// MediaStorageSOPInstanceUID and is written as it is.
template <typename Edit>
DicomSeries DoctoredCopy(const DicomSeries& original, const fs::path& dir,
                         Edit edit, bool drop_media_uid = false) {
  fs::create_directories(dir);
  DicomSeries source = original;
  for (size_t s = 0; s < source.slices.size(); ++s) {
    const fs::path to = dir / fs::path(source.slices[s].path).filename();
    auto file = Load(source.slices[s].path);
    EXPECT_TRUE(file->loadAllDataIntoMemory().good());
    edit(*file->getDataset());
    if (drop_media_uid) {
      file->getMetaInfo()->findAndDeleteElement(DCM_MediaStorageSOPInstanceUID);
    }
    EXPECT_TRUE(
        file->saveFile(to.c_str(), EXS_Unknown, EET_UndefinedLength,
                       EGL_recalcGL, EPD_noChange, 0, 0,
                       drop_media_uid ? EWM_dontUpdateMeta : EWM_fileformat)
            .good());
    source.slices[s].path = to.string();
  }
  return source;
}

// The UIDs an anonymiser blanks.
void StripUids(DcmDataset& ds) {
  for (const DcmTagKey& tag :
       {DCM_SOPInstanceUID, DCM_StudyInstanceUID, DCM_FrameOfReferenceUID}) {
    ds.findAndDeleteElement(tag);
  }
}

TEST_F(DicomWriterTest, UidsAreDerivedFromSourceAndJob) {
  const DerivedObjects a = Plan();
  const DerivedObjects b = Plan();
  EXPECT_EQ(a.intensity.series_instance_uid, b.intensity.series_instance_uid);
  EXPECT_EQ(a.intensity.sop_instance_uids, b.intensity.sop_instance_uids);
  EXPECT_EQ(a.segmentation.sop_instance_uids, b.segmentation.sop_instance_uids);
  EXPECT_EQ(a.distance_map.sop_instance_uids, b.distance_map.sop_instance_uids);

  // All distinct, all under the root, all at most 64 characters.
  std::set<std::string> all;
  for (const DerivedObjectIdentity* o :
       {&a.intensity, &a.distance_map, &a.segmentation}) {
    all.insert(o->series_instance_uid);
    for (const std::string& uid : o->sop_instance_uids) all.insert(uid);
    if (!o->dimension_organization_uid.empty()) {
      all.insert(o->dimension_organization_uid);
    }
  }
  EXPECT_EQ(all.size(), 3u + grid_->size[2] + 2 + 2);
  for (const std::string& uid : all) {
    EXPECT_THAT(uid, StartsWith(std::string(kTestRoot) + "."));
    EXPECT_LE(uid.size(), 64u);
  }

  DicomWriteOptions other_job = Options();
  other_job.derivation_key = "another threshold";
  EXPECT_NE(Plan(other_job).intensity.series_instance_uid,
            a.intensity.series_instance_uid);
  DicomWriteOptions other_root = Options();
  other_root.uid_root.clear();
  const DerivedObjects c = Plan(other_root);
  EXPECT_THAT(c.intensity.series_instance_uid, StartsWith("2.25."));
  EXPECT_EQ(c.intensity.series_instance_uid,
            Plan(other_root).intensity.series_instance_uid);
  DicomSeries other_source = *source_;
  other_source.slices[2].sop_instance_uid += "1";
  EXPECT_NE(PlanDerivedObjects(other_source, grid_->size[2], Options())
                ->intensity.series_instance_uid,
            a.intensity.series_instance_uid);

  DicomWriteOptions random = Options();
  random.random_uids = true;
  const DerivedObjects r1 = Plan(random), r2 = Plan(random);
  EXPECT_NE(r1.intensity.series_instance_uid, r2.intensity.series_instance_uid);
  EXPECT_NE(r1.intensity.sop_instance_uids[0],
            r2.intensity.sop_instance_uids[0]);
  EXPECT_THAT(r1.intensity.series_instance_uid, StartsWith(kTestRoot));

  // A source whose SOP Instance UIDs were blanked is identified by its
  // files' meta headers (AnonymisedSourceKeepsOneStudyAndFrameForEveryJob);
  // one that nothing identifies (no meta UIDs, no pixel digest: a series
  // made up in memory) gets random UIDs rather than the same UIDs as every
  // other such series.
  TempDir dir;
  DicomSeries anonymous = DoctoredCopy(
      *source_, dir.path(), [](DcmDataset&) {}, /*drop_media_uid=*/true);
  for (DicomSliceInfo& s : anonymous.slices) s.sop_instance_uid.clear();
  anonymous.pixel_digest.clear();
  EXPECT_NE(PlanDerivedObjects(anonymous, grid_->size[2], Options())
                ->intensity.series_instance_uid,
            PlanDerivedObjects(anonymous, grid_->size[2], Options())
                ->intensity.series_instance_uid);
}

TEST_F(DicomWriterTest, SeriesNumbersFollowTheSource) {
  DicomWriteOptions options = Options();
  options.series_number_base = 0;
  const DerivedObjects objects = Plan(options);
  // tests/data/ct-thick has SeriesNumber 201.
  EXPECT_EQ(objects.intensity.series_number, 201001);
  EXPECT_EQ(objects.distance_map.series_number, 201002);
  EXPECT_EQ(objects.segmentation.series_number, 201003);
  EXPECT_EQ(Plan().intensity.series_number, 901);
}

TEST(DeriveDicomUidTest, IsAStableVersion5Uuid) {
  auto uid = DeriveDicomUid("", "interslice test name");
  ASSERT_TRUE(uid.ok()) << uid.status();
  ASSERT_THAT(*uid, StartsWith("2.25."));
  unsigned __int128 value = 0;
  for (char c : uid->substr(5)) value = value * 10 + (c - '0');
  EXPECT_EQ(static_cast<int>((value >> 76) & 0xF), 5);  // version
  EXPECT_EQ(static_cast<int>((value >> 62) & 0x3), 2);  // RFC 4122 variant
  // Pinned: every derived UID depends on this function, so a change would
  // make reruns duplicate earlier results on a PACS instead of replacing them.
  EXPECT_EQ(*uid, *DeriveDicomUid("", "interslice test name"));
  // The value Python's uuid.uuid5(UUID("3f1c9a52-7d0e-4b6a-9c41-52e8d7a0b613"),
  // "interslice test name").int gives: an independent check of the RFC 4122
  // construction.
  EXPECT_EQ(*uid, "2.25.225100569045220189285300786265432999039");
  EXPECT_NE(*uid, *DeriveDicomUid("", "interslice test name."));
  auto rooted = DeriveDicomUid("1.2.3", "interslice test name");
  ASSERT_TRUE(rooted.ok());
  EXPECT_THAT(*rooted, StartsWith("1.2.3."));
  EXPECT_EQ(DeriveDicomUid("1.02", "x").status().code(),
            absl::StatusCode::kInvalidArgument);
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

// A source with DICOM errors of its own (empty type 1C attributes, an empty
// sequence) must not pass them into the derived objects.
TEST_F(DicomWriterTest, EmptyConditionalSourceAttributesAreDropped) {
  TempDir dir;
  const fs::path copy = dir.path() / "source";
  fs::create_directories(copy);
  DicomSeries source = *source_;
  for (size_t s = 0; s < source.slices.size(); ++s) {
    const fs::path to = copy / fs::path(source.slices[s].path).filename();
    fs::copy_file(source.slices[s].path, to);
    source.slices[s].path = to.string();
  }
  {
    auto file = Load(source.slices[0].path);
    DcmDataset& ds = *file->getDataset();
    // Patient Identity Removed YES makes De-identification Method type 1C.
    ds.putAndInsertString(DCM_PatientIdentityRemoved, "YES");
    ds.insertEmptyElement(DCM_DeidentificationMethod);
    ds.insertEmptyElement(DCM_PatientSpeciesDescription);
    ds.insertEmptyElement(DCM_ResponsiblePersonRole);
    ds.insertEmptyElement(DCM_ReferencedStudySequence);
    // Saving over the file it was loaded from: read the pixel data first.
    ASSERT_TRUE(file->loadAllDataIntoMemory().good());
    ASSERT_TRUE(file->saveFile(source.slices[0].path.c_str()).good());
  }
  // The doctored source is invalid (else this test could not fail).
  ASSERT_GT(DciodvfyErrors({source.slices[0].path}), 0);

  const DerivedObjects objects = Plan();
  auto paths = WriteIntensitySeries(source, Intensity(), objects.intensity,
                                    Options(), (dir.path() / "i").string());
  ASSERT_TRUE(paths.ok()) << paths.status();
  const std::string seg = (dir.path() / "seg.dcm").string();
  ASSERT_TRUE(WriteSegmentation(source, Mask(Distance()), objects.segmentation,
                                objects.intensity, SegmentDescription(),
                                Options(), seg)
                  .ok());
  EXPECT_EQ(DciodvfyErrors({paths->front(), seg}), 0);
  auto file = Load(paths->front());
  EXPECT_FALSE(file->getDataset()->tagExists(DCM_ReferencedStudySequence));
  EXPECT_FALSE(file->getDataset()->tagExists(DCM_PatientSpeciesDescription));
  // Repaired, saying only what is known.
  EXPECT_THAT(GetString(*file->getDataset(), DCM_DeidentificationMethod),
              HasSubstr("unknown"));
  EXPECT_EQ(GetString(*file->getDataset(), DCM_PatientIdentityRemoved), "YES");
}

// A copy of the source's files in `dir`, each edited by `edit`, and the
// series pointing at the copies.
// Issue 26: an anonymised source (no SOP Instance, Study Instance or Frame
// of Reference UIDs) got a new random study for every job: `run` and `fill`
// of one series landed in two studies and a rerun duplicated both. Now its
// file meta UIDs, else its pixels, identify it.
TEST_F(DicomWriterTest, AnonymisedSourceKeepsOneStudyAndFrameForEveryJob) {
  TempDir dir;
  for (const bool drop_media_uid : {false, true}) {
    SCOPED_TRACE(drop_media_uid ? "pixels identify it" : "meta identifies it");
    const fs::path copies = dir.path() / (drop_media_uid ? "no-meta" : "meta");
    DoctoredCopy(*source_, copies, StripUids, drop_media_uid);
    {
      DcmFileFormat copy;
      ASSERT_TRUE(copy.loadFile((copies / "I10.dcm").c_str()).good());
      EXPECT_EQ(copy.getMetaInfo()->tagExists(DCM_MediaStorageSOPInstanceUID),
                !drop_media_uid);
    }
    // As a job reads it: the reader sees no SOP Instance UIDs.
    auto read = ReadDicomSeries({copies.string()}, {}, {});
    ASSERT_TRUE(read.ok()) << read.status();
    const DicomSeries& source = *read;
    ASSERT_TRUE(source.study_instance_uid.empty());
    ASSERT_TRUE(source.frame_of_reference_uid.empty());
    ASSERT_TRUE(source.slices[0].sop_instance_uid.empty());
    EXPECT_EQ(source.pixel_digest.size(), 64u);

    DicomWriteOptions run = Options();
    run.derivation_key = "run job";
    DicomWriteOptions fill = Options();
    fill.derivation_key = "fill job";
    auto a = PlanDerivedObjects(source, 5, run);
    auto again = PlanDerivedObjects(source, 5, run);
    auto b = PlanDerivedObjects(source, 5, fill);
    ASSERT_TRUE(a.ok() && again.ok() && b.ok());
    EXPECT_FALSE(a->intensity.study_instance_uid.empty());
    EXPECT_FALSE(a->intensity.frame_of_reference_uid.empty());
    EXPECT_NE(a->intensity.study_instance_uid,
              a->intensity.frame_of_reference_uid);
    // One study and frame for both jobs, and for every object of each.
    EXPECT_EQ(b->segmentation.study_instance_uid,
              a->intensity.study_instance_uid);
    EXPECT_EQ(b->segmentation.frame_of_reference_uid,
              a->intensity.frame_of_reference_uid);
    EXPECT_EQ(a->surface_stl.study_instance_uid,
              a->intensity.study_instance_uid);
    auto previews =
        PlanPreviewSeries(source, {"axial"}, fill, /*same_study=*/nullptr);
    ASSERT_TRUE(previews.ok());
    EXPECT_EQ(previews->study_instance_uid, a->intensity.study_instance_uid);
    EXPECT_EQ(previews->frame_of_reference_uid,
              a->intensity.frame_of_reference_uid);
    // The jobs' own objects differ; a rerun names everything the same.
    EXPECT_NE(b->segmentation.series_instance_uid,
              a->segmentation.series_instance_uid);
    EXPECT_EQ(again->intensity.study_instance_uid,
              a->intensity.study_instance_uid);
    EXPECT_EQ(again->intensity.frame_of_reference_uid,
              a->intensity.frame_of_reference_uid);
    EXPECT_EQ(again->segmentation.series_instance_uid,
              a->segmentation.series_instance_uid);
    EXPECT_EQ(again->intensity.sop_instance_uids,
              a->intensity.sop_instance_uids);

    // Another series (the first three slices only) is another source.
    const fs::path fewer =
        dir.path() / (drop_media_uid ? "fewer-no-meta" : "fewer-meta");
    fs::create_directories(fewer);
    for (const auto& entry : fs::directory_iterator(copies)) {
      if (entry.path().filename() != "I40.dcm") {
        fs::copy_file(entry.path(), fewer / entry.path().filename());
      }
    }
    auto other = ReadDicomSeries({fewer.string()}, {}, {});
    ASSERT_TRUE(other.ok()) << other.status();
    auto c = PlanDerivedObjects(*other, 5, run);
    ASSERT_TRUE(c.ok());
    EXPECT_NE(c->intensity.study_instance_uid, a->intensity.study_instance_uid);
    EXPECT_NE(c->intensity.frame_of_reference_uid,
              a->intensity.frame_of_reference_uid);

    // random_uids still asks for fresh ones.
    DicomWriteOptions random = run;
    random.random_uids = true;
    auto r = PlanDerivedObjects(source, 5, random);
    ASSERT_TRUE(r.ok());
    EXPECT_NE(r->intensity.study_instance_uid, a->intensity.study_instance_uid);
  }
}

std::string SegmentLabelOf(const std::string& path, std::string* type_code,
                           std::string* category_code) {
  DcmSegmentation* raw = nullptr;
  if (!DcmSegmentation::loadFile(path.c_str(), raw).good()) return "";
  std::unique_ptr<DcmSegmentation> seg(raw);
  DcmSegment* segment = seg->getSegment(1);
  if (segment == nullptr) return "";
  OFString label, type, category;
  segment->getSegmentLabel(label);
  segment->getSegmentedPropertyTypeCode().getCodeValue(type);
  segment->getSegmentedPropertyCategoryCode().getCodeValue(category);
  *type_code = type.c_str();
  *category_code = category.c_str();
  return label.c_str();
}

// Issue 26: every SEG was "Bone", an MR brain mask at 100 too.
TEST_F(DicomWriterTest, SegmentIsNamedForModalityAndThreshold) {
  TempDir dir;
  struct Case {
    const char* name;
    const char* modality;
    double lower;
    std::optional<double> upper;
    std::string label;
    std::optional<CodedConcept> code;
    const char* expected_label;
    const char* expected_type;
    const char* expected_category;
  };
  const CodedConcept brain = {"12738006", "SCT", "Brain"};
  const Case cases[] = {
      {"ct bone", "CT", 300, std::nullopt, "", std::nullopt, "Bone",
       kBoneCodeValue, kTissueCodeValue},
      {"ct at 200", "CT", 200, std::nullopt, "", std::nullopt, "Bone",
       kBoneCodeValue, kTissueCodeValue},
      {"ct soft tissue", "CT", 40, std::nullopt, "", std::nullopt,
       "Region above 40 HU", kAnatomicalStructureCodeValue,
       kAnatomicalStructureCodeValue},
      {"ct window", "CT", -500, 199.5, "", std::nullopt,
       "Region -500 to 199.5 HU", kAnatomicalStructureCodeValue,
       kAnatomicalStructureCodeValue},
      {"mr", "MR", 100, std::nullopt, "", std::nullopt,
       "Region above 100 units", kAnatomicalStructureCodeValue,
       kAnatomicalStructureCodeValue},
      {"mr named", "MR", 100, std::nullopt, "Brain mask", std::nullopt,
       "Brain mask", kAnatomicalStructureCodeValue,
       kAnatomicalStructureCodeValue},
      {"mr coded", "MR", 100, std::nullopt, "", brain, "Brain", "12738006",
       kAnatomicalStructureCodeValue},
      {"ct coded bone, labelled", "CT", 100, std::nullopt, "Skull",
       CodedConcept{kBoneCodeValue, "SCT", "Bone"}, "Skull", kBoneCodeValue,
       kTissueCodeValue},
  };
  // Without RescaleType: an MR's values have no units of their own.
  const DicomSeries plain =
      DoctoredCopy(*source_, dir.path() / "plain", [](DcmDataset& ds) {
        ds.findAndDeleteElement(DCM_RescaleType);
        ds.findAndDeleteElement(DCM_Units);
      });
  const DerivedObjects objects = Plan();
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    DicomSeries source = plain;
    source.modality = c.modality;
    absl::StatusOr<SegmentDescription> segment =
        DescribeThresholdSegment(source, c.lower, c.upper, c.label, c.code);
    ASSERT_TRUE(segment.ok()) << segment.status();
    // What the SEG says, read back with DCMTK.
    const std::string path = (dir.path() / "seg.dcm").string();
    ASSERT_TRUE(WriteSegmentation(source, Mask(Distance()),
                                  objects.segmentation, objects.intensity,
                                  *segment, Options(), path)
                    .ok());
    std::string type, category;
    EXPECT_EQ(SegmentLabelOf(path, &type, &category), c.expected_label);
    EXPECT_EQ(type, c.expected_type);
    EXPECT_EQ(category, c.expected_category);
  }
  // The source's own units: PET's Units, else a RescaleType.
  {
    const DicomSeries pet =
        DoctoredCopy(*source_, dir.path() / "pet", [](DcmDataset& ds) {
          ds.findAndDeleteElement(DCM_RescaleType);
          ds.putAndInsertString(DCM_Units, "BQML");
        });
    DicomSeries source = pet;
    source.modality = "PT";
    auto segment =
        DescribeThresholdSegment(source, 2500, std::nullopt, "", std::nullopt);
    ASSERT_TRUE(segment.ok()) << segment.status();
    EXPECT_EQ(segment->label, "Region above 2500 BQML");
  }
  {
    const DicomSeries us = DoctoredCopy(
        *source_, dir.path() / "us",
        [](DcmDataset& ds) { ds.putAndInsertString(DCM_RescaleType, "US"); });
    DicomSeries source = us;
    source.modality = "MR";
    auto segment =
        DescribeThresholdSegment(source, 7, std::nullopt, "", std::nullopt);
    ASSERT_TRUE(segment.ok()) << segment.status();
    EXPECT_EQ(segment->label, "Region above 7 units");  // US = unspecified
  }
  EXPECT_EQ(DescribeThresholdSegment(*source_, 300, std::nullopt,
                                     std::string(65, 'x'), std::nullopt)
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
}

// Issue 44: series descriptions a radiologist reads at a glance: the object
// in words, the parameters, and the source series' number and description;
// cut at the 64 characters of an LO from the end, a source description that
// is not printable ASCII left out rather than copied into objects that may
// declare another character set.
TEST_F(DicomWriterTest, SeriesDescriptionsNameTheObjectAndTheSourceSeries) {
  TempDir dir;
  auto describe = [&](const char* name, const std::string& number,
                      const std::string& description) {
    const DicomSeries copy =
        DoctoredCopy(*source_, dir.path() / name, [&](DcmDataset& ds) {
          ds.findAndDeleteElement(DCM_SeriesNumber);
          ds.findAndDeleteElement(DCM_SeriesDescription);
          if (!number.empty()) {
            ds.putAndInsertString(DCM_SeriesNumber, number.c_str());
          }
          if (!description.empty()) {
            ds.putAndInsertString(DCM_SeriesDescription, description.c_str());
          }
        });
    DicomWriteOptions options = Options();
    options.parameter_summary = ">=300 HU, 0.5 mm, smooth";
    options.intensity_summary = "0.5 mm, linear";
    const absl::StatusOr<DerivedObjects> objects =
        PlanDerivedObjects(copy, grid_->size[2], options);
    EXPECT_TRUE(objects.ok()) << objects.status();
    return objects.ok() ? *objects : DerivedObjects{};
  };
  const DerivedObjects named = describe("named", "3", "HEAD 5MM");
  EXPECT_EQ(named.segmentation.series_description,
            "Segmentation >=300 HU, 0.5 mm, smooth, from #3 HEAD 5MM");
  EXPECT_EQ(named.distance_map.series_description,
            "Distance (mm) >=300 HU, 0.5 mm, smooth, from #3 HEAD 5MM");
  EXPECT_EQ(named.surface_stl.series_description,
            "Surface (STL) >=300 HU, 0.5 mm, smooth, from #3 HEAD 5MM");
  EXPECT_EQ(named.intensity.series_description,
            "Interpolated 0.5 mm, linear, from #3 HEAD 5MM");
  EXPECT_EQ(describe("number only", "3", "").segmentation.series_description,
            "Segmentation >=300 HU, 0.5 mm, smooth, from #3");
  EXPECT_EQ(describe("none", "", "").segmentation.series_description,
            "Segmentation >=300 HU, 0.5 mm, smooth");
  // UTF-8 "Kopf ä": left out, the number kept.
  EXPECT_EQ(
      describe("utf8", "3", "Kopf \xc3\xa4").segmentation.series_description,
      "Segmentation >=300 HU, 0.5 mm, smooth, from #3");
  // A long source description is cut, never the object or the parameters,
  // and the cut leaves no trailing blank.
  const std::string cut = describe("long", "3", "Head routine a 5 mm")
                              .segmentation.series_description;
  EXPECT_EQ(cut,
            "Segmentation >=300 HU, 0.5 mm, smooth, from #3 Head routine a 5");
}

// Issue 44: units longer than 16 characters became "units" ("SIGNAL
// INTENSITY (UNITLESS)", an MR's RescaleType, an LO of up to 64).
TEST_F(DicomWriterTest, LongUnitsAreKeptOrRefusedNeverReplaced) {
  TempDir dir;
  const std::string units = "SIGNAL INTENSITY (UNITLESS)";
  const DicomSeries doctored =
      DoctoredCopy(*source_, dir.path() / "mr", [&units](DcmDataset& ds) {
        ds.putAndInsertString(DCM_RescaleType, units.c_str());
      });
  DicomSeries source = doctored;
  source.modality = "MR";
  const DerivedObjects objects = Plan();
  for (const std::optional<double> upper :
       {std::optional<double>(), std::optional<double>(1500)}) {
    absl::StatusOr<SegmentDescription> segment =
        DescribeThresholdSegment(source, 100, upper, "", std::nullopt);
    ASSERT_TRUE(segment.ok()) << segment.status();
    const std::string expected = upper.has_value()
                                     ? "Region 100 to 1500 " + units
                                     : "Region above 100 " + units;
    EXPECT_EQ(segment->label, expected);
    // The SEG holds it whole (SegmentLabel, LO) and stays valid.
    const std::string path = (dir.path() / "seg.dcm").string();
    ASSERT_TRUE(WriteSegmentation(source, Mask(Distance()),
                                  objects.segmentation, objects.intensity,
                                  *segment, Options(), path)
                    .ok());
    ExpectValidIod({path});
    std::string type, category;
    EXPECT_EQ(SegmentLabelOf(path, &type, &category), expected);
  }

  // Units that cannot fit the label (RescaleType's full 64 characters) are
  // an error that says how to name the segment, not a shorter label.
  const DicomSeries longest =
      DoctoredCopy(*source_, dir.path() / "longest", [](DcmDataset& ds) {
        ds.putAndInsertString(DCM_RescaleType, std::string(64, 'U').c_str());
      });
  source = longest;
  source.modality = "MR";
  absl::StatusOr<SegmentDescription> refused =
      DescribeThresholdSegment(source, 100, std::nullopt, "", std::nullopt);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(refused.status().message()),
              HasSubstr("--segment-label"));
  // A label of the job's own needs no units.
  absl::StatusOr<SegmentDescription> named = DescribeThresholdSegment(
      source, 100, std::nullopt, "Brain mask", std::nullopt);
  ASSERT_TRUE(named.ok()) << named.status();
  EXPECT_EQ(named->label, "Brain mask");
}

// Issue 44: OHIF warned "RecommendedDisplayCIELabValue not found ... the
// default color was used" for every `run` SEG (the fill's SEGs have one).
TEST_F(DicomWriterTest, SegmentCarriesItsDisplayColour) {
  TempDir dir;
  struct Case {
    const char* name;
    const char* modality;
    double lower;
    std::array<uint8_t, 3> expected_rgb;
  };
  const Case cases[] = {
      // Bone as 3D Slicer's GenericAnatomyColors shows it.
      {"ct bone", "CT", 300, {241, 214, 145}},
      // A region claims no tissue: the colour of a fill's first label.
      {"mr region", "MR", 100, *DefaultLabelSegment(1).rgb},
  };
  const DerivedObjects objects = Plan();
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    DicomSeries source = *source_;
    source.modality = c.modality;
    absl::StatusOr<SegmentDescription> segment = DescribeThresholdSegment(
        source, c.lower, std::nullopt, "", std::nullopt);
    ASSERT_TRUE(segment.ok()) << segment.status();
    EXPECT_EQ(segment->rgb, c.expected_rgb);
    const std::string path = (dir.path() / "seg.dcm").string();
    ASSERT_TRUE(WriteSegmentation(source, Mask(Distance()),
                                  objects.segmentation, objects.intensity,
                                  *segment, Options(), path)
                    .ok());
    ExpectValidIod({path});
    // Read back with DCMTK: present, encoded as the fill's SEG encodes its
    // colours, and decoding to the intended sRGB colour.
    DcmSegmentation* raw = nullptr;
    ASSERT_TRUE(DcmSegmentation::loadFile(path.c_str(), raw).good());
    std::unique_ptr<DcmSegmentation> seg(raw);
    DcmSegment* written = seg->getSegment(1);
    ASSERT_NE(written, nullptr);
    Uint16 l = 0, a = 0, b = 0;
    ASSERT_TRUE(written->getRecommendedDisplayCIELabValue(l, a, b).good());
    LabelSegment same_colour;
    same_colour.rgb = c.expected_rgb;
    EXPECT_EQ((std::array<uint16_t, 3>{l, a, b}), SegmentCieLab(same_colour));
    double r = 0, g = 0, bl = 0;
    IODCIELabUtil::dicomLab2RGB(r, g, bl, l, a, b);
    EXPECT_NEAR(255 * r, c.expected_rgb[0], 1);
    EXPECT_NEAR(255 * g, c.expected_rgb[1], 1);
    EXPECT_NEAR(255 * bl, c.expected_rgb[2], 1);
  }
}

TEST(ParseCodedConceptTest, SchemeValueMeaningEachChecked) {
  auto bone = ParseCodedConcept("SCT:272673000:Bone");
  ASSERT_TRUE(bone.ok()) << bone.status();
  EXPECT_EQ(bone->scheme, "SCT");
  EXPECT_EQ(bone->value, "272673000");
  EXPECT_EQ(bone->meaning, "Bone");
  auto colon = ParseCodedConcept("99LOCAL_X:a-1:Ratio 1:2");
  ASSERT_TRUE(colon.ok()) << colon.status();
  EXPECT_EQ(colon->meaning, "Ratio 1:2");
  struct Bad {
    const char* text;
    const char* says;
  };
  for (const Bad& bad : {
           Bad{"SCT:272673000", "scheme:value:meaning"},
           Bad{"sct:272673000:Bone", "coding scheme"},
           Bad{":272673000:Bone", "coding scheme"},
           Bad{"SCHEMEWAYTOOLONG17:1:Bone", "coding scheme"},
           Bad{"SCT::Bone", "code value"},
           Bad{"SCT:12345678901234567:Bone", "code value"},
           Bad{"SCT:1\\2:Bone", "code value"},
           Bad{"SCT:272673000:", "code meaning"},
           Bad{"SCT:272673000:Bone\\Marrow", "code meaning"},
       }) {
    SCOPED_TRACE(bad.text);
    absl::Status status = ParseCodedConcept(bad.text).status();
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(status.message()), HasSubstr(bad.says));
  }
  EXPECT_FALSE(
      ParseCodedConcept(absl::StrCat("SCT:1:", std::string(65, 'm'))).ok());
  EXPECT_TRUE(ValidateSegmentLabel("Region above 100 units").ok());
  EXPECT_FALSE(ValidateSegmentLabel("").ok());
  EXPECT_FALSE(ValidateSegmentLabel("a\\b").ok());
  EXPECT_FALSE(ValidateSegmentLabel("tab\there").ok());
}

// Issue 26: dciodvfy found Laterality (General Series, type 2C) missing on
// the intensity series of sources without BodyPartExamined or with a paired
// one and no laterality. Each case: the intensity series, the SEG, the
// distance map and the preview series pass dciodvfy.
TEST_F(DicomWriterTest, LateralityIsValidWhateverTheSourceLacks) {
  TempDir dir;
  struct Case {
    const char* name;
    const char* body_part;         // null = absent
    const char* laterality;        // null = absent
    const char* image_laterality;  // null = absent
    // Expected in the intensity series: null = absent, "" = empty.
    const char* expected_body_part;
    const char* expected_laterality;
    const char* expected_image_laterality;
  };
  const Case cases[] = {
      {"no body part", nullptr, nullptr, nullptr, nullptr, "", nullptr},
      {"paired, no laterality", "KNEE", nullptr, nullptr, "KNEE", "", nullptr},
      {"unknown term", "KNEEJOINT", nullptr, nullptr, "KNEEJOINT", "", nullptr},
      {"unpaired", "HEAD", nullptr, nullptr, "HEAD", nullptr, nullptr},
      {"paired with laterality", "KNEE", "R", nullptr, "KNEE", "R", nullptr},
      {"image laterality", "BREAST", nullptr, "L", "BREAST", nullptr, "L"},
      {"invalid values dropped", "head", "X", nullptr, nullptr, "", nullptr},
      {"empty laterality, unpaired", "CHEST", "", nullptr, "CHEST", nullptr,
       nullptr},
  };
  const DerivedObjects objects = Plan();
  const Volume<float> intensity = Intensity();
  const Volume<float> distance = Distance();
  const std::vector<uint8_t> rgb(16 * 8 * 3, 128);
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    const fs::path here = dir.path() / c.name;
    const DicomSeries source =
        DoctoredCopy(*source_, here / "source", [&c](DcmDataset& ds) {
          for (const DcmTagKey& tag :
               {DCM_BodyPartExamined, DCM_Laterality, DCM_ImageLaterality}) {
            ds.findAndDeleteElement(tag);
          }
          if (c.body_part) {
            ds.putAndInsertString(DCM_BodyPartExamined, c.body_part);
          }
          if (c.laterality) ds.putAndInsertString(DCM_Laterality, c.laterality);
          if (c.image_laterality) {
            ds.putAndInsertString(DCM_ImageLaterality, c.image_laterality);
          }
        });
    auto paths = WriteIntensitySeries(source, intensity, objects.intensity,
                                      Options(), (here / "i").string());
    ASSERT_TRUE(paths.ok()) << paths.status();
    const std::string seg = (here / "seg.dcm").string();
    ASSERT_TRUE(WriteSegmentation(source, Mask(distance), objects.segmentation,
                                  objects.intensity, SegmentDescription(),
                                  Options(), seg)
                    .ok());
    const std::string map = (here / "distance.dcm").string();
    ASSERT_TRUE(WriteDistanceMap(source, distance, objects.distance_map,
                                 objects.intensity, Options(), map)
                    .ok());
    RgbPicture picture;
    picture.name = "axial";
    picture.width = 16;
    picture.height = 8;
    picture.rgb = &rgb;
    picture.description = "test";
    auto preview_identity =
        PlanPreviewSeries(source, {"axial"}, Options(), &objects.intensity);
    ASSERT_TRUE(preview_identity.ok()) << preview_identity.status();
    auto previews = WritePreviewSeries(source, *grid_, {picture},
                                       *preview_identity, &objects.intensity,
                                       Options(), (here / "p").string());
    ASSERT_TRUE(previews.ok()) << previews.status();
    std::string errors;
    EXPECT_EQ(
        DciodvfyErrors({paths->front(), seg, map, previews->front()}, &errors),
        0)
        << errors;

    auto file = Load(paths->front());
    DcmDataset& ds = *file->getDataset();
    const auto expect = [&ds](const DcmTagKey& tag, const char* expected) {
      if (expected == nullptr) {
        EXPECT_FALSE(ds.tagExists(tag)) << tag.toString();
      } else {
        EXPECT_TRUE(ds.tagExists(tag)) << tag.toString();
        EXPECT_EQ(GetString(ds, tag), expected) << tag.toString();
      }
    };
    expect(DCM_BodyPartExamined, c.expected_body_part);
    expect(DCM_Laterality, c.expected_laterality);
    expect(DCM_ImageLaterality, c.expected_image_laterality);
  }
}

TEST_F(DicomWriterTest, UnwritableFolderIsAClearError) {
  TempDir dir;
  const fs::path blocker = dir.path() / "a_file";
  std::ofstream(blocker) << "x";
  const DerivedObjects objects = Plan();
  auto paths = WriteIntensitySeries(*source_, Intensity(), objects.intensity,
                                    Options(), (blocker / "out").string());
  ASSERT_FALSE(paths.ok());
  EXPECT_EQ(paths.status().code(), absl::StatusCode::kInternal);
  EXPECT_THAT(paths.status().message(), HasSubstr("output folder"));

  const absl::Status seg = WriteSegmentation(
      *source_, Mask(Distance()), objects.segmentation, objects.intensity,
      SegmentDescription(), Options(), (blocker / "seg.dcm").string());
  EXPECT_EQ(seg.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(seg.message(), HasSubstr("seg.dcm"));
  // No temporary files left behind.
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()),
                          fs::directory_iterator()),
            1);
}

TEST_F(DicomWriterTest, GridMismatchIsInvalidArgument) {
  TempDir dir;
  const DerivedObjects objects = Plan();
  Volume<uint8_t> mask = Mask(Distance());
  // A rotated grid (direction differs from the source's).
  Volume<uint8_t> rotated = mask;
  rotated.grid.direction = {0, 1, 0, 1, 0, 0, 0, 0, -1};
  auto write_seg = [&](const Volume<uint8_t>& m,
                       const DerivedObjectIdentity& referenced) {
    return WriteSegmentation(*source_, m, objects.segmentation, referenced,
                             SegmentDescription(), Options(),
                             (dir.path() / "s.dcm").string())
        .code();
  };
  EXPECT_EQ(write_seg(rotated, objects.intensity),
            absl::StatusCode::kInvalidArgument);
  // Voxel count that does not match the grid.
  Volume<uint8_t> short_mask = mask;
  short_mask.data.pop_back();
  EXPECT_EQ(write_seg(short_mask, objects.intensity),
            absl::StatusCode::kInvalidArgument);
  // A referenced series with too few images.
  DerivedObjectIdentity few = objects.intensity;
  few.sop_instance_uids.pop_back();
  EXPECT_EQ(write_seg(mask, few), absl::StatusCode::kInvalidArgument);
  Volume<float> values = Intensity();
  values.grid.direction = rotated.grid.direction;
  EXPECT_EQ(WriteIntensitySeries(*source_, values, objects.intensity, Options(),
                                 (dir.path() / "d").string())
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  // Non-finite values.
  Volume<float> nan = Intensity();
  nan.data[5] = std::nanf("");
  EXPECT_EQ(WriteIntensitySeries(*source_, nan, objects.intensity, Options(),
                                 (dir.path() / "n").string())
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  // A malformed UID root.
  DicomWriteOptions bad = Options();
  bad.uid_root = "1.2.x";
  EXPECT_EQ(PlanDerivedObjects(*source_, grid_->size[2], bad).status().code(),
            absl::StatusCode::kInvalidArgument);
  // Nothing was written.
  EXPECT_TRUE(fs::is_empty(dir.path()));
}

TEST_F(DicomWriterTest, MeshConventionNoteNamesFrameAndAxes) {
  const std::string note = MeshConventionNote(*source_);
  EXPECT_THAT(note, HasSubstr("LPS"));
  EXPECT_THAT(note, HasSubstr("millimetres"));
  EXPECT_THAT(note, HasSubstr(source_->frame_of_reference_uid));
}

// The same data presented as an MR series and as a series of another image
// class (PET here), which take the MR Image and Secondary Capture paths.
TEST_F(DicomWriterTest, MrAndOtherSourcesPassDciodvfy) {
  TempDir dir;
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
    auto objects = PlanDerivedObjects(source, grid_->size[2], Options());
    ASSERT_TRUE(objects.ok()) << objects.status();
    EXPECT_EQ(objects->intensity.sop_class_uid, c.expected_sop_class);
    const std::string out = (dir.path() / c.name).string();
    auto paths = WriteIntensitySeries(source, Intensity(), objects->intensity,
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

}  // namespace
}  // namespace interslice
