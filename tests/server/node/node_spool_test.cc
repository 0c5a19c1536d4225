// A job of the DICOM node keeps only what it was asked for (issue 25,
// server/engine/spool.h RemoveArtifactsNotAskedFor): the shipped rule
// (deploy/config/rules.yaml: the derived series, the SEG and the mesh as an
// Encapsulated STL, sent to `orthanc`) on tests/data/ct-tilt sent by
// storescu, the results delivered to a real Orthanc; then the job's folder
// in the spool must hold its record and the DICOM objects Orthanc received,
// and nothing else (before: also surface.stl, the same mesh again, and its
// coordinates note, written and then removed; and PNG previews, which the
// shipped rule no longer asks for: no peer receives them). A job submitted over
// gRPC with the same outputs keeps every artifact: its client fetches them.
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;

const std::string kCli = ::interslice::testing::CliPath();
const std::string kStoreScu = "/usr/bin/storescu";  // Debian's dcmtk
const std::string kSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-tilt";
const std::string kShippedRules =
    std::string(::interslice::testing::SourceDir()) +
    "/deploy/config/rules.yaml";

// Every regular file below `dir`: its path relative to `dir` -> bytes.
std::map<std::string, int64_t> Files(const fs::path& dir) {
  std::map<std::string, int64_t> files;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (e.is_regular_file()) {
      files[fs::relative(e.path(), dir).string()] =
          static_cast<int64_t>(e.file_size());
    }
  }
  return files;
}

std::vector<std::string> JobFolders(const fs::path& spool) {
  std::vector<std::string> ids;
  for (const auto& e : fs::directory_iterator(spool / "jobs")) {
    if (e.is_directory()) ids.push_back(e.path().filename().string());
  }
  return ids;
}

// The job runs in a worker process (the default) or on the server's own
// threads (--isolation thread): each path tells the job what to omit.
class NodeSpoolTest : public ::testing::TestWithParam<std::string> {};

TEST_P(NodeSpoolTest, ShippedRulesJobKeepsOnlyWhatItDelivers) {
  TempDir dir("interslice_node_spool_");
  const fs::path root = dir.path();
  auto orthanc = Orthanc::Start((root / "orthanc").string(), {});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  // The shipped rule sends to the peer `orthanc`: this one.
  const std::string peers = (root / "peers.yaml").string();
  std::ofstream(peers) << "peers:\n  - {name: orthanc, ae_title: "
                       << (*orthanc)->ae_title() << ", host: 127.0.0.1, port: "
                       << (*orthanc)->dicom_port() << "}\n";
  const fs::path spool = root / "spool";
  ServerProcess server(ServerOptions{
      .spool = spool.string(),
      .log = (root / "server.log").string(),
      .extra = {"--dicom-listen", "127.0.0.1:0", "--dicom-ae", "INTERSLICE",
                "--dicom-peers", peers, "--rules", kShippedRules,
                "--delivery-retry", "0.2", "--delivery-retry-max", "1",
                "--isolation", GetParam()},
      .threads_per_job = 1});
  ASSERT_TRUE(server.Start());
  const std::vector<std::string> client = server.ServerFlag();

  // The series as the PACS would send it (its AE title: a known peer).
  std::vector<std::string> store = {kStoreScu,
                                    "-aet",
                                    (*orthanc)->ae_title(),
                                    "-aec",
                                    "INTERSLICE",
                                    "127.0.0.1",
                                    std::to_string(server.dicom_port())};
  for (const auto& e : fs::directory_iterator(kSeries)) {
    if (e.path().extension() == ".dcm") store.push_back(e.path().string());
  }
  const CommandResult stored = RunCommand(store, 120);
  ASSERT_EQ(stored.exit_code, 0) << stored.err << server.Log();

  std::vector<std::string> ids;
  ASSERT_TRUE(WaitFor(
      [&] {
        ids = JobFolders(spool);
        return !ids.empty();
      },
      std::chrono::seconds(120)))
      << server.Log();
  ASSERT_EQ(ids.size(), 1u);
  const std::string job = ids[0];
  const CommandResult watch =
      RunCommand(Cat({kCli, "watch", job, "--wait-deliveries"}, client), 300);
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  EXPECT_THAT(server.Log(), HasSubstr("made by rule ct-bone"));
  // The job never wrote what it would not keep (JobKind::
  // OmitFilesDicomObjectsCarry), so nothing had to be removed afterwards.
  EXPECT_THAT(server.Log(), Not(HasSubstr("kept only what it was asked for")));

  // What Orthanc received: every result instance, byte for byte as sent.
  auto instances = (*orthanc)->GetJson("/instances");
  ASSERT_TRUE(instances.ok()) << instances.status();
  // (storescu sent the source to the node, not to Orthanc.)
  const int delivered = static_cast<int>(instances->size());
  ASSERT_GE(delivered, 3) << "the derived series, the SEG, the STL";
  EXPECT_THAT(watch.out, HasSubstr(absl::StrCat("to orthanc: delivered, ",
                                                delivered, " of ", delivered)));
  int64_t delivered_bytes = 0;
  for (const auto& id : *instances) {
    auto file = (*orthanc)->InstanceFile(id.get<std::string>());
    ASSERT_TRUE(file.ok()) << file.status();
    delivered_bytes += static_cast<int64_t>(file->size());
  }

  // The job's folder: its record and the delivered objects.
  const fs::path folder = spool / "jobs" / job;
  const std::map<std::string, int64_t> files = Files(folder);
  std::set<std::string> names;
  for (const auto& [name, bytes] : files) names.insert(name);
  std::set<std::string> expected = {
      "job.pb",
      "out/seg.dcm",
      "out/surface-stl.dcm",
  };
  // The derived series: one file per output slice, the rest of what went.
  const int derived_slices = delivered - 2;
  for (int k = 1; k <= derived_slices; ++k) {
    char name[64];
    std::snprintf(name, sizeof(name), "out/series-intensity/IM%05d.dcm", k);
    expected.insert(name);
  }
  EXPECT_EQ(names, expected) << "spool folder of the job " << job;
  // Its size: what was delivered, plus the record (the only file no peer
  // received).
  int64_t total = 0, not_delivered = 0;
  for (const auto& [name, bytes] : files) {
    total += bytes;
    if (name == "job.pb") {
      not_delivered += bytes;
    }
  }
  EXPECT_LE(total, delivered_bytes + not_delivered)
      << "the job keeps " << total << " bytes; delivered " << delivered_bytes
      << ", record " << not_delivered;

  // The job's status lists only what is there: fetch gets every artifact,
  // and they are the folder's out/ files.
  const fs::path fetched = root / "fetched";
  const CommandResult fetch = RunCommand(
      Cat({kCli, "fetch", job, "--out", fetched.string()}, client), 300);
  ASSERT_EQ(fetch.exit_code, 0) << fetch.err << server.Log();
  std::set<std::string> fetched_names;
  for (const auto& [name, bytes] : Files(fetched)) {
    fetched_names.insert("out/" + name);
  }
  std::set<std::string> out_names = names;
  out_names.erase("job.pb");
  EXPECT_EQ(fetched_names, out_names);

  // The same outputs submitted over gRPC (with send_to): every artifact is
  // kept, the mesh file too; its client fetches them.
  const CommandResult submit = RunCommand(
      Cat({kCli, "submit", kSeries, "--threshold", "300", "--method", "direct",
           "--output-series", "intensity", "--seg", "--mesh", "stl", "--volume",
           "none", "--send-to", "orthanc"},
          client),
      300);
  ASSERT_EQ(submit.exit_code, 0) << submit.err;
  const std::string grpc_job =
      submit.out.substr(0, submit.out.find_first_of(" \n"));
  const CommandResult grpc_watch = RunCommand(
      Cat({kCli, "watch", grpc_job, "--wait-deliveries"}, client), 300);
  ASSERT_EQ(grpc_watch.exit_code, 0) << grpc_watch.err << server.Log();
  const std::map<std::string, int64_t> grpc_files =
      Files(spool / "jobs" / grpc_job);
  EXPECT_EQ(grpc_files.count("out/surface.stl"), 1u);
  EXPECT_EQ(grpc_files.count("out/surface-coordinates.txt"), 1u);
  EXPECT_EQ(server.Stop(), 0) << server.Log();
}

INSTANTIATE_TEST_SUITE_P(Isolation, NodeSpoolTest,
                         ::testing::Values("process", "thread"));

}  // namespace
}  // namespace interslice::testing
