// End-to-end tests of the `interslice` binary: real processes, real data.
#include "tests/testing/cli.h"

#include <unistd.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "core/dicom/series_reader.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "nlohmann/json.hpp"
#include "tests/testing/mesh_checks.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;

using testing::CommandResult;
using testing::RunCli;

class CliTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice_cli_test_" + std::to_string(getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
};

const std::string kSmallSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-thick";
const std::string kPhantom = std::string(::interslice::testing::SourceDir()) +
                             "/data/ct-head-phantom-thick";

TEST_F(CliTest, HelpExitsZero) {
  const CommandResult r = RunCli("run --help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_THAT(r.out, ::testing::HasSubstr("--threshold"));
  EXPECT_THAT(r.out, ::testing::HasSubstr("--method"));
}

TEST_F(CliTest, BadInputGivesOneLineAndExitCodeOne) {
  const std::string out = (dir_ / "out").string();
  struct Case {
    std::string args;
    std::string message;
  };
  const Case cases[] = {
      {"run " + kSmallSeries + " --out " + out, "--threshold"},
      {"run " + kSmallSeries + " --threshold abc --out " + out, "threshold"},
      {"run " + kSmallSeries + " --threshold 300 --method magic --out " + out,
       "--method"},
      {"run " + kSmallSeries + " --threshold 300 --roi 1,2,3 --out " + out,
       "--roi"},
      {"run " + kSmallSeries + " --threshold 300 --roi 0,0,0,600,10,2 --out " +
           out,
       "along x"},
      {"run " + kSmallSeries + " --threshold 300 --mesh vrml --out " + out,
       "--mesh"},
      {"run " + kSmallSeries +
           " --threshold 300 --factor 2 --spacing 1 --out " + out,
       "--factor"},
      {"run " + (dir_ / "missing").string() + " --threshold 300 --out " + out,
       "missing"},
      {"run " + kSmallSeries + " --threshold 300 --upper 100 --out " + out,
       "upper"},
      {"frobnicate", "frobnicate"},
  };
  for (const Case& c : cases) {
    const CommandResult r = RunCli(c.args);
    EXPECT_EQ(r.exit_code, 1) << c.args << "\n" << r.out;
    EXPECT_THAT(r.out, ::testing::HasSubstr(c.message)) << c.args;
    // One line: the reason, and nothing else.
    EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << c.args << "\n"
                                                               << r.out;
  }
  EXPECT_FALSE(fs::exists(dir_ / "out" / "surface.stl"));
}

TEST_F(CliTest, RunWritesVolumesMeshAndReport) {
  const fs::path out = dir_ / "out";
  const fs::path report = dir_ / "report.json";
  // A region of interest keeps this quick: 96x96 pixels of the 4 slices.
  const CommandResult r = RunCli(
      "run " + kSmallSeries +
      " --threshold 300 --roi 200,40,0,296,136,4 --method direct --factor 5 "
      "--mesh stl,ply,obj --volume nii,nrrd --out " +
      out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  for (const char* name :
       {"distance.nii.gz", "mask.nii.gz", "distance.nrrd", "mask.nrrd",
        "surface.stl", "surface.ply", "surface.obj"}) {
    EXPECT_TRUE(fs::exists(out / name)) << name;
  }
  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  for (const char* stage :
       {"read", "contour", "stack", "solve", "mesh", "write"}) {
    EXPECT_TRUE(j["stages"].contains(stage)) << stage;
    EXPECT_GE(j["stages"][stage].get<double>(), 0.0);
  }
  EXPECT_EQ(j["solver"]["method"], "direct");
  EXPECT_LT(j["solver"]["relative_residual"].get<double>(), 1e-3);
  EXPECT_LT(j["solver"]["energy"].get<double>(),
            j["solver"]["initial_energy"].get<double>());
  EXPECT_EQ(j["grid"]["size"], nlohmann::json::array({96, 96, 16}));
  EXPECT_NEAR(j["grid"]["spacing"][2].get<double>(), 1.0, 1e-6);
  EXPECT_GT(j["peak_rss_bytes"].get<int64_t>(), 0);

  // The written volume has the reported geometry; origin is ROI voxel
  // (200, 40, 0) of the series.
  const auto distance = ReadVolumeAsFloat((out / "distance.nii.gz").string());
  ASSERT_TRUE(distance.ok()) << distance.status();
  EXPECT_EQ(distance->grid.size, (Index3{96, 96, 16}));
  for (int a = 0; a < 3; ++a) {
    EXPECT_NEAR(distance->grid.spacing[a],
                j["grid"]["spacing"][a].get<double>(), 1e-4);
    EXPECT_NEAR(distance->grid.origin[a], j["grid"]["origin"][a].get<double>(),
                1e-3);
  }
  testing::TriangleSoup soup;
  ASSERT_TRUE(testing::ReadBinaryStl((out / "surface.stl").string(), soup));
  EXPECT_GT(soup.triangles.size(), 100u);
  const testing::MeshTopology topo = testing::AnalyzeSoup(soup);
  EXPECT_EQ(topo.boundary_edges, 0);
  EXPECT_GT(topo.signed_volume, 0);
}

// Issue 42: a series whose anonymiser gave every slice its own
// FrameOfReferenceUID, with one geometry, is read as one stack with a note
// in the report and a warning; --strict-frame-of-reference refuses it.
TEST_F(CliTest, OwnFrameOfReferencePerSliceIsAReportNoteAndAWarning) {
  const fs::path series = dir_ / "series";
  fs::create_directories(series);
  for (const char* name : {"I10.dcm", "I20.dcm", "I30.dcm", "I40.dcm"}) {
    DcmFileFormat file;
    ASSERT_TRUE(file.loadFile((kSmallSeries + "/" + name).c_str()).good());
    char uid[100];
    ASSERT_TRUE(file.getDataset()
                    ->putAndInsertString(DCM_FrameOfReferenceUID,
                                         dcmGenerateUniqueIdentifier(
                                             uid, SITE_INSTANCE_UID_ROOT))
                    .good());
    ASSERT_TRUE(file.saveFile((series / name).c_str(), EXS_LittleEndianExplicit)
                    .good());
  }
  const std::string job = "run " + series.string() +
                          " --threshold 300 --roi 200,40,0,296,136,4 --method "
                          "linear --factor 2 --volume none --previews none "
                          "--out ";
  const fs::path report = dir_ / "report.json";
  const CommandResult r =
      RunCli(job + (dir_ / "out").string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  const std::string note =
      "FrameOfReferenceUID not the same on every slice (4 different UIDs "
      "among the 4 slices): read as one stack because the geometry was "
      "checked";
  EXPECT_THAT(r.out, ::testing::HasSubstr("interslice: warning: " + note));
  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  EXPECT_THAT(j["input"]["notes"].get<std::vector<std::string>>(),
              ::testing::ElementsAre(::testing::HasSubstr(note)));

  const CommandResult strict =
      RunCli(job + (dir_ / "strict").string() + " --strict-frame-of-reference");
  EXPECT_EQ(strict.exit_code, 1) << strict.out;
  EXPECT_THAT(strict.out,
              ::testing::HasSubstr("inconsistent FrameOfReferenceUID: each of "
                                   "the 4 slices has a different one"));
}

// This process's resident set size now, bytes (VmRSS).
int64_t ResidentBytes() {
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);) {
    long long kilobytes = 0;
    if (std::sscanf(line.c_str(), "VmRSS: %lld kB", &kilobytes) == 1) {
      return kilobytes * 1024;
    }
  }
  return -1;
}

// Issue 42: the report's peak_rss_bytes counted the parent (1.6 GB for a
// 230 MB job started from Python): Linux carries getrusage's ru_maxrss
// over execve, and a forked child starts with its parent's pages. The
// same tiny job, started by this process as it is and then while it holds
// 320 MB more (touched), must report the same peak: the CLI's own.
TEST_F(CliTest, ReportPeakRssIsTheCliProcessNotItsParent) {
  const std::vector<std::string> job = {::interslice::testing::CliPath(),
                                        "run",
                                        kSmallSeries,
                                        "--threshold",
                                        "300",
                                        "--roi",
                                        "200,40,0,296,136,4",
                                        "--method",
                                        "linear",
                                        "--factor",
                                        "2",
                                        "--volume",
                                        "none",
                                        "--previews",
                                        "none",
                                        "--quiet",
                                        "--out"};
  auto peak_of = [&](const std::string& name) -> int64_t {
    const fs::path report = dir_ / (name + ".json");
    const CommandResult r = testing::RunCommand(testing::Cat(
        job, {(dir_ / name).string(), "--report", report.string()}));
    EXPECT_EQ(r.exit_code, 0) << r.out << r.err;
    std::ifstream in(report);
    return nlohmann::json::parse(in)["peak_rss_bytes"].get<int64_t>();
  };
  const int64_t alone = peak_of("alone");

  constexpr size_t kParentBytes = size_t{320} << 20;
  std::vector<char> ballast(kParentBytes);
  std::memset(ballast.data(), 1, ballast.size());  // every page resident
  ASSERT_GE(ResidentBytes(), static_cast<int64_t>(kParentBytes));
  const int64_t beside_ballast = peak_of("beside-ballast");
  EXPECT_EQ(ballast[kParentBytes - 1], 1);

  EXPECT_GT(alone, 0);
  EXPECT_LT(beside_ballast, alone + static_cast<int64_t>(kParentBytes / 2))
      << "alone " << alone << " bytes, beside a parent of " << ResidentBytes()
      << " bytes: " << beside_ballast;
}

TEST_F(CliTest, CgLinearDirectAndMorphAllRun) {
  for (const char* method : {"linear", "cg", "direct", "morph"}) {
    const fs::path out = dir_ / method;
    const CommandResult r =
        RunCli("run " + kSmallSeries +
               " --threshold 300 --roi 200,40,1,264,104,3 --method " + method +
               " --iterations 5 --volume none --mesh stl --quiet --out " +
               out.string() + " --report " + (out / "r.json").string());
    ASSERT_EQ(r.exit_code, 0) << method << ": " << r.out;
    std::ifstream in(out / "r.json");
    const nlohmann::json j = nlohmann::json::parse(in);
    EXPECT_EQ(j["solver"]["method"], method);
    if (std::string(method) == "cg") {
      EXPECT_EQ(j["solver"]["iterations"], 5);
    }
  }
}

// The acceptance run: the shipped thick phantom at 300 HU gives an
// isotropic distance volume and a watertight, outward skull mesh.
TEST_F(CliTest, ShippedPhantomGivesIsotropicVolumeAndWatertightSkull) {
  const fs::path out = dir_ / "phantom";
  const fs::path report = dir_ / "report.json";
  const CommandResult r = RunCli("run " + kPhantom +
                                 " --threshold 300 --method direct --quiet "
                                 "--volume nrrd --mesh stl,ply --out " +
                                 out.string() + " --report " + report.string());
  ASSERT_EQ(r.exit_code, 0) << r.out;
  std::ifstream in(report);
  const nlohmann::json j = nlohmann::json::parse(in);
  const double sx = j["grid"]["spacing"][0], sy = j["grid"]["spacing"][1],
               sz = j["grid"]["spacing"][2];
  // 5 mm slices, 0.451 mm pixels: N = 11, z spacing 0.4545 mm (within 1%).
  EXPECT_EQ(j["grid"]["insertion_factor"], 11);
  EXPECT_NEAR(sx, sy, 1e-9);
  EXPECT_NEAR(sz / sx, 1.0, 0.01);
  EXPECT_EQ(j["grid"]["size"][2], 27 * 11 + 1);
  const auto distance = ReadVolumeAsFloat((out / "distance.nrrd").string());
  ASSERT_TRUE(distance.ok()) << distance.status();
  EXPECT_NEAR(distance->grid.spacing[2], sz, 1e-6);

  // Topology by vertex index from the PLY (STL keeps no indices).
  testing::IndexedMesh mesh;
  ASSERT_TRUE(testing::ReadBinaryPly((out / "surface.ply").string(), mesh));
  EXPECT_GT(mesh.triangles.size(), 100000u);
  const testing::MeshTopology topo = testing::AnalyzeIndexed(mesh);
  EXPECT_EQ(topo.boundary_edges, 0);
  EXPECT_EQ(topo.non_manifold_edges, 0);
  EXPECT_GT(topo.signed_volume, 0);
  // The STL holds the same triangles, closed once welded by position.
  testing::TriangleSoup soup;
  ASSERT_TRUE(testing::ReadBinaryStl((out / "surface.stl").string(), soup));
  EXPECT_EQ(soup.triangles.size(), mesh.triangles.size());
  EXPECT_EQ(testing::AnalyzeSoup(soup).boundary_edges, 0);
  // Vertices lie in patient space inside the series' extent (z 696..831 mm).
  for (const auto& v : mesh.vertices) {
    ASSERT_GT(v[2], 696.21 - 1.0);
    ASSERT_LT(v[2], 831.21 + 1.0);
  }
}

}  // namespace
}  // namespace interslice
