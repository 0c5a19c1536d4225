// WriteDistanceMap: the Parametric Map of the signed distance passes
// dciodvfy, round-trips exactly through DCMTK, sits on the output grid,
// references the intensity series image by image, and rejects bad input.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <memory>
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
#include "dcmtk/dcmfg/fginterface.h"
#include "dcmtk/dcmfg/fgplanpo.h"
#include "dcmtk/dcmpmap/dpmparametricmapiod.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using testing::ExpectValidIod;
using testing::GetString;
using ::testing::HasSubstr;
using testing::LoadDicom;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
constexpr char kCtImageStorage[] = "1.2.840.10008.5.1.4.1.1.2";

class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_pmap_") {}
};

std::string NewUid() {
  auto uid = GenerateDicomUid("");
  EXPECT_TRUE(uid.ok()) << uid.status();
  return uid.ok() ? *uid : std::string();
}

// The real 4-slice CT (5 mm apart), an output grid through part of it (a
// 64x64 in-plane crop, 1 mm slices over the whole 15 mm) and a sphere's
// signed distance on it (radius 9 mm, positive inside), as in
// dicom_writer_test.cc.
class ParametricMapTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
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
          d.at(i, j, k) = static_cast<float>(9.0 - r);
        }
      }
    }
    return d;
  }

  // What PlanDerivedObjects would give, built by hand: the map's identity
  // and the intensity series (one image per output slice) it derives from.
  static DerivedObjectIdentity MapIdentity() {
    DerivedObjectIdentity identity;
    identity.series_instance_uid = NewUid();
    identity.sop_instance_uids = {NewUid()};
    identity.series_number = 201002;
    identity.series_description = "interslice signed distance";
    identity.sop_class_uid = UID_ParametricMapStorage;
    identity.dimension_organization_uid = NewUid();
    return identity;
  }
  static DerivedObjectIdentity IntensityIdentity() {
    DerivedObjectIdentity identity;
    identity.series_instance_uid = NewUid();
    for (int64_t k = 0; k < grid_->size[2]; ++k) {
      identity.sop_instance_uids.push_back(NewUid());
    }
    identity.series_number = 201001;
    identity.series_description = "interslice intensity";
    identity.sop_class_uid = kCtImageStorage;
    return identity;
  }

  static DicomSeries* source_;
  static Grid* grid_;
};

DicomSeries* ParametricMapTest::source_ = nullptr;
Grid* ParametricMapTest::grid_ = nullptr;

double GetDouble(DcmItem& item, const DcmTagKey& tag, unsigned long pos = 0) {
  Float64 value = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(item.findAndGetFloat64(tag, value, pos).good())
      << DcmTag(tag).getTagName();
  return value;
}

// The first item of `sequence` in `item` (fails the test if absent).
DcmItem* Item(DcmItem& item, const DcmTagKey& sequence, long index = 0) {
  DcmItem* found = nullptr;
  EXPECT_TRUE(item.findAndGetSequenceItem(sequence, found, index).good())
      << DcmTag(sequence).getTagName() << " item " << index;
  return found;
}

TEST_F(ParametricMapTest, PassesDciodvfy) {
  TempDir dir;
  const std::string path = (dir.path() / "distance.dcm").string();
  const absl::Status status =
      WriteDistanceMap(*source_, Distance(), MapIdentity(), IntensityIdentity(),
                       DicomWriteOptions(), path);
  ASSERT_TRUE(status.ok()) << status;
  // Fails on any "Error" line, prints the warnings.
  ExpectValidIod({path});
  // Keeps the map for inspection when asked to.
  if (const char* keep = std::getenv("INTERSLICE_KEEP_DICOM_OUT")) {
    fs::create_directories(keep);
    fs::copy_file(path, fs::path(keep) / "distance.dcm",
                  fs::copy_options::overwrite_existing);
  }
}

TEST_F(ParametricMapTest, RoundTripsThroughDcmtk) {
  TempDir dir;
  const std::string path = (dir.path() / "distance.dcm").string();
  const Volume<float> distance = Distance();
  const DerivedObjectIdentity identity = MapIdentity();
  const DerivedObjectIdentity referenced = IntensityIdentity();
  const absl::Status status = WriteDistanceMap(
      *source_, distance, identity, referenced, DicomWriteOptions(), path);
  ASSERT_TRUE(status.ok()) << status;
  const size_t slices = static_cast<size_t>(grid_->size[2]);
  const size_t frame_pixels = static_cast<size_t>(grid_->SliceVoxelCount());

  // Through dcmpmap: frames, exact float pixels, positions.
  OFvariant<OFCondition, DPMParametricMapIOD*> loaded =
      DPMParametricMapIOD::loadFile(path.c_str());
  DPMParametricMapIOD** loaded_map = OFget<DPMParametricMapIOD*>(&loaded);
  ASSERT_NE(loaded_map, nullptr) << OFget<OFCondition>(&loaded)->text();
  std::unique_ptr<DPMParametricMapIOD> map(*loaded_map);
  ASSERT_EQ(map->getNumberOfFrames(), slices);
  Uint16 rows = 0, columns = 0;
  ASSERT_TRUE(map->getRows(rows).good());
  ASSERT_TRUE(map->getColumns(columns).good());
  EXPECT_EQ(rows, grid_->size[1]);
  EXPECT_EQ(columns, grid_->size[0]);
  DPMParametricMapIOD::FramesType frames_variant = map->getFrames();
  auto* frames = OFget<DPMParametricMapIOD::Frames<Float32>>(&frames_variant);
  ASSERT_NE(frames, nullptr) << "pixels are not 32-bit float";
  const Vec3 n = grid_->Axis(2);
  for (size_t k = 0; k < slices; ++k) {
    SCOPED_TRACE(k);
    const Float32* frame = frames->getFrame(k);
    ASSERT_NE(frame, nullptr);
    EXPECT_EQ(std::memcmp(frame, &distance.data[k * frame_pixels],
                          frame_pixels * sizeof(Float32)),
              0)
        << "frame pixels differ from the input";

    auto* position = OFstatic_cast(
        FGPlanePosPatient*,
        map->getFunctionalGroups().get(static_cast<Uint32>(k),
                                       DcmFGTypes::EFG_PLANEPOSPATIENT));
    ASSERT_NE(position, nullptr);
    Float64 x = 0, y = 0, z = 0;
    ASSERT_TRUE(position->getImagePositionPatient(x, y, z).good());
    const double step = static_cast<double>(k) * grid_->spacing[2];
    EXPECT_NEAR(x, grid_->origin[0] + step * n[0], 1e-3);
    EXPECT_NEAR(y, grid_->origin[1] + step * n[1], 1e-3);
    EXPECT_NEAR(z, grid_->origin[2] + step * n[2], 1e-3);
  }

  // Attributes, read with plain dcmdata.
  const std::unique_ptr<DcmFileFormat> file = LoadDicom(path);
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_SOPClassUID), UID_ParametricMapStorage);
  EXPECT_EQ(GetString(ds, DCM_SOPInstanceUID), identity.sop_instance_uids[0]);
  EXPECT_EQ(GetString(*file->getMetaInfo(), DCM_MediaStorageSOPInstanceUID),
            identity.sop_instance_uids[0]);
  EXPECT_EQ(GetString(ds, DCM_SeriesInstanceUID), identity.series_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_SeriesNumber), "201002");
  EXPECT_EQ(GetString(ds, DCM_SeriesDescription), identity.series_description);
  EXPECT_EQ(GetString(ds, DCM_Modality), "CT");
  EXPECT_EQ(GetString(ds, DCM_StudyInstanceUID), source_->study_instance_uid);
  EXPECT_EQ(GetString(ds, DCM_FrameOfReferenceUID),
            source_->frame_of_reference_uid);
  EXPECT_EQ(GetString(ds, DCM_NumberOfFrames), std::to_string(slices));
  EXPECT_EQ(GetString(ds, DCM_BitsAllocated), "32");
  EXPECT_EQ(GetString(ds, DCM_ImageType), "DERIVED\\PRIMARY\\VOLUME\\DISTANCE");
  {
    // Patient and study copied from the source, not invented.
    const std::unique_ptr<DcmFileFormat> source_file =
        LoadDicom(source_->slices[0].path);
    DcmDataset& src = *source_file->getDataset();
    EXPECT_EQ(GetString(ds, DCM_PatientID), GetString(src, DCM_PatientID));
    EXPECT_EQ(GetString(ds, DCM_PatientName), GetString(src, DCM_PatientName));
    EXPECT_EQ(GetString(ds, DCM_StudyDate), GetString(src, DCM_StudyDate));
  }

  // Dimension: ImagePositionPatient in the Plane Position Sequence, under
  // the identity's dimension organization.
  DcmItem* organization = Item(ds, DCM_DimensionOrganizationSequence);
  ASSERT_NE(organization, nullptr);
  EXPECT_EQ(GetString(*organization, DCM_DimensionOrganizationUID),
            identity.dimension_organization_uid);
  DcmItem* dimension = Item(ds, DCM_DimensionIndexSequence);
  ASSERT_NE(dimension, nullptr);
  EXPECT_EQ(GetString(*dimension, DCM_DimensionOrganizationUID),
            identity.dimension_organization_uid);

  // Shared groups: pixel measures, orientation, real world value mapping,
  // identity transformation, window.
  DcmItem* shared = Item(ds, DCM_SharedFunctionalGroupsSequence);
  ASSERT_NE(shared, nullptr);
  DcmItem* measures = Item(*shared, DCM_PixelMeasuresSequence);
  ASSERT_NE(measures, nullptr);
  EXPECT_NEAR(GetDouble(*measures, DCM_PixelSpacing, 0), grid_->spacing[1],
              1e-6);
  EXPECT_NEAR(GetDouble(*measures, DCM_PixelSpacing, 1), grid_->spacing[0],
              1e-6);
  EXPECT_NEAR(GetDouble(*measures, DCM_SliceThickness), grid_->spacing[2],
              1e-6);
  EXPECT_NEAR(GetDouble(*measures, DCM_SpacingBetweenSlices), grid_->spacing[2],
              1e-6);
  DcmItem* orientation = Item(*shared, DCM_PlaneOrientationSequence);
  ASSERT_NE(orientation, nullptr);
  const Vec3 row = grid_->Axis(0), col = grid_->Axis(1);
  for (int c = 0; c < 3; ++c) {
    EXPECT_NEAR(GetDouble(*orientation, DCM_ImageOrientationPatient, c), row[c],
                1e-6);
    EXPECT_NEAR(GetDouble(*orientation, DCM_ImageOrientationPatient, 3 + c),
                col[c], 1e-6);
  }

  DcmItem* rwvm = Item(*shared, DCM_RealWorldValueMappingSequence);
  ASSERT_NE(rwvm, nullptr);
  DcmItem* units = Item(*rwvm, DCM_MeasurementUnitsCodeSequence);
  ASSERT_NE(units, nullptr);
  EXPECT_EQ(GetString(*units, DCM_CodeValue), "mm");
  EXPECT_EQ(GetString(*units, DCM_CodingSchemeDesignator), "UCUM");
  EXPECT_EQ(GetDouble(*rwvm, DCM_RealWorldValueSlope), 1.0);
  EXPECT_EQ(GetDouble(*rwvm, DCM_RealWorldValueIntercept), 0.0);
  const auto [min_it, max_it] =
      std::minmax_element(distance.data.begin(), distance.data.end());
  EXPECT_EQ(GetDouble(*rwvm, DCM_DoubleFloatRealWorldValueFirstValueMapped),
            static_cast<double>(*min_it));
  EXPECT_EQ(GetDouble(*rwvm, DCM_DoubleFloatRealWorldValueLastValueMapped),
            static_cast<double>(*max_it));
  EXPECT_FALSE(ds.tagExistsWithValue(DCM_RealWorldValueFirstValueMapped,
                                     /*searchIntoSub=*/OFTrue));
  EXPECT_THAT(GetString(*rwvm, DCM_LUTExplanation),
              HasSubstr("positive inside"));
  DcmItem* quantity = Item(*rwvm, DCM_QuantityDefinitionSequence);
  ASSERT_NE(quantity, nullptr);
  DcmItem* concept_code = Item(*quantity, DCM_ConceptCodeSequence);
  ASSERT_NE(concept_code, nullptr);
  EXPECT_EQ(GetString(*concept_code, DCM_CodeMeaning), "Distance");

  DcmItem* transform = Item(*shared, DCM_PixelValueTransformationSequence);
  ASSERT_NE(transform, nullptr);
  EXPECT_EQ(GetDouble(*transform, DCM_RescaleSlope), 1.0);
  EXPECT_EQ(GetDouble(*transform, DCM_RescaleIntercept), 0.0);
  DcmItem* voi = Item(*shared, DCM_FrameVOILUTSequence);
  ASSERT_NE(voi, nullptr);
  EXPECT_EQ(GetDouble(*voi, DCM_WindowCenter), 0.0);
  // max |d| is well above 10 mm here, so the width is clamped to 20 mm.
  EXPECT_EQ(GetDouble(*voi, DCM_WindowWidth), 20.0);
  DcmItem* anatomy = Item(*shared, DCM_FrameAnatomySequence);
  ASSERT_NE(anatomy, nullptr);
  DcmItem* region = Item(*anatomy, DCM_AnatomicRegionSequence);
  ASSERT_NE(region, nullptr);
  // The source's BodyPartExamined is BRAIN (PS3.16 Annex L).
  EXPECT_EQ(GetString(*region, DCM_CodeValue), "12738006");

  // Per frame: frame content index k + 1 and the derivation from image k of
  // the intensity series.
  DcmSequenceOfItems* per_frame = nullptr;
  ASSERT_TRUE(
      ds.findAndGetSequence(DCM_PerFrameFunctionalGroupsSequence, per_frame)
          .good());
  ASSERT_EQ(per_frame->card(), slices);
  for (size_t k = 0; k < slices; ++k) {
    SCOPED_TRACE(k);
    DcmItem* frame = per_frame->getItem(static_cast<unsigned long>(k));
    DcmItem* content = Item(*frame, DCM_FrameContentSequence);
    ASSERT_NE(content, nullptr);
    Uint32 index = 0;
    ASSERT_TRUE(
        content->findAndGetUint32(DCM_DimensionIndexValues, index).good());
    EXPECT_EQ(index, k + 1);
    DcmItem* derivation = Item(*frame, DCM_DerivationImageSequence);
    ASSERT_NE(derivation, nullptr);
    DcmSequenceOfItems* sources = nullptr;
    ASSERT_TRUE(derivation->findAndGetSequence(DCM_SourceImageSequence, sources)
                    .good());
    ASSERT_EQ(sources->card(), 1u);
    DcmItem* image = sources->getItem(0);
    EXPECT_EQ(GetString(*image, DCM_ReferencedSOPInstanceUID),
              referenced.sop_instance_uids[k]);
    EXPECT_EQ(GetString(*image, DCM_ReferencedSOPClassUID), kCtImageStorage);
  }

  // Common Instance Reference: every image of the intensity series.
  DcmItem* series = Item(ds, DCM_ReferencedSeriesSequence);
  ASSERT_NE(series, nullptr);
  EXPECT_EQ(GetString(*series, DCM_SeriesInstanceUID),
            referenced.series_instance_uid);
  DcmSequenceOfItems* instances = nullptr;
  ASSERT_TRUE(
      series->findAndGetSequence(DCM_ReferencedInstanceSequence, instances)
          .good());
  ASSERT_EQ(instances->card(), slices);
  for (size_t k = 0; k < slices; ++k) {
    EXPECT_EQ(GetString(*instances->getItem(static_cast<unsigned long>(k)),
                        DCM_ReferencedSOPInstanceUID),
              referenced.sop_instance_uids[k]);
  }
}

TEST_F(ParametricMapTest, ModalityAndWindowFollowTheInput) {
  TempDir dir;
  const std::string path = (dir.path() / "distance.dcm").string();
  DicomSeries mr = *source_;
  mr.modality = "MR";
  // A thin shell: max |d| = 0.25 mm, so the window is clamped to 1 mm.
  Volume<float> distance = Distance();
  for (float& d : distance.data) d = std::clamp(d, -0.25f, 0.125f);
  ASSERT_TRUE(WriteDistanceMap(mr, distance, MapIdentity(), IntensityIdentity(),
                               DicomWriteOptions(), path)
                  .ok());
  const std::unique_ptr<DcmFileFormat> file = LoadDicom(path);
  DcmDataset& ds = *file->getDataset();
  EXPECT_EQ(GetString(ds, DCM_Modality), "MR");
  DcmItem* shared = Item(ds, DCM_SharedFunctionalGroupsSequence);
  ASSERT_NE(shared, nullptr);
  DcmItem* voi = Item(*shared, DCM_FrameVOILUTSequence);
  ASSERT_NE(voi, nullptr);
  EXPECT_EQ(GetDouble(*voi, DCM_WindowWidth), 1.0);
  DcmItem* rwvm = Item(*shared, DCM_RealWorldValueMappingSequence);
  ASSERT_NE(rwvm, nullptr);
  EXPECT_EQ(GetDouble(*rwvm, DCM_DoubleFloatRealWorldValueFirstValueMapped),
            -0.25);
  EXPECT_EQ(GetDouble(*rwvm, DCM_DoubleFloatRealWorldValueLastValueMapped),
            0.125);
}

TEST_F(ParametricMapTest, BadInputIsInvalidArgumentAndWritesNothing) {
  TempDir dir;
  const std::string path = (dir.path() / "distance.dcm").string();
  const DerivedObjectIdentity identity = MapIdentity();
  const DerivedObjectIdentity referenced = IntensityIdentity();
  const auto write = [&](const Volume<float>& values,
                         const DerivedObjectIdentity& map_identity,
                         const DerivedObjectIdentity& images) {
    return WriteDistanceMap(*source_, values, map_identity, images,
                            DicomWriteOptions(), path)
        .code();
  };

  Volume<float> nan = Distance();
  nan.data[5] = std::nanf("");
  EXPECT_EQ(write(nan, identity, referenced),
            absl::StatusCode::kInvalidArgument);
  Volume<float> inf = Distance();
  inf.data.back() = -std::numeric_limits<float>::infinity();
  EXPECT_EQ(write(inf, identity, referenced),
            absl::StatusCode::kInvalidArgument);

  DerivedObjectIdentity short_referenced = referenced;
  short_referenced.sop_instance_uids.pop_back();
  EXPECT_EQ(write(Distance(), identity, short_referenced),
            absl::StatusCode::kInvalidArgument);
  DerivedObjectIdentity long_referenced = referenced;
  long_referenced.sop_instance_uids.push_back(NewUid());
  EXPECT_EQ(write(Distance(), identity, long_referenced),
            absl::StatusCode::kInvalidArgument);

  Volume<float> rotated = Distance();
  rotated.grid.direction = {0, 1, 0, 1, 0, 0, 0, 0, -1};
  EXPECT_EQ(write(rotated, identity, referenced),
            absl::StatusCode::kInvalidArgument);
  Volume<float> short_values = Distance();
  short_values.data.pop_back();
  EXPECT_EQ(write(short_values, identity, referenced),
            absl::StatusCode::kInvalidArgument);

  DerivedObjectIdentity two_instances = identity;
  two_instances.sop_instance_uids.push_back(NewUid());
  EXPECT_EQ(write(Distance(), two_instances, referenced),
            absl::StatusCode::kInvalidArgument);
  DerivedObjectIdentity wrong_class = identity;
  wrong_class.sop_class_uid = kCtImageStorage;
  EXPECT_EQ(write(Distance(), wrong_class, referenced),
            absl::StatusCode::kInvalidArgument);

  EXPECT_TRUE(fs::is_empty(dir.path()));
}

TEST_F(ParametricMapTest, UnwritablePathIsInternalAndLeavesNoTemporary) {
  TempDir dir;
  const fs::path blocker = dir.path() / "a_file";
  std::ofstream(blocker) << "x";
  const absl::Status status = WriteDistanceMap(
      *source_, Distance(), MapIdentity(), IntensityIdentity(),
      DicomWriteOptions(), (blocker / "distance.dcm").string());
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(status.message(), HasSubstr("distance.dcm"));
  EXPECT_EQ(std::distance(fs::directory_iterator(dir.path()),
                          fs::directory_iterator()),
            1);
}

}  // namespace
}  // namespace interslice
