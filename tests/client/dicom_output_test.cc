// End-to-end tests of the DICOM objects `interslice run` writes, on series a
// hospital sends: the shipped phantom, the phantom with uneven gaps and with
// a missing slice (made here from the shipped files with DCMTK), and a
// tilted head CT. Real processes; consumers other than our own reader (ITK's
// GDCM series reader, dciodvfy) check what a viewer or PACS would see.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include "absl/strings/str_format.h"
#include "core/dicom/series_reader.h"
#include "core/pipeline/pipeline.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "itkGDCMImageIO.h"
#include "itkGDCMSeriesFileNames.h"
#include "itkImage.h"
#include "itkImageFileReader.h"
#include "itkImageSeriesReader.h"
#include "nlohmann/json.hpp"
#include "tests/testing/cli.h"
#include "tests/testing/dciodvfy.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;

using testing::CommandResult;
using testing::RunCli;

const fs::path kPhantom =
    fs::path(::interslice::testing::SourceDir()) / "data/ct-head-phantom-thick";
const fs::path kTilt =
    fs::path(::interslice::testing::TestDataDir()) / "ct-tilt";
// A Siemens XA10 Enhanced MR (6 frames, one volume).
const fs::path kEnhancedMr = fs::path(::interslice::testing::TestDataDir()) /
                             "multiframe" / "siemens-xa10-6_1.dcm";

class DicomOutputTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice_dicom_output_test_" + std::to_string(getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
};

std::vector<fs::path> SortedFiles(const fs::path& folder) {
  std::vector<fs::path> files;
  for (const auto& entry : fs::directory_iterator(folder)) {
    files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

// dciodvfy's problems with one file (tests/testing/dciodvfy.h: its error
// lines, and a non-zero exit status), appended to `errors`.
int DciodvfyErrors(const fs::path& file, std::string* errors) {
  return testing::DciodvfyErrors({file.string()}, errors);
}

std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  item.findAndGetOFStringArray(tag, value);
  return std::string(value.c_str());
}

nlohmann::json ReadJson(const fs::path& path) {
  std::ifstream in(path);
  return nlohmann::json::parse(in);
}

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

// Copies `slices` (indices into the sorted source files) of `source` to
// `to`, moving slice i to `positions[i]` mm along the normal from the first
// one's original position: the anatomy of each file stays its own, only
// where it lies changes, as in a series with uneven gaps.
void MakeSeries(const fs::path& source, const std::vector<int>& slices,
                const std::vector<double>& positions, const fs::path& to) {
  fs::create_directories(to);
  const std::vector<fs::path> files = SortedFiles(source);
  auto series = ReadDicomSeries({source.string()}, {}, {});
  ASSERT_TRUE(series.ok()) << series.status();
  const Vec3 n = series->image.grid.Axis(2);
  const Vec3 base = series->slices[slices.front()].image_position;
  for (size_t i = 0; i < slices.size(); ++i) {
    const DicomSliceInfo& info = series->slices[slices[i]];
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile(OFFilename(info.path.c_str())).good());
    ASSERT_TRUE(file.loadAllDataIntoMemory().good());
    char ipp[200];
    std::snprintf(ipp, sizeof(ipp), "%.6f\\%.6f\\%.6f",
                  base[0] + positions[i] * n[0], base[1] + positions[i] * n[1],
                  base[2] + positions[i] * n[2]);
    file.getDataset()->putAndInsertString(DCM_ImagePositionPatient, ipp);
    // Scanners write SliceLocation too; keep it consistent.
    file.getDataset()->putAndInsertString(
        DCM_SliceLocation, std::to_string(Dot(base, n) + positions[i]).c_str());
    const fs::path out = to / ("S" + std::to_string(1000 + i) + ".dcm");
    ASSERT_TRUE(file.saveFile(OFFilename(out.c_str())).good());
  }
}

// The intensity series against the source: at the output slice nearest each
// source slice, the values equal the source's linearly interpolated at that
// slice's position (at most half an output spacing from the source slice),
// within the 1 HU storage step; the first and last output slices hold the
// anatomy of the first and last source slices.
// (x0, y0): the region of interest's first column and row in the source.
void ExpectIntensityPlacedByTruePositions(const fs::path& source_dir,
                                          const fs::path& intensity_dir,
                                          const nlohmann::json& report,
                                          int64_t x0 = 0, int64_t y0 = 0) {
  auto source = ReadDicomSeries({source_dir.string()}, {}, {});
  ASSERT_TRUE(source.ok()) << source.status();
  auto out = ReadDicomSeries({intensity_dir.string()}, {}, {});
  ASSERT_TRUE(out.ok()) << out.status();
  const Grid& g = out->image.grid;
  // The intensity series lies on the report's grid.
  for (int a = 0; a < 3; ++a) {
    EXPECT_EQ(g.size[a], report["grid"]["size"][a].get<int64_t>());
    EXPECT_NEAR(g.spacing[a], report["grid"]["spacing"][a].get<double>(), 1e-4);
    EXPECT_NEAR(g.origin[a], report["grid"]["origin"][a].get<double>(), 1e-3);
  }
  const int64_t plane = g.size[0] * g.size[1];
  const int64_t source_plane =
      source->image.grid.size[0] * source->image.grid.size[1];
  // Index of output pixel i within a source slice.
  auto at = [&](int64_t i) {
    return (y0 + i / g.size[0]) * source->image.grid.size[0] + x0 +
           i % g.size[0];
  };
  const auto& q = source->slices;
  double worst = 0;
  for (size_t s = 0; s < q.size(); ++s) {
    // The output slice nearest source slice s.
    int64_t k = 0;
    for (int64_t j = 1; j < g.size[2]; ++j) {
      if (std::abs(out->slices[j].position_along_normal -
                   q[s].position_along_normal) <
          std::abs(out->slices[k].position_along_normal -
                   q[s].position_along_normal)) {
        k = j;
      }
    }
    const double p = out->slices[k].position_along_normal;
    ASSERT_LE(std::abs(p - q[s].position_along_normal),
              0.5 * g.spacing[2] + 1e-3)
        << "source slice " << s;
    // Bracketing source slices of p and the weight.
    size_t a = s, b = s;
    if (p < q[s].position_along_normal - 1e-4 && s > 0) a = s - 1;
    if (p > q[s].position_along_normal + 1e-4 && s + 1 < q.size()) b = s + 1;
    const double t =
        a == b ? 0
               : (p - q[a].position_along_normal) /
                     (q[b].position_along_normal - q[a].position_along_normal);
    for (int64_t i = 0; i < plane; i += 37) {
      const double expected =
          (1 - t) * source->image.data[a * source_plane + at(i)] +
          t * source->image.data[b * source_plane + at(i)];
      worst =
          std::max(worst, std::abs(out->image.data[k * plane + i] - expected));
    }
  }
  EXPECT_LE(worst, 0.5 + 1e-3) << "HU off where the source slices are";
  // Top and bottom: the output spans the source, its first slice on the
  // first source slice and its last within half a spacing of the last; the
  // anatomy there is the source's (not padding, not another slice's: a few
  // HU of blending with the neighbour at most).
  EXPECT_NEAR(out->slices.front().position_along_normal,
              q.front().position_along_normal, 1e-3);
  EXPECT_LE(std::abs(out->slices.back().position_along_normal -
                     q.back().position_along_normal),
            0.5 * g.spacing[2] + 1e-3);
  for (const auto& [source_slice, out_slice] :
       {std::pair<int64_t, int64_t>{0, 0},
        {static_cast<int64_t>(q.size()) - 1, g.size[2] - 1}}) {
    double difference = 0;
    for (int64_t i = 0; i < plane; ++i) {
      difference +=
          std::abs(out->image.data[out_slice * plane + i] -
                   source->image.data[source_slice * source_plane + at(i)]);
    }
    EXPECT_LE(difference / plane, 5.0)
        << "output slice " << out_slice << " vs source slice " << source_slice;
  }
}

// ITK's GDCM series reader (what ITK-based tools and many pipelines use)
// sees the grid of the report.
void ExpectItkSeesReportGrid(const fs::path& intensity_dir,
                             const nlohmann::json& report) {
  using Image = itk::Image<float, 3>;
  auto names = itk::GDCMSeriesFileNames::New();
  names->SetDirectory(intensity_dir.string());
  const std::vector<std::string> files = names->GetInputFileNames();
  auto reader = itk::ImageSeriesReader<Image>::New();
  reader->SetImageIO(itk::GDCMImageIO::New());
  reader->SetFileNames(files);
  ASSERT_NO_THROW(reader->Update());
  const Image* image = reader->GetOutput();
  const auto size = image->GetLargestPossibleRegion().GetSize();
  for (int a = 0; a < 3; ++a) {
    EXPECT_EQ(static_cast<int64_t>(size[a]),
              report["grid"]["size"][a].get<int64_t>());
    EXPECT_NEAR(image->GetSpacing()[a],
                report["grid"]["spacing"][a].get<double>(), 1e-4);
    EXPECT_NEAR(image->GetOrigin()[a],
                report["grid"]["origin"][a].get<double>(), 1e-3);
    for (int c = 0; c < 3; ++c) {
      // ITK's direction matrix has the index axes as columns, as ours.
      EXPECT_NEAR(image->GetDirection()(a, c),
                  report["grid"]["direction"][3 * a + c].get<double>(), 1e-5);
    }
  }
}

// The shipped phantom (a 100 x 100 region to keep it quick): intensity
// series, distance map and SEG pass dciodvfy and are placed on the report's
// grid by our reader and by ITK/GDCM; the distance map holds the field.
TEST_F(DicomOutputTest, ShippedPhantomObjectsValidateAndLieOnTheReportGrid) {
  const fs::path out = dir_ / "out";
  const fs::path report_path = dir_ / "report.json";
  const CommandResult r = RunCli(
      "run " + kPhantom.string() +
      " --threshold 300 --roi 200,60,0,300,160,28 --method direct --quiet "
      "--volume nrrd --mesh none --output-series intensity,distance --seg "
      "--out " +
      out.string() + " --report " + report_path.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const nlohmann::json report = ReadJson(report_path);
  EXPECT_FALSE(fs::exists(out / "series-mask"));
  EXPECT_FALSE(fs::exists(out / "series-distance"));

  const std::vector<fs::path> files = SortedFiles(out / "series-intensity");
  ASSERT_EQ(files.size(), 298u);
  std::string errors;
  int count = 0;
  for (const fs::path& f :
       {files.front(), files[files.size() / 2], files.back(), out / "seg.dcm",
        out / "distance.dcm"}) {
    count += DciodvfyErrors(f, &errors);
  }
  EXPECT_EQ(count, 0) << errors;

  ExpectIntensityPlacedByTruePositions(kPhantom, out / "series-intensity",
                                       report, 200, 60);
  ExpectItkSeesReportGrid(out / "series-intensity", report);

  // The distance map's frames are the field (float32, bit for bit).
  const auto distance = ReadVolumeAsFloat((out / "distance.nrrd").string());
  ASSERT_TRUE(distance.ok()) << distance.status();
  DcmFileFormat pmap;
  ASSERT_TRUE(pmap.loadFile(OFFilename((out / "distance.dcm").c_str())).good());
  const Float32* floats = nullptr;
  unsigned long count_floats = 0;
  ASSERT_TRUE(
      pmap.getDataset()
          ->findAndGetFloat32Array(DCM_FloatPixelData, floats, &count_floats)
          .good());
  ASSERT_EQ(count_floats, distance->data.size());
  EXPECT_TRUE(std::equal(distance->data.begin(), distance->data.end(), floats));

  // Series numbers from the source's (201 x 1000, + 10 x the parameter
  // set's slot, + the object; the intensity series in the slot of what
  // shapes it alone) and descriptions that say what each object holds,
  // with which parameters and from which series (docs/dicom-output.md).
  DcmFileFormat first;
  ASSERT_TRUE(first.loadFile(OFFilename(files.front().c_str())).good());
  const int intensity_number =
      std::stoi(GetString(*first.getDataset(), DCM_SeriesNumber));
  EXPECT_EQ(intensity_number / 1000, 201);
  EXPECT_EQ(intensity_number % 10, 1);
  const int distance_number =
      std::stoi(GetString(*pmap.getDataset(), DCM_SeriesNumber));
  EXPECT_EQ(distance_number / 1000, 201);
  EXPECT_EQ(distance_number % 10, 2);
  EXPECT_EQ(
      GetString(*pmap.getDataset(), DCM_SeriesDescription),
      ("Distance (mm) >=300 HU, " +
       absl::StrFormat("%.3g", report["grid"]["spacing"][2].get<double>()) +
       " mm, smooth, from #201 STD BRAIN 5MM")
          .substr(0, 64));
  DcmFileFormat seg;
  ASSERT_TRUE(seg.loadFile(OFFilename((out / "seg.dcm").c_str())).good());
  EXPECT_EQ(GetString(*seg.getDataset(), DCM_SeriesNumber),
            std::to_string(distance_number + 1));
  EXPECT_EQ(GetString(*seg.getDataset(), DCM_SOPClassUID),
            "1.2.840.10008.5.1.4.1.1.66.4");
  EXPECT_EQ(GetString(*pmap.getDataset(), DCM_SOPClassUID),
            "1.2.840.10008.5.1.4.1.1.30");
}

// Gaps of 4.2 / 1.1 / 7.4 / ... mm (the defect: the intensity used the median
// gap and squeezed the anatomy), and a regular series with a missing slice.
TEST_F(DicomOutputTest, UnevenGapsAndMissingSlicesArePlacedByTruePositions) {
  struct Case {
    const char* name;
    std::vector<int> slices;
    std::vector<double> positions;
  };
  const Case cases[] = {
      {"uneven",
       {8, 9, 10, 11, 12, 13, 14, 15},
       {0, 4.2, 5.3, 12.7, 17.7, 20.7, 26.9, 31.9}},
      {"missing", {8, 9, 10, 12, 13, 14, 15}, {0, 5, 10, 20, 25, 30, 35}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    const fs::path source = dir_ / c.name / "source";
    MakeSeries(kPhantom, c.slices, c.positions, source);
    const fs::path out = dir_ / c.name / "out";
    const fs::path report_path = dir_ / c.name / "report.json";
    const CommandResult r = RunCli(
        "run " + source.string() + " --threshold 300 --roi 150,100,0,350,300," +
        std::to_string(c.slices.size()) +
        " --method direct --quiet --volume none --mesh none --seg "
        "--intensity-method linear --out " +
        out.string() + " --report " + report_path.string());
    ASSERT_EQ(r.exit_code, 0) << r.out;
    const nlohmann::json report = ReadJson(report_path);
    // The placement is checked against the linear blend's formula below (the
    // morph's own placement on uneven gaps: tests/core/morph).
    EXPECT_EQ(report["intensity"]["method"], "linear");
    double max_gap = 0;
    for (size_t i = 1; i < c.positions.size(); ++i) {
      max_gap = std::max(max_gap, c.positions[i] - c.positions[i - 1]);
    }
    EXPECT_NEAR(report["input"]["max_gap_mm"].get<double>(), max_gap, 1e-3);
    ExpectIntensityPlacedByTruePositions(source, out / "series-intensity",
                                         report, 150, 100);
    ExpectItkSeesReportGrid(out / "series-intensity", report);
    std::string errors;
    EXPECT_EQ(DciodvfyErrors(out / "seg.dcm", &errors), 0) << errors;
  }
}

// --intensity-method: the morph (default) and the linear blend keep the
// source slices bit for bit and differ between them; each is named in the
// report, the objects validate, and the two get different UIDs.
TEST_F(DicomOutputTest, IntensityMethodKeepsSourceSlicesAndSaysWhichItUsed) {
  std::map<std::string, DicomSeries> series;
  for (const std::string method : {"", "linear", "morph"}) {
    const std::string name = method.empty() ? "default" : method;
    const fs::path out = dir_ / ("intensity-" + name);
    const fs::path report_path = dir_ / ("intensity-" + name + ".json");
    const CommandResult r = RunCli(
        "run " + kPhantom.string() +
        " --threshold 300 --roi 150,100,0,350,300,6 --method direct --quiet "
        "--volume none --mesh none --output-series intensity " +
        (method.empty() ? "" : "--intensity-method " + method + " ") +
        "--out " + out.string() + " --report " + report_path.string());
    ASSERT_EQ(r.exit_code, 0) << r.out;
    const nlohmann::json report = ReadJson(report_path);
    EXPECT_EQ(report["intensity"]["method"], method.empty() ? "morph" : method);
    auto read = ReadDicomSeries({(out / "series-intensity").string()}, {}, {});
    ASSERT_TRUE(read.ok()) << read.status();
    std::string errors;
    EXPECT_EQ(DciodvfyErrors(out / "series-intensity" / "IM00002.dcm", &errors),
              0)
        << errors;
    series.emplace(name, *std::move(read));
  }
  auto source = ReadDicomSeries({kPhantom.string()}, {}, {});
  ASSERT_TRUE(source.ok()) << source.status();
  const DicomSeries& linear = series["linear"];
  const DicomSeries& morph = series["morph"];
  EXPECT_TRUE(series["default"].image.data == morph.image.data);
  EXPECT_EQ(series["default"].series_instance_uid, morph.series_instance_uid);
  EXPECT_NE(linear.series_instance_uid, morph.series_instance_uid);
  ASSERT_EQ(linear.image.grid.size, morph.image.grid.size);
  const int64_t plane = linear.image.grid.size[0] * linear.image.grid.size[1];
  int64_t differing_planes = 0, source_planes = 0;
  for (int64_t k = 0; k < linear.image.grid.size[2]; ++k) {
    const bool same = std::equal(linear.image.data.begin() + k * plane,
                                 linear.image.data.begin() + (k + 1) * plane,
                                 morph.image.data.begin() + k * plane);
    // A slice at a source slice's position is that slice in both.
    bool on_source = false;
    for (const DicomSliceInfo& s : source->slices) {
      on_source =
          on_source || std::abs(s.position_along_normal -
                                linear.slices[k].position_along_normal) < 1e-3;
    }
    if (on_source) {
      ++source_planes;
      EXPECT_TRUE(same) << "source slice at output slice " << k;
    } else if (!same) {
      ++differing_planes;
    }
  }
  EXPECT_EQ(source_planes, 6);
  EXPECT_GT(differing_planes, 0);
  const CommandResult bad = RunCli("run " + kPhantom.string() +
                                   " --threshold 300 --intensity-method cubic "
                                   "--out " +
                                   (dir_ / "bad").string());
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_THAT(bad.out, HasSubstr("--intensity-method: unknown value 'cubic'"));
}

// --dicom-compression rle: the intensity series is RLE Lossless and reads
// (our reader, ITK/GDCM) exactly as the native one; a bad value is a
// one-line error.
TEST_F(DicomOutputTest, RleIntensitySeriesReadsAsTheNativeOne) {
  const std::string common =
      "run " + kPhantom.string() +
      " --threshold 300 --roi 150,100,0,350,300,6 --factor 3 --method direct "
      "--quiet --volume none --mesh none --output-series intensity ";
  for (const char* mode : {"none", "rle"}) {
    const CommandResult r =
        RunCli(common + "--dicom-compression " + mode + " --out " +
               (dir_ / mode).string() + " --report " +
               (dir_ / (std::string(mode) + ".json")).string());
    ASSERT_EQ(r.exit_code, 0) << r.out;
  }
  const fs::path rle = dir_ / "rle" / "series-intensity";
  const std::vector<fs::path> files = SortedFiles(rle);
  ASSERT_EQ(files.size(), 16u);
  for (const fs::path& file : files) {
    DcmFileFormat ff;
    ASSERT_TRUE(ff.loadFile(OFFilename(file.c_str())).good()) << file;
    OFString xfer;
    ff.getMetaInfo()->findAndGetOFString(DCM_TransferSyntaxUID, xfer);
    EXPECT_EQ(xfer, UID_RLELosslessTransferSyntax) << file;
  }
  std::string errors;
  EXPECT_EQ(DciodvfyErrors(files.front(), &errors), 0) << errors;
  auto native = ReadDicomSeries({(dir_ / "none").string()}, {}, {});
  auto compressed = ReadDicomSeries({rle.string()}, {}, {});
  ASSERT_TRUE(native.ok()) << native.status();
  ASSERT_TRUE(compressed.ok()) << compressed.status();
  EXPECT_EQ(compressed->image.data, native->image.data);
  ExpectItkSeesReportGrid(rle, ReadJson(dir_ / "rle.json"));

  const CommandResult bad = RunCli(common + "--dicom-compression jpeg --out " +
                                   (dir_ / "x").string());
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_THAT(bad.out, HasSubstr("--dicom-compression"));
}

// ITK's GDCM reader on the one Enhanced CT file (GDCM takes the geometry
// from its functional groups) sees the grid of the report.
void ExpectItkSeesReportGridInOneFile(const fs::path& file,
                                      const nlohmann::json& report) {
  using Image = itk::Image<float, 3>;
  auto reader = itk::ImageFileReader<Image>::New();
  reader->SetImageIO(itk::GDCMImageIO::New());
  reader->SetFileName(file.string());
  ASSERT_NO_THROW(reader->Update());
  const Image* image = reader->GetOutput();
  const auto size = image->GetLargestPossibleRegion().GetSize();
  for (int a = 0; a < 3; ++a) {
    EXPECT_EQ(static_cast<int64_t>(size[a]),
              report["grid"]["size"][a].get<int64_t>());
    EXPECT_NEAR(image->GetSpacing()[a],
                report["grid"]["spacing"][a].get<double>(), 1e-4);
    EXPECT_NEAR(image->GetOrigin()[a],
                report["grid"]["origin"][a].get<double>(), 1e-3);
    for (int c = 0; c < 3; ++c) {
      EXPECT_NEAR(image->GetDirection()(a, c),
                  report["grid"]["direction"][3 * a + c].get<double>(), 1e-5);
    }
  }
}

// --dicom-layout enhanced: the intensity series is one Enhanced CT (CT
// sources) or Enhanced MR (MR sources) file that our reader and ITK/GDCM
// read as the classic series' volume (the phantom, the tilted CT and a
// Siemens enhanced MR), valid for dciodvfy with the SEG and the distance map
// that reference it; a bad value is a one-line error.
TEST_F(DicomOutputTest, EnhancedLayoutIsTheClassicVolume) {
  struct Source {
    std::string name;
    fs::path dir;
    std::string args;
    const char* sop_class;
  };
  for (const Source& source : std::vector<Source>{
           {"phantom", kPhantom,
            "--threshold 300 --roi 150,100,0,350,300,6 --factor 3",
            UID_EnhancedCTImageStorage},
           {"tilt", kTilt, "--threshold 300 --factor 2",
            UID_EnhancedCTImageStorage},
           {"mr", kEnhancedMr, "--threshold 100 --factor 2",
            UID_EnhancedMRImageStorage}}) {
    SCOPED_TRACE(source.name);
    const std::string common =
        "run " + source.dir.string() + " " + source.args +
        " --method direct --quiet --volume none --mesh none --previews none "
        "--output-series intensity,mask,distance ";
    for (const char* layout : {"classic", "enhanced"}) {
      const std::string name = source.name + "-" + layout;
      const CommandResult r =
          RunCli(common + "--dicom-layout " + layout + " --out " +
                 (dir_ / name).string() + " --report " +
                 (dir_ / (name + ".json")).string());
      ASSERT_EQ(r.exit_code, 0) << r.out;
    }
    const fs::path classic = dir_ / (source.name + "-classic");
    const fs::path enhanced = dir_ / (source.name + "-enhanced");
    const std::vector<fs::path> files =
        SortedFiles(enhanced / "series-intensity");
    ASSERT_EQ(files.size(), 1u);
    EXPECT_EQ(files[0].filename(), "enhanced.dcm");
    const nlohmann::json report =
        ReadJson(dir_ / (source.name + "-enhanced.json"));
    EXPECT_EQ(report["grid"],
              ReadJson(dir_ / (source.name + "-classic.json"))["grid"]);
    for (const fs::path& object :
         {files[0], enhanced / "seg.dcm", enhanced / "distance.dcm"}) {
      std::string errors;
      EXPECT_EQ(DciodvfyErrors(object, &errors), 0)
          << object.filename() << ": " << errors;
    }
    auto from_classic =
        ReadDicomSeries({(classic / "series-intensity").string()}, {}, {});
    auto from_enhanced =
        ReadDicomSeries({(enhanced / "series-intensity").string()}, {}, {});
    ASSERT_TRUE(from_classic.ok()) << from_classic.status();
    ASSERT_TRUE(from_enhanced.ok()) << from_enhanced.status();
    EXPECT_EQ(from_enhanced->sop_class_uid, source.sop_class);
    const Grid& a = from_classic->image.grid;
    const Grid& b = from_enhanced->image.grid;
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(a.size[c], b.size[c]);
      EXPECT_NEAR(a.spacing[c], b.spacing[c], 1e-6);
      EXPECT_NEAR(a.origin[c], b.origin[c], 1e-6);
    }
    for (int i = 0; i < 9; ++i)
      EXPECT_NEAR(a.direction[i], b.direction[i], 1e-9);
    EXPECT_EQ(from_enhanced->image.data, from_classic->image.data);
    ExpectItkSeesReportGridInOneFile(files[0], report);

    // The SEG names the enhanced series and frame k + 1 of its instance.
    DcmFileFormat seg;
    ASSERT_TRUE(
        seg.loadFile(OFFilename((enhanced / "seg.dcm").c_str())).good());
    DcmItem* series = nullptr;
    ASSERT_TRUE(
        seg.getDataset()
            ->findAndGetSequenceItem(DCM_ReferencedSeriesSequence, series, 0)
            .good());
    DcmFileFormat image;
    ASSERT_TRUE(image.loadFile(OFFilename(files[0].c_str())).good());
    EXPECT_EQ(GetString(*series, DCM_SeriesInstanceUID),
              GetString(*image.getDataset(), DCM_SeriesInstanceUID));
    DcmItem* frame = nullptr;
    DcmItem* derivation = nullptr;
    DcmItem* source_image = nullptr;
    ASSERT_TRUE(seg.getDataset()
                    ->findAndGetSequenceItem(
                        DCM_PerFrameFunctionalGroupsSequence, frame, 2)
                    .good());
    ASSERT_TRUE(
        frame
            ->findAndGetSequenceItem(DCM_DerivationImageSequence, derivation, 0)
            .good());
    ASSERT_TRUE(
        derivation
            ->findAndGetSequenceItem(DCM_SourceImageSequence, source_image, 0)
            .good());
    EXPECT_EQ(GetString(*source_image, DCM_ReferencedSOPInstanceUID),
              GetString(*image.getDataset(), DCM_SOPInstanceUID));
    EXPECT_EQ(GetString(*source_image, DCM_ReferencedFrameNumber), "3");
  }
  const CommandResult bad = RunCli(
      "run " + kTilt.string() +
      " --threshold 300 --dicom-layout stacked --out " + (dir_ / "x").string());
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_THAT(bad.out, HasSubstr("--dicom-layout"));
}

// A tilted head CT: the tilt is corrected, reported and summarised, and the
// intensity series equals the tilt-resampled source on its slices.
TEST_F(DicomOutputTest, TiltedSeriesIsCorrectedAndReported) {
  const fs::path out = dir_ / "out";
  const fs::path report_path = dir_ / "report.json";
  const CommandResult r =
      RunCli("run " + kTilt.string() +
             " --threshold 300 --method direct --volume none --mesh none "
             "--output-series intensity --out " +
             out.string() + " --report " + report_path.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  EXPECT_THAT(r.out, HasSubstr("gantry tilt of 18.5 degrees"));
  const nlohmann::json report = ReadJson(report_path);
  EXPECT_NEAR(std::abs(report["input"]["gantry_tilt_degrees"].get<double>()),
              18.5, 0.1);
  ExpectIntensityPlacedByTruePositions(kTilt, out / "series-intensity", report);
  ExpectItkSeesReportGrid(out / "series-intensity", report);
}

// An anonymised export (SOP, series, study and frame-of-reference UIDs all
// blanked; the meta header kept) still gives valid objects that belong
// together: one new study and frame of reference shared by all three.
TEST_F(DicomOutputTest, AnonymisedSourceGivesValidObjectsThatBelongTogether) {
  const fs::path source = dir_ / "anonymised";
  MakeSeries(kPhantom, {8, 9, 10, 11}, {0, 5, 10, 15}, source);
  for (const fs::path& f : SortedFiles(source)) {
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile(OFFilename(f.c_str())).good());
    ASSERT_TRUE(file.loadAllDataIntoMemory().good());
    DcmDataset& ds = *file.getDataset();
    for (const DcmTagKey& tag :
         {DCM_SOPClassUID, DCM_SOPInstanceUID, DCM_SeriesInstanceUID,
          DCM_StudyInstanceUID, DCM_FrameOfReferenceUID}) {
      ds.putAndInsertString(tag, "");
    }
    // Keep the meta header as the anonymiser left it.
    ASSERT_TRUE(file.saveFile(OFFilename(f.c_str()), EXS_Unknown,
                              EET_UndefinedLength, EGL_recalcGL, EPD_noChange,
                              0, 0, EWM_dontUpdateMeta)
                    .good());
  }
  const fs::path out = dir_ / "out";
  const CommandResult r =
      RunCli("run " + source.string() +
             " --threshold 300 --roi 200,60,0,300,160,4 --method direct "
             "--quiet --volume none --mesh none --seg --output-series "
             "intensity,distance --out " +
             out.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const std::vector<fs::path> files = SortedFiles(out / "series-intensity");
  ASSERT_FALSE(files.empty());
  std::string errors;
  int count = 0;
  std::vector<std::string> studies, frames;
  for (const fs::path& f :
       {files.front(), files.back(), out / "seg.dcm", out / "distance.dcm"}) {
    count += DciodvfyErrors(f, &errors);
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile(OFFilename(f.c_str())).good());
    studies.push_back(GetString(*file.getDataset(), DCM_StudyInstanceUID));
    frames.push_back(GetString(*file.getDataset(), DCM_FrameOfReferenceUID));
  }
  EXPECT_EQ(count, 0) << errors;
  for (size_t i = 0; i < studies.size(); ++i) {
    EXPECT_FALSE(studies[i].empty());
    EXPECT_EQ(studies[i], studies[0]);
    EXPECT_FALSE(frames[i].empty());
    EXPECT_EQ(frames[i], frames[0]);
  }
}

// The same job twice gives the same UIDs (a PACS replaces instead of
// duplicating); --random-uids gives new ones.
TEST_F(DicomOutputTest, RerunKeepsUidsAndRandomUidsDoNot) {
  // UIDs, then "series number | series description" of each object.
  std::map<std::string, std::vector<std::string>> series_of;
  auto run = [&](const std::string& name, const std::string& extra) {
    const fs::path out = dir_ / name;
    const CommandResult r =
        RunCli("run " + kPhantom.string() +
               " --roi 200,60,0,260,120,28 --method linear "
               "--quiet --volume none --mesh none --seg --out " +
               out.string() + " " + extra);
    EXPECT_EQ(r.exit_code, 0) << r.out;
    std::vector<std::string> uids;
    for (const fs::path& f :
         {out / "seg.dcm", out / "series-intensity" / "IM00001.dcm",
          out / "series-intensity" / "IM00100.dcm"}) {
      DcmFileFormat file;
      EXPECT_TRUE(file.loadFile(OFFilename(f.c_str())).good()) << f;
      uids.push_back(GetString(*file.getDataset(), DCM_SOPInstanceUID));
      uids.push_back(GetString(*file.getDataset(), DCM_SeriesInstanceUID));
      series_of[name].push_back(
          GetString(*file.getDataset(), DCM_SeriesNumber) + " | " +
          GetString(*file.getDataset(), DCM_SeriesDescription));
    }
    return uids;
  };
  const std::vector<std::string> first = run("first", "--threshold 300");
  const std::vector<std::string> again = run("again", "--threshold 300");
  ASSERT_EQ(first.size(), 6u);
  EXPECT_EQ(first, again);
  const std::vector<std::string> other_job = run("other", "--threshold 400");
  EXPECT_NE(first[0], other_job[0]);

  // Results of other parameters are told apart in the study: thresholds 250
  // and 300 give the SEG other series numbers and descriptions, and share
  // the intensity series, which the threshold does not change (issue 44: one
  // copy in the study, saying nothing of a threshold); a rerun of 300 gives
  // the same ones (so the PACS replaces them).
  run("t250", "--threshold 250");
  const std::vector<std::string>& t300 = series_of["first"];
  ASSERT_EQ(t300.size(), 3u);
  EXPECT_EQ(series_of["again"], t300);
  EXPECT_EQ(t300[0].substr(0, t300[0].find(' ')).size(), 6u) << t300[0];
  EXPECT_THAT(t300[0], HasSubstr("| Segmentation >=300 HU, "));
  EXPECT_THAT(t300[0], HasSubstr(" mm, linear, from #"));
  EXPECT_THAT(t300[1], HasSubstr("| Interpolated "));
  EXPECT_THAT(t300[1], HasSubstr(" mm, motion-compensated, from #"));
  {
    const std::string& a = t300[0];
    const std::string& b = series_of["t250"][0];
    EXPECT_NE(a.substr(0, a.find(' ')), b.substr(0, b.find(' ')))
        << a << " vs " << b;
    EXPECT_NE(a.substr(a.find('|')), b.substr(b.find('|')));
    EXPECT_THAT(b, HasSubstr(">=250 HU"));
  }
  for (size_t k = 1; k < t300.size(); ++k) {
    EXPECT_EQ(series_of["t250"][k], t300[k]);
    EXPECT_THAT(t300[k], Not(HasSubstr("HU")));
  }
  const std::vector<std::string> t250 = run("t250-uids", "--threshold 250");
  EXPECT_NE(t250[0], first[0]);  // the SEG
  for (size_t i = 2; i < first.size(); ++i) EXPECT_EQ(t250[i], first[i]);
  const std::vector<std::string> random1 =
      run("random1", "--threshold 300 --random-uids");
  const std::vector<std::string> random2 =
      run("random2", "--threshold 300 --random-uids");
  for (size_t i = 0; i < first.size(); ++i) {
    EXPECT_NE(random1[i], first[i]);
    EXPECT_NE(random1[i], random2[i]);
  }
}

// --dicom-mesh-adaptivity simplifies only the mesh stored as Encapsulated
// STL, and the report says how far it lies from the full surface.
TEST_F(DicomOutputTest, DicomMeshAdaptivitySimplifiesTheEncapsulatedStlOnly) {
  auto run = [&](const std::string& name, const std::string& extra) {
    const fs::path out = dir_ / name;
    const CommandResult r = RunCli(
        "run " + kPhantom.string() +
        " --threshold 300 --roi 200,60,0,300,160,28 --method linear --quiet "
        "--volume none --mesh stl --previews none --seg --out " +
        out.string() + " --report " + (out / "report.json").string() + " " +
        extra);
    EXPECT_EQ(r.exit_code, 0) << r.out;
    return ReadJson(out / "report.json");
  };
  const nlohmann::json full = run("full", "");
  const nlohmann::json simple = run("simple", "--dicom-mesh-adaptivity 1");
  // surface.stl is the same full mesh in both.
  EXPECT_EQ(fs::file_size(dir_ / "full/surface.stl"),
            fs::file_size(dir_ / "simple/surface.stl"));
  const int64_t triangles = full["mesh"]["triangles"].get<int64_t>();
  EXPECT_EQ(full["dicom_mesh"]["triangles"].get<int64_t>(), triangles);
  EXPECT_EQ(full["dicom_mesh"]["max_deviation_mm"].get<double>(), 0);
  const int64_t simplified = simple["dicom_mesh"]["triangles"].get<int64_t>();
  EXPECT_LT(simplified, triangles / 2);
  EXPECT_GT(simple["dicom_mesh"]["max_deviation_mm"].get<double>(), 0);
  EXPECT_LT(simple["dicom_mesh"]["max_deviation_mm"].get<double>(), 5);
  EXPECT_EQ(simple["dicom_mesh"]["samples_beyond_band"].get<int64_t>(), 0);
  // The Encapsulated STL embeds the simplified mesh (binary STL: 84 + 50
  // bytes per triangle), and no temporary file is left.
  for (const auto& [name, count] :
       {std::pair<std::string, int64_t>{"full", triangles},
        {"simple", simplified}}) {
    DcmFileFormat file;
    ASSERT_TRUE(
        file.loadFile(OFFilename((dir_ / name / "surface-stl.dcm").c_str()))
            .good());
    Uint32 length = 0;
    ASSERT_TRUE(file.getDataset()
                    ->findAndGetUint32(DCM_EncapsulatedDocumentLength, length)
                    .good());
    EXPECT_EQ(static_cast<int64_t>(length), 84 + 50 * count) << name;
    EXPECT_FALSE(fs::exists(dir_ / name / ".surface-dicom.stl"));
  }
  const CommandResult bad =
      RunCli("run " + kPhantom.string() +
             " --threshold 300 --dicom-mesh-adaptivity 1.5 --out " +
             (dir_ / "bad").string());
  EXPECT_EQ(bad.exit_code, 1);
  EXPECT_THAT(bad.out, HasSubstr("dicom-mesh-adaptivity"));
}

// The Encapsulated STL is capped in size (--dicom-mesh-max-mb, default 25
// MB) by simplifying its mesh; surface.stl stays the full mesh, and the
// report gives the triangles, size and the simplifier's error estimate.
TEST_F(DicomOutputTest, DicomMeshMaxMbCapsTheEncapsulatedStlOnly) {
  auto run = [&](const std::string& name, const std::string& extra) {
    const fs::path out = dir_ / name;
    const CommandResult r =
        RunCli("run " + kPhantom.string() +
               " --threshold 300 --roi 200,60,0,300,160,28 --method linear "
               "--volume none --mesh stl --previews none --seg --out " +
               out.string() + " --report " + (out / "report.json").string() +
               " " + extra);
    EXPECT_EQ(r.exit_code, 0) << r.out;
    return std::pair(ReadJson(out / "report.json"), r.out);
  };
  // The default cap (25 MB) is above this region's mesh: nothing simplified.
  const auto [uncapped, uncapped_out] = run("default", "");
  const int64_t triangles = uncapped["mesh"]["triangles"].get<int64_t>();
  ASSERT_GT(84 + 50 * triangles, 300'000) << "the region's mesh is too small "
                                             "for the cap below to bite";
  const nlohmann::json& d0 = uncapped["dicom_mesh"];
  EXPECT_EQ(d0["max_mb"].get<double>(), kDefaultDicomMeshMaxMb);
  EXPECT_EQ(d0["triangles"].get<int64_t>(), triangles);
  EXPECT_EQ(d0["triangles_before_cap"].get<int64_t>(), triangles);
  EXPECT_EQ(d0["simplify_error_mm"].get<double>(), 0);
  EXPECT_EQ(d0["stl_bytes"].get<int64_t>(), 84 + 50 * triangles);
  EXPECT_FALSE(d0["over_cap"].get<bool>());
  EXPECT_LE(fs::file_size(dir_ / "default/surface-stl.dcm"),
            kDefaultDicomMeshMaxMb * 1e6);
  EXPECT_THAT(uncapped_out, Not(HasSubstr("DICOM mesh capped")));

  // A cap of 0.3 MB: the object is at most 300 000 bytes, its STL the
  // simplified mesh, surface.stl unchanged.
  const auto [capped, capped_out] = run("capped", "--dicom-mesh-max-mb 0.3");
  const nlohmann::json& d = capped["dicom_mesh"];
  const int64_t kept = d["triangles"].get<int64_t>();
  EXPECT_EQ(d["max_mb"].get<double>(), 0.3);
  EXPECT_EQ(d["triangles_before_cap"].get<int64_t>(), triangles);
  // The phantom has 28 slices, each referenced in the object's header.
  EXPECT_LE(kept, MaxEncapsulatedStlTriangles(0.3, 28));
  EXPECT_GT(kept, MaxEncapsulatedStlTriangles(0.3, 28) * 9 / 10);
  EXPECT_EQ(d["stl_bytes"].get<int64_t>(), 84 + 50 * kept);
  EXPECT_FALSE(d["over_cap"].get<bool>());
  // The simplifier's estimate: positive, well under the 1 mm voxels.
  EXPECT_GT(d["simplify_error_mm"].get<double>(), 0);
  EXPECT_LT(d["simplify_error_mm"].get<double>(), 1.0);
  EXPECT_LE(fs::file_size(dir_ / "capped/surface-stl.dcm"), 300'000u);
  EXPECT_EQ(fs::file_size(dir_ / "capped/surface.stl"),
            fs::file_size(dir_ / "default/surface.stl"));
  EXPECT_THAT(capped_out, HasSubstr("DICOM mesh capped at 0.3 MB"));
  EXPECT_THAT(capped_out,
              HasSubstr("distance from the full surface not measured"));
  DcmFileFormat file;
  ASSERT_TRUE(
      file.loadFile(OFFilename((dir_ / "capped/surface-stl.dcm").c_str()))
          .good());
  Uint32 length = 0;
  ASSERT_TRUE(file.getDataset()
                  ->findAndGetUint32(DCM_EncapsulatedDocumentLength, length)
                  .good());
  EXPECT_EQ(static_cast<int64_t>(length), 84 + 50 * kept);
  EXPECT_FALSE(fs::exists(dir_ / "capped/.surface-dicom.stl"));

  // After the adaptivity: the cap applies to the re-extracted mesh, and the
  // deviation is measured for the mesh stored.
  const auto [both, both_out] =
      run("both", "--dicom-mesh-adaptivity 0.2 --dicom-mesh-max-mb 0.3");
  const nlohmann::json& b = both["dicom_mesh"];
  EXPECT_LT(b["triangles_before_cap"].get<int64_t>(), triangles);
  EXPECT_LE(b["triangles"].get<int64_t>(),
            MaxEncapsulatedStlTriangles(0.3, 28));
  EXPECT_GT(b["max_deviation_mm"].get<double>(), 0);
  EXPECT_EQ(b["samples_beyond_band"].get<int64_t>(), 0);
  EXPECT_LE(fs::file_size(dir_ / "both/surface-stl.dcm"), 300'000u);

  // No cap: the object holds surface.stl as it is.
  const auto [none, none_out] = run("none", "--dicom-mesh-max-mb 0");
  EXPECT_EQ(none["dicom_mesh"]["triangles"].get<int64_t>(), triangles);

  for (const char* value : {"0.05", "-1", "5000", "nan"}) {
    const CommandResult bad = RunCli(
        "run " + kPhantom.string() + " --threshold 300 " +
        "--dicom-mesh-max-mb " + value + " --out " + (dir_ / "bad").string());
    EXPECT_EQ(bad.exit_code, 1) << value;
    EXPECT_THAT(bad.out, HasSubstr("dicom-mesh-max-mb")) << value;
  }
}

}  // namespace
}  // namespace interslice
