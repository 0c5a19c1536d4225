// The enhanced layout (core/dicom_out/enhanced_series.h): one Enhanced CT
// instance that is the classic intensity series frame by frame, valid for
// dciodvfy, referenced frame by frame by the SEG and the Parametric Map.
#include "core/dicom_out/enhanced_series.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/pixel_decode.h"
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
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using testing::ExpectValidIod;
using testing::GetString;
using ::testing::HasSubstr;
using testing::LoadDicom;

constexpr char kTestRoot[] = "1.2.826.0.1.3680043.10.1234";
// The field-map volume of philips-enhanced-mr-64frames.dcm (as the reader
// names it).
constexpr char kPhilipsFieldMapVolume[] =
    "stack 1, temporal position 1, frame type "
    "ORIGINAL\\PRIMARY\\T1\\FIELD_MAP (REAL)";

class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_enhanced_") {}
};

DicomWriteOptions Options() {
  DicomWriteOptions options;
  options.uid_root = kTestRoot;
  options.series_number_base = 900;
  options.derivation_key = "enhanced test job";
  return options;
}

// A source series of tests/data, an output grid (a 64 x 64 in-plane crop,
// 1 mm slices over the whole series) and the source resampled onto it.
struct Case {
  DicomSeries source;
  Grid grid;
  Volume<float> intensity;
};

// `name`: a folder or file under tests/data, or an absolute path; `volume`
// picks one volume of a multi-frame source (DicomReadOptions::volume).
Case LoadCase(const std::string& name, const std::string& volume = "") {
  QuietDicomToolkitLogging();
  Case c;
  DicomReadOptions read_options;
  read_options.volume = volume;
  auto series = ReadDicomSeries(
      {(fs::path(::interslice::testing::TestDataDir()) / name).string()},
      read_options, {});
  EXPECT_TRUE(series.ok()) << series.status();
  if (!series.ok()) return c;
  c.source = *std::move(series);
  const Grid& in = c.source.image.grid;
  const int64_t x0 = in.size[0] / 2 - 32, y0 = in.size[1] / 2 - 32;
  const VoxelBox box{{x0, y0, 0}, {x0 + 64, y0 + 64, in.size[2]}};
  c.grid = CropGrid(in, VoxelBox{box.begin, {box.end[0], box.end[1], 1}});
  const double extent = c.source.slices.back().position_along_normal -
                        c.source.slices.front().position_along_normal;
  c.grid.spacing[2] = 1.0;
  c.grid.size[2] = static_cast<int64_t>(std::floor(extent)) + 1;
  const Volume<float> cropped = CropVolume(c.source.image, box);
  std::vector<double> positions;
  for (const DicomSliceInfo& s : c.source.slices) {
    positions.push_back(s.position_along_normal);
  }
  auto intensity =
      ResampleSourceSlices(cropped, positions, c.grid, std::nullopt, {});
  EXPECT_TRUE(intensity.ok()) << intensity.status();
  if (intensity.ok()) c.intensity = *std::move(intensity);
  return c;
}

DcmItem* Item(DcmItem& parent, const DcmTagKey& sequence, unsigned long i) {
  DcmItem* item = nullptr;
  if (parent.findAndGetSequenceItem(sequence, item, static_cast<int>(i))
          .bad()) {
    return nullptr;
  }
  return item;
}

// The functional group `group` of frame `k`: per frame if there, else shared.
DcmItem* Group(DcmItem& ds, const DcmTagKey& group, unsigned long k) {
  if (DcmItem* frame = Item(ds, DCM_PerFrameFunctionalGroupsSequence, k)) {
    if (DcmItem* item = Item(*frame, group, 0)) return item;
  }
  if (DcmItem* shared = Item(ds, DCM_SharedFunctionalGroupsSequence, 0)) {
    return Item(*shared, group, 0);
  }
  return nullptr;
}

// Writes the classic and the enhanced layout of `c` and checks that frame k
// of the enhanced instance is image k of the classic series: position,
// orientation, spacing, rescale and every stored value, read back with
// DCMTK's plain dataset API (not the writer's classes).
void ExpectEnhancedIsClassic(const Case& c, const DicomWriteOptions& options) {
  TempDir dir;
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], options);
  ASSERT_TRUE(objects.ok()) << objects.status();
  auto classic =
      WriteIntensitySeries(c.source, c.intensity, objects->intensity, options,
                           (dir.path() / "classic").string());
  ASSERT_TRUE(classic.ok()) << classic.status();
  auto identity = PlanEnhancedIntensity(c.source, objects->intensity, options);
  ASSERT_TRUE(identity.ok()) << identity.status();
  const std::string path = (dir.path() / "enhanced.dcm").string();
  ASSERT_TRUE(
      WriteEnhancedIntensity(c.source, c.intensity, *identity, options, path)
          .ok());
  {
    SCOPED_TRACE("enhanced " + c.source.modality);
    ExpectValidIod({path});
  }
  RegisterDicomDecoders();
  auto enhanced = LoadDicom(path);
  DcmDataset& e = *enhanced->getDataset();
  ASSERT_TRUE(e.chooseRepresentation(EXS_LittleEndianExplicit, nullptr).good());
  EXPECT_EQ(GetString(e, DCM_SOPClassUID), c.source.modality == "MR"
                                               ? UID_EnhancedMRImageStorage
                                               : UID_EnhancedCTImageStorage);
  EXPECT_EQ(GetString(e, DCM_Modality), c.source.modality);
  EXPECT_EQ(GetString(e, DCM_SOPInstanceUID), identity->sop_instance_uids[0]);
  EXPECT_EQ(GetString(e, DCM_StudyInstanceUID), c.source.study_instance_uid);
  EXPECT_EQ(GetString(e, DCM_FrameOfReferenceUID),
            c.source.frame_of_reference_uid);
  EXPECT_EQ(GetString(e, DCM_SeriesNumber), "901");
  ASSERT_EQ(GetString(e, DCM_NumberOfFrames), std::to_string(c.grid.size[2]));
  const Uint16* pixels = nullptr;
  unsigned long count = 0;
  ASSERT_TRUE(e.findAndGetUint16Array(DCM_PixelData, pixels, &count).good());
  const size_t plane = static_cast<size_t>(c.grid.size[0] * c.grid.size[1]);
  ASSERT_EQ(count, plane * static_cast<size_t>(c.grid.size[2]));
  for (size_t k = 0; k < classic->size(); ++k) {
    SCOPED_TRACE(k);
    auto image = LoadDicom((*classic)[k]);
    DcmDataset& i = *image->getDataset();
    ASSERT_TRUE(
        i.chooseRepresentation(EXS_LittleEndianExplicit, nullptr).good());
    DcmItem* position = Group(e, DCM_PlanePositionSequence, k);
    DcmItem* orientation = Group(e, DCM_PlaneOrientationSequence, k);
    DcmItem* measures = Group(e, DCM_PixelMeasuresSequence, k);
    DcmItem* transform = Group(e, DCM_PixelValueTransformationSequence, k);
    ASSERT_NE(position, nullptr);
    ASSERT_NE(orientation, nullptr);
    ASSERT_NE(measures, nullptr);
    ASSERT_NE(transform, nullptr);
    EXPECT_EQ(GetString(*position, DCM_ImagePositionPatient),
              GetString(i, DCM_ImagePositionPatient));
    EXPECT_EQ(GetString(*orientation, DCM_ImageOrientationPatient),
              GetString(i, DCM_ImageOrientationPatient));
    EXPECT_EQ(GetString(*measures, DCM_PixelSpacing),
              GetString(i, DCM_PixelSpacing));
    EXPECT_EQ(GetString(*measures, DCM_SliceThickness),
              GetString(i, DCM_SliceThickness));
    // A classic MR image without a rescale has the identity (MR images
    // have no Modality LUT module).
    const bool classic_rescale = i.tagExists(DCM_RescaleSlope);
    EXPECT_EQ(GetString(*transform, DCM_RescaleSlope),
              classic_rescale ? GetString(i, DCM_RescaleSlope) : "1");
    EXPECT_EQ(GetString(*transform, DCM_RescaleIntercept),
              classic_rescale ? GetString(i, DCM_RescaleIntercept) : "0");
    EXPECT_EQ(GetString(e, DCM_PixelRepresentation),
              GetString(i, DCM_PixelRepresentation));
    // Frame content: dimension index k + 1 along the normal.
    DcmItem* content = Group(e, DCM_FrameContentSequence, k);
    ASSERT_NE(content, nullptr);
    EXPECT_EQ(GetString(*content, DCM_DimensionIndexValues),
              std::to_string(k + 1));
    const Uint16* classic_pixels = nullptr;
    unsigned long classic_count = 0;
    ASSERT_TRUE(
        i.findAndGetUint16Array(DCM_PixelData, classic_pixels, &classic_count)
            .good());
    ASSERT_EQ(classic_count, plane);
    size_t differing = 0;
    for (size_t p = 0; p < plane; ++p) {
      differing += pixels[k * plane + p] != classic_pixels[p];
    }
    EXPECT_EQ(differing, 0u);
  }
}

TEST(EnhancedSeriesTest, ThickCtFramesAreTheClassicImages) {
  const Case c = LoadCase("ct-thick");
  ExpectEnhancedIsClassic(c, Options());
}

// The tilted head CT (tilt resampled in-plane by the reader): the same.
TEST(EnhancedSeriesTest, TiltedCtFramesAreTheClassicImages) {
  const Case c = LoadCase("ct-tilt");
  ExpectEnhancedIsClassic(c, Options());
}

// An MR Image Storage series (4 slices, 5 mm apart, written here from the
// one real Siemens MR slice of tests/data/transfer-syntaxes with its own
// positions and UIDs): the classic layout is MR Image, the enhanced one
// Enhanced MR Image, frame k = image k.
std::string WriteMrImageSeries(const fs::path& dir) {
  auto file = LoadDicom((fs::path(::interslice::testing::TestDataDir()) /
                         "transfer-syntaxes" / "1.dcm")
                            .string());
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_SOPClassUID), UID_MRImageStorage);
  double position[3], orientation[6];
  for (int i = 0; i < 3; ++i) {
    ds.findAndGetFloat64(DCM_ImagePositionPatient, position[i], i);
  }
  for (int i = 0; i < 6; ++i) {
    ds.findAndGetFloat64(DCM_ImageOrientationPatient, orientation[i], i);
  }
  const double normal[3] = {
      orientation[1] * orientation[5] - orientation[2] * orientation[4],
      orientation[2] * orientation[3] - orientation[0] * orientation[5],
      orientation[0] * orientation[4] - orientation[1] * orientation[3]};
  fs::create_directories(dir);
  for (int k = 0; k < 4; ++k) {
    std::string text;
    for (int i = 0; i < 3; ++i) {
      if (i > 0) text += "\\";
      text += std::to_string(position[i] + 5.0 * k * normal[i]);
    }
    EXPECT_TRUE(
        ds.putAndInsertString(DCM_ImagePositionPatient, text.c_str()).good());
    const std::string uid =
        std::string(kTestRoot) + ".77." + std::to_string(k + 1);
    ds.putAndInsertString(DCM_SOPInstanceUID, uid.c_str());
    ds.putAndInsertString(DCM_InstanceNumber, std::to_string(k + 1).c_str());
    ds.findAndDeleteElement(DCM_SliceLocation);
    ds.findAndDeleteElement(DCM_MediaStorageSOPInstanceUID);
    file->getMetaInfo()->clear();
    EXPECT_TRUE(
        file->saveFile((dir / ("MR" + std::to_string(k) + ".dcm")).c_str(),
                       EXS_LittleEndianExplicit)
            .good());
  }
  return dir.string();
}

TEST(EnhancedSeriesTest, MrImageSeriesFramesAreTheEnhancedMrImages) {
  TempDir source_dir;
  const Case c = LoadCase(WriteMrImageSeries(source_dir.path() / "mr"));
  ASSERT_EQ(c.source.modality, "MR");
  ASSERT_EQ(c.source.sop_class_uid, UID_MRImageStorage);
  ASSERT_EQ(c.source.slices.size(), 4u);
  ExpectEnhancedIsClassic(c, Options());
}

// A Siemens XA10 Enhanced MR source (6 frames): read as MR, written as
// Enhanced MR (its classic layout is Secondary Capture).
TEST(EnhancedSeriesTest, EnhancedMrSourceFramesAreTheClassicImages) {
  const Case c = LoadCase("multiframe/siemens-xa10-6_1.dcm");
  ASSERT_EQ(c.source.modality, "MR");
  ExpectEnhancedIsClassic(c, Options());
}

// The Philips field map (the REAL frames of a T1 B0 acquisition, rescaled
// -500 + 1.28 x stored): its own complex component and contrast, its
// rescale, and each derivation names the source frame it came from.
TEST(EnhancedSeriesTest, EnhancedMrDescribesItsSourceFrames) {
  const Case c = LoadCase("multiframe/philips-enhanced-mr-64frames.dcm",
                          kPhilipsFieldMapVolume);
  ASSERT_EQ(c.source.modality, "MR");
  ExpectEnhancedIsClassic(c, Options());
  TempDir dir;
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], Options());
  ASSERT_TRUE(objects.ok());
  auto identity =
      PlanEnhancedIntensity(c.source, objects->intensity, Options());
  ASSERT_TRUE(identity.ok());
  const std::string path = (dir.path() / "enhanced.dcm").string();
  ASSERT_TRUE(
      WriteEnhancedIntensity(c.source, c.intensity, *identity, Options(), path)
          .ok());
  auto file = LoadDicom(path);
  DcmDataset& e = *file->getDataset();
  DcmItem* type = Group(e, DCM_MRImageFrameTypeSequence, 0);
  ASSERT_NE(type, nullptr);
  EXPECT_EQ(GetString(*type, DCM_FrameType),
            "DERIVED\\PRIMARY\\VOLUME\\RESAMPLED");
  EXPECT_EQ(GetString(*type, DCM_ComplexImageComponent), "REAL");
  EXPECT_EQ(GetString(*type, DCM_AcquisitionContrast), "T1");
  EXPECT_EQ(GetString(e, DCM_ComplexImageComponent), "REAL");
  EXPECT_EQ(GetString(e, DCM_ImageType), "DERIVED\\PRIMARY\\VOLUME\\RESAMPLED");
  // No CT groups in an MR object.
  EXPECT_EQ(Group(e, DCM_CTImageFrameTypeSequence, 0), nullptr);
  EXPECT_EQ(Group(e, DCM_IrradiationEventIdentificationSequence, 0), nullptr);
  DcmItem* transform = Group(e, DCM_PixelValueTransformationSequence, 0);
  ASSERT_NE(transform, nullptr);
  EXPECT_EQ(GetString(*transform, DCM_RescaleIntercept), "-500");
  // Frame k's derivation names source frames (1-based, of the one source
  // instance) whose positions bracket it.
  for (unsigned long k = 0; k < static_cast<unsigned long>(c.grid.size[2]);
       ++k) {
    SCOPED_TRACE(k);
    DcmItem* derivation = Group(e, DCM_DerivationImageSequence, k);
    ASSERT_NE(derivation, nullptr);
    DcmItem* source = Item(*derivation, DCM_SourceImageSequence, 0);
    ASSERT_NE(source, nullptr);
    const std::string frame = GetString(*source, DCM_ReferencedFrameNumber);
    ASSERT_FALSE(frame.empty());
    const int n = std::stoi(frame);
    const auto slice =
        std::find_if(c.source.slices.begin(), c.source.slices.end(),
                     [n](const DicomSliceInfo& s) { return s.frame + 1 == n; });
    ASSERT_NE(slice, c.source.slices.end()) << "frame " << n;
    EXPECT_LE(std::abs(slice->position_along_normal -
                       (c.source.slices.front().position_along_normal +
                        static_cast<double>(k) * c.grid.spacing[2])),
              c.source.max_gap_mm + 1e-3);
  }
  // Source Image Evidence lists the one source instance once.
  DcmItem* evidence = Item(e, DCM_SourceImageEvidenceSequence, 0);
  ASSERT_NE(evidence, nullptr);
  DcmItem* series = Item(*evidence, DCM_ReferencedSeriesSequence, 0);
  ASSERT_NE(series, nullptr);
  EXPECT_NE(Item(*series, DCM_ReferencedSOPSequence, 0), nullptr);
  EXPECT_EQ(Item(*series, DCM_ReferencedSOPSequence, 1), nullptr);
}

TEST(EnhancedSeriesTest, RleEnhancedCtIsValidAndTheSameVolume) {
  const Case c = LoadCase("ct-thick");
  DicomWriteOptions options = Options();
  options.intensity_encoding = DicomWriteOptions::PixelEncoding::kRleLossless;
  ExpectEnhancedIsClassic(c, options);
  TempDir dir;
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], options);
  ASSERT_TRUE(objects.ok());
  auto identity = PlanEnhancedIntensity(c.source, objects->intensity, options);
  ASSERT_TRUE(identity.ok());
  const std::string path = (dir.path() / "rle.dcm").string();
  ASSERT_TRUE(
      WriteEnhancedIntensity(c.source, c.intensity, *identity, options, path)
          .ok());
  auto file = LoadDicom(path);
  EXPECT_EQ(GetString(*file->getMetaInfo(), DCM_TransferSyntaxUID),
            UID_RLELosslessTransferSyntax);
}

// The SEG and the distance map reference frame k + 1 of the one enhanced
// instance (not image k of a series that is not there), and stay valid.
void ExpectSegAndDistanceMapReferenceFrames(const Case& c,
                                            const char* enhanced_sop_class,
                                            float threshold) {
  const DicomWriteOptions options = Options();
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], options);
  ASSERT_TRUE(objects.ok());
  auto enhanced = PlanEnhancedIntensity(c.source, objects->intensity, options);
  ASSERT_TRUE(enhanced.ok());
  Volume<float> distance;
  distance.grid = c.grid;
  distance.data.resize(c.grid.VoxelCount());
  Volume<uint8_t> mask;
  mask.grid = c.grid;
  mask.data.resize(c.grid.VoxelCount());
  for (size_t n = 0; n < distance.data.size(); ++n) {
    distance.data[n] = c.intensity.data[n] > threshold ? 1.0f : -1.0f;
    mask.data[n] = distance.data[n] > 0;
  }
  TempDir dir;
  const std::string seg = (dir.path() / "seg.dcm").string();
  const std::string map = (dir.path() / "distance.dcm").string();
  ASSERT_TRUE(WriteSegmentation(c.source, mask, objects->segmentation,
                                *enhanced, SegmentDescription{}, options, seg)
                  .ok());
  ASSERT_TRUE(WriteDistanceMap(c.source, distance, objects->distance_map,
                               *enhanced, options, map)
                  .ok());
  ExpectValidIod({seg, map});
  for (const std::string& path : {seg, map}) {
    SCOPED_TRACE(path);
    auto file = LoadDicom(path);
    DcmDataset& ds = *file->getDataset();
    for (unsigned long k = 0; k < static_cast<unsigned long>(c.grid.size[2]);
         ++k) {
      SCOPED_TRACE(k);
      DcmItem* derivation = Group(ds, DCM_DerivationImageSequence, k);
      ASSERT_NE(derivation, nullptr);
      DcmItem* source = Item(*derivation, DCM_SourceImageSequence, 0);
      ASSERT_NE(source, nullptr);
      EXPECT_EQ(GetString(*source, DCM_ReferencedSOPClassUID),
                enhanced_sop_class);
      EXPECT_EQ(GetString(*source, DCM_ReferencedSOPInstanceUID),
                enhanced->sop_instance_uids[0]);
      EXPECT_EQ(GetString(*source, DCM_ReferencedFrameNumber),
                std::to_string(k + 1));
    }
    DcmItem* series = Item(ds, DCM_ReferencedSeriesSequence, 0);
    ASSERT_NE(series, nullptr);
    EXPECT_EQ(GetString(*series, DCM_SeriesInstanceUID),
              enhanced->series_instance_uid);
  }
}

TEST(EnhancedSeriesTest, SegAndDistanceMapReferenceItsFrames) {
  ExpectSegAndDistanceMapReferenceFrames(LoadCase("ct-thick"),
                                         UID_EnhancedCTImageStorage, 300);
}

// The same for an Enhanced MR (item 2 of issue 25: as for CT).
TEST(EnhancedSeriesTest, SegAndDistanceMapReferenceEnhancedMrFrames) {
  const Case c = LoadCase("multiframe/siemens-xa10-6_1.dcm");
  ASSERT_EQ(c.source.modality, "MR");
  ExpectSegAndDistanceMapReferenceFrames(c, UID_EnhancedMRImageStorage, 100);
}

// UIDs: derived like the classic ones (a rerun replaces), never the classic
// series' own, fresh under random_uids.
TEST(EnhancedSeriesTest, UidsAreDerivedAndDistinctFromTheClassicSeries) {
  const Case c = LoadCase("ct-thick");
  const DicomWriteOptions options = Options();
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], options);
  ASSERT_TRUE(objects.ok());
  auto a = PlanEnhancedIntensity(c.source, objects->intensity, options);
  auto b = PlanEnhancedIntensity(c.source, objects->intensity, options);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->series_instance_uid, b->series_instance_uid);
  EXPECT_EQ(a->sop_instance_uids, b->sop_instance_uids);
  EXPECT_EQ(a->dimension_organization_uid, b->dimension_organization_uid);
  EXPECT_NE(a->series_instance_uid, objects->intensity.series_instance_uid);
  EXPECT_THAT(a->series_instance_uid, ::testing::StartsWith(kTestRoot));
  EXPECT_EQ(a->series_number, objects->intensity.series_number);
  ASSERT_EQ(a->sop_instance_uids.size(), 1u);

  DicomWriteOptions random = options;
  random.random_uids = true;
  auto r1 = PlanDerivedObjects(c.source, c.grid.size[2], random);
  auto r2 = PlanDerivedObjects(c.source, c.grid.size[2], random);
  ASSERT_TRUE(r1.ok() && r2.ok());
  auto e1 = PlanEnhancedIntensity(c.source, r1->intensity, random);
  auto e2 = PlanEnhancedIntensity(c.source, r2->intensity, random);
  ASSERT_TRUE(e1.ok() && e2.ok());
  EXPECT_NE(e1->sop_instance_uids, e2->sop_instance_uids);
}

// Only CT and MR have an enhanced IOD written here: another modality is a
// clear refusal naming it, never a CT or MR object.
TEST(EnhancedSeriesTest, OtherModalityIsRefusedByName) {
  Case c = LoadCase("ct-thick");
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], Options());
  ASSERT_TRUE(objects.ok());
  c.source.modality = "PT";
  auto refused = PlanEnhancedIntensity(c.source, objects->intensity, Options());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(refused.status().message(), HasSubstr("'PT'"));
  EXPECT_THAT(refused.status().message(), HasSubstr("CT and MR"));
  EXPECT_THAT(refused.status().message(), HasSubstr("classic layout"));
  TempDir dir;
  auto ct = PlanEnhancedIntensity(LoadCase("ct-thick").source,
                                  objects->intensity, Options());
  ASSERT_TRUE(ct.ok());
  const absl::Status status = WriteEnhancedIntensity(
      c.source, c.intensity, *ct, Options(), (dir.path() / "x.dcm").string());
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(status.message(), HasSubstr("'PT'"));
  EXPECT_FALSE(fs::exists(dir.path() / "x.dcm"));
}

// An identity planned for a CT source does not write an MR source (nor the
// reverse): the SOP class follows the source's modality.
TEST(EnhancedSeriesTest, IdentityOfTheOtherModalityIsInvalidArgument) {
  const Case ct = LoadCase("ct-thick");
  Case mr = ct;
  mr.source.modality = "MR";
  auto objects = PlanDerivedObjects(ct.source, ct.grid.size[2], Options());
  ASSERT_TRUE(objects.ok());
  auto ct_identity =
      PlanEnhancedIntensity(ct.source, objects->intensity, Options());
  auto mr_identity =
      PlanEnhancedIntensity(mr.source, objects->intensity, Options());
  ASSERT_TRUE(ct_identity.ok() && mr_identity.ok());
  EXPECT_EQ(ct_identity->sop_class_uid, UID_EnhancedCTImageStorage);
  EXPECT_EQ(mr_identity->sop_class_uid, UID_EnhancedMRImageStorage);
  TempDir dir;
  EXPECT_EQ(WriteEnhancedIntensity(mr.source, mr.intensity, *ct_identity,
                                   Options(), (dir.path() / "a.dcm").string())
                .code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WriteEnhancedIntensity(ct.source, ct.intensity, *mr_identity,
                                   Options(), (dir.path() / "b.dcm").string())
                .code(),
            absl::StatusCode::kInvalidArgument);
}

// A classic identity (one UID per slice) is not an enhanced one.
TEST(EnhancedSeriesTest, ClassicIdentityIsInvalidArgument) {
  const Case c = LoadCase("ct-thick");
  auto objects = PlanDerivedObjects(c.source, c.grid.size[2], Options());
  ASSERT_TRUE(objects.ok());
  TempDir dir;
  const absl::Status status =
      WriteEnhancedIntensity(c.source, c.intensity, objects->intensity,
                             Options(), (dir.path() / "x.dcm").string());
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(dir.path() / "x.dcm"));
}

}  // namespace
}  // namespace interslice
