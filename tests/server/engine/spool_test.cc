// What a finished job keeps (server/engine/spool.h RemoveArtifactsNotAskedFor,
// issue 25), on a job folder of stand-in files: which artifacts go, for which
// jobs, and that the result and its report then list only what is kept. The
// end-to-end case (the shipped rule through the DICOM node, delivered to
// Orthanc) is tests/server/node/node_spool_test.cc.
#include "server/engine/spool.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <string>
#include <vector>

#include "nlohmann/json.hpp"
#include "tests/testing/temp_dir.h"

namespace interslice::server {
namespace {

namespace fs = std::filesystem;
using ::testing::UnorderedElementsAre;

struct Outputs {
  fs::path dir;
  job::JobResult result;
};

// A job's out/ folder with `files` (name -> kind), 100 bytes each, and the
// result and report JSON that list them (by bare name, as JobKind::UseSpool
// makes them).
Outputs Make(const fs::path& dir,
             const std::vector<std::pair<std::string, std::string>>& files) {
  Outputs o{dir, {}};
  fs::create_directories(dir);
  nlohmann::ordered_json report = {{"mesh", {{"triangles", 12}}}};
  report["artifacts"] = nlohmann::ordered_json::array();
  for (const auto& [name, kind] : files) {
    const fs::path path = dir / name;
    if (name.find('/') != std::string::npos) {
      fs::create_directories(path.parent_path());
      std::ofstream(path) << std::string(100, 'x');
      const fs::path top = dir / name.substr(0, name.find('/'));
      o.result.artifacts.push_back({kind, top.string(), 100});
      report["artifacts"].push_back({{"kind", kind},
                                     {"path", top.filename().string()},
                                     {"size_bytes", 100}});
      continue;
    }
    std::ofstream(path) << std::string(100, 'x');
    o.result.artifacts.push_back({kind, path.string(), 100});
    report["artifacts"].push_back(
        {{"kind", kind}, {"path", name}, {"size_bytes", 100}});
  }
  o.result.report_json = report.dump(2);
  return o;
}

std::set<std::string> OnDisk(const fs::path& dir) {
  std::set<std::string> names;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (e.is_regular_file()) names.insert(fs::relative(e.path(), dir).string());
  }
  return names;
}

std::set<std::string> Listed(const job::JobResult& result) {
  std::set<std::string> names;
  for (const Artifact& a : result.artifacts) {
    names.insert(fs::path(a.path).filename().string());
  }
  return names;
}

std::set<std::string> InReport(const job::JobResult& result) {
  std::set<std::string> names;
  const nlohmann::json report = nlohmann::json::parse(result.report_json);
  for (const auto& a : report["artifacts"]) {
    names.insert(a["path"].get<std::string>());
  }
  return names;
}

JobRecord NodeJob(bool send_to) {
  JobRecord record;
  record.mutable_status()->mutable_source()->set_door(v1::JobOrigin::DICOM);
  record.mutable_status()->set_origin("dicom:ORTHANC->INTERSLICE rule r");
  if (send_to) record.mutable_spec()->add_send_to("orthanc");
  return record;
}

const std::vector<std::pair<std::string, std::string>> kShippedRuleOutputs = {
    {"series-intensity/IM00001.dcm", "series-intensity"},
    {"seg.dcm", "seg"},
    {"surface.stl", "surface"},
    {"surface-coordinates.txt", "surface-coordinates"},
    {"surface-stl.dcm", "surface-stl-dicom"},
    {"previews/axial.png", "previews"},
};

TEST(RemoveArtifactsNotAskedForTest, NodeJobThatDeliversKeepsWhatItDelivers) {
  testing::TempDir dir;
  Outputs o = Make(dir.path() / "out", kShippedRuleOutputs);
  EXPECT_EQ(RemoveArtifactsNotAskedFor(NodeJob(true), &o.result), 200);
  const std::set<std::string> kept = {"series-intensity/IM00001.dcm", "seg.dcm",
                                      "surface-stl.dcm", "previews/axial.png"};
  EXPECT_EQ(OnDisk(o.dir), kept);
  EXPECT_THAT(Listed(o.result),
              UnorderedElementsAre("series-intensity", "seg.dcm",
                                   "surface-stl.dcm", "previews"));
  EXPECT_EQ(InReport(o.result), Listed(o.result));
  // The rest of the report is untouched.
  EXPECT_EQ(nlohmann::json::parse(o.result.report_json)["mesh"]["triangles"],
            12);
}

TEST(RemoveArtifactsNotAskedForTest, VolumesGoOnlyWhenADicomObjectCarriesThem) {
  testing::TempDir dir;
  // A SEG carries the mask; no distance map, so the distance volume is the
  // only copy of the distance field; a PLY mesh no DICOM object carries keeps
  // the coordinates note.
  Outputs o = Make(dir.path() / "out",
                   {{"seg.dcm", "seg"},
                    {"mask.nii.gz", "mask"},
                    {"distance.nii.gz", "distance"},
                    {"surface.stl", "surface"},
                    {"surface.ply", "surface"},
                    {"surface-coordinates.txt", "surface-coordinates"},
                    {"surface-stl.dcm", "surface-stl-dicom"}});
  EXPECT_EQ(RemoveArtifactsNotAskedFor(NodeJob(true), &o.result), 200);
  EXPECT_EQ(OnDisk(o.dir), (std::set<std::string>{
                               "seg.dcm", "distance.nii.gz", "surface.ply",
                               "surface-coordinates.txt", "surface-stl.dcm"}));
  EXPECT_EQ(InReport(o.result), Listed(o.result));

  // With the distance map as DICOM, its volume goes too.
  testing::TempDir dir2;
  Outputs d = Make(dir2.path() / "out", {{"distance.dcm", "distance-map"},
                                         {"distance.nii.gz", "distance"},
                                         {"mask.nrrd", "mask"}});
  EXPECT_EQ(RemoveArtifactsNotAskedFor(NodeJob(true), &d.result), 100);
  EXPECT_EQ(OnDisk(d.dir),
            (std::set<std::string>{"distance.dcm", "mask.nrrd"}));
}

TEST(RemoveArtifactsNotAskedForTest, JobsWhoseFilesAreFetchedKeepEverything) {
  // A node job without send_to (its results are only in the spool), and a
  // job submitted over gRPC with send_to (its client fetches them).
  JobRecord grpc;
  grpc.mutable_status()->mutable_source()->set_door(v1::JobOrigin::GRPC);
  grpc.mutable_spec()->add_send_to("orthanc");
  for (const JobRecord& record : {NodeJob(false), grpc}) {
    testing::TempDir dir;
    Outputs o = Make(dir.path() / "out", kShippedRuleOutputs);
    const std::string report = o.result.report_json;
    EXPECT_EQ(RemoveArtifactsNotAskedFor(record, &o.result), 0);
    EXPECT_EQ(OnDisk(o.dir).size(), kShippedRuleOutputs.size());
    EXPECT_EQ(o.result.artifacts.size(), kShippedRuleOutputs.size());
    EXPECT_EQ(o.result.report_json, report);
  }
}

}  // namespace
}  // namespace interslice::server
