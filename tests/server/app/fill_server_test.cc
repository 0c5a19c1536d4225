// Fill jobs through the daemon: a real interslice-server process
// on loopback, driven by the real `interslice` client (`fill --server`,
// `fetch`) and, for detached jobs and malformed specs, by a gRPC stub. The
// artifacts must equal those of RunFillJob in this process, voxel for voxel
// and byte for byte.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <openssl/evp.h>

#include <chrono>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "core/labels/fill_job.h"
#include "core/labels/segmentation_reader.h"
#include "core/volume_io/volume_io.h"
#include "grpcpp/grpcpp.h"
#include "interslice/v1/interslice.grpc.pb.h"
#include "nlohmann/json.hpp"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kCli = ::interslice::testing::CliPath();
const std::string kSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-thick";

// A gRPC stub talking to the server.
std::unique_ptr<v1::InterSlice::Stub> StubTo(const ServerProcess& server) {
  return v1::InterSlice::NewStub(grpc::CreateChannel(
      server.address(), grpc::InsecureChannelCredentials()));
}

CommandResult Cli(const std::vector<std::string>& args, double timeout = 300) {
  return RunCommand(Cat({kCli}, args), timeout);
}

std::string Sha256(const std::string& data) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int n = 0;
  EVP_Digest(data.data(), data.size(), digest, &n, EVP_sha256(), nullptr);
  return std::string(reinterpret_cast<char*>(digest), n);
}

struct UploadFile {
  std::string path;
  std::string name;  // FileChunk.file_name
};

std::vector<UploadFile> SeriesFiles(const std::string& dir) {
  std::vector<UploadFile> files;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (e.path().extension() == ".dcm") {
      files.push_back(
          {e.path().string(), "series/" + e.path().filename().string()});
    }
  }
  std::sort(files.begin(), files.end(),
            [](const auto& a, const auto& b) { return a.path < b.path; });
  return files;
}

// A detached job by Submit: the status and, if OK, the job id.
grpc::Status Submit(const ServerProcess& server, const v1::JobSpec& spec,
                    const std::vector<UploadFile>& files, std::string* id) {
  auto stub = StubTo(server);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(60));
  v1::SubmitResponse response;
  auto writer = stub->Submit(&context, &response);
  v1::UploadRequest request;
  v1::UploadHeader* header = request.mutable_header();
  *header->mutable_spec() = spec;
  header->set_file_count(static_cast<int>(files.size()));
  std::vector<std::string> contents;
  int64_t total = 0;
  for (const UploadFile& f : files) {
    contents.push_back(ReadFileOrEmpty(f.path));
    total += static_cast<int64_t>(contents.back().size());
  }
  header->set_total_bytes(total);
  bool open = writer->Write(request);
  for (size_t i = 0; open && i < files.size(); ++i) {
    request.Clear();
    v1::FileChunk* chunk = request.mutable_chunk();
    chunk->set_file_index(static_cast<int>(i));
    chunk->set_file_name(files[i].name);
    chunk->set_file_size(static_cast<int64_t>(contents[i].size()));
    chunk->set_sha256(Sha256(contents[i]));
    chunk->set_offset(0);
    chunk->set_data(contents[i]);
    open = writer->Write(request);
  }
  if (open) writer->WritesDone();
  const grpc::Status status = writer->Finish();
  if (status.ok() && id != nullptr) *id = response.job_id();
  return status;
}

// Waits for the end of a detached job.
v1::JobStatus WaitForEnd(const ServerProcess& server, const std::string& id) {
  auto stub = StubTo(server);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(240));
  v1::WatchRequest request;
  request.set_job_id(id);
  auto reader = stub->Watch(&context, request);
  v1::JobStatus status, last;
  while (reader->Read(&status)) last = status;
  reader->Finish();
  return last;
}

// RunFillJob in this process, on one thread: the reference results.
FillJobReport RunLocally(const std::string& segmentation,
                         const std::string& reference, const std::string& out,
                         const std::vector<int64_t>& key_slices = {}) {
  FillJobSpec spec;
  spec.segmentation = segmentation;
  spec.reference = {reference};
  spec.output_dir = out;
  spec.fill.method = FillMethod::kSolver;  // as the server for DIRECT
  spec.fill.solver.method = SolverMethod::kDirect;
  if (!key_slices.empty()) spec.fill.key_slices = key_slices;
  spec.volume_formats = {"nii", "nrrd"};
  spec.mesh_formats = {"stl"};
  absl::StatusOr<FillJobReport> report =
      RunFillJob(spec, ComputeContext{.threads = 1});
  EXPECT_TRUE(report.ok()) << report.status();
  return report.ok() ? *report : FillJobReport{};
}

// Every file of `expected` exists in `actual` with the same bytes, and the
// label maps agree voxel for voxel (said separately for a clear failure).
void ExpectSameResults(const std::string& expected, const std::string& actual) {
  int files = 0;
  // The previews are a folder: its files too.
  for (const auto& e : fs::recursive_directory_iterator(expected)) {
    if (!e.is_regular_file()) continue;
    const std::string name = fs::relative(e.path(), expected).string();
    ASSERT_TRUE(fs::exists(fs::path(actual) / name)) << name;
    EXPECT_TRUE(ReadFileOrEmpty(e.path().string()) ==
                ReadFileOrEmpty((fs::path(actual) / name).string()))
        << name << " differs";
    ++files;
  }
  EXPECT_GE(files, 3);  // labels.nii.gz, labels.nrrd, at least one mesh
  absl::StatusOr<Volume<float>> a =
      ReadVolumeAsFloat((fs::path(expected) / "labels.nrrd").string());
  absl::StatusOr<Volume<float>> b =
      ReadVolumeAsFloat((fs::path(actual) / "labels.nrrd").string());
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  ASSERT_EQ(a->grid.size, b->grid.size);
  int64_t differing = 0, labelled = 0;
  for (size_t n = 0; n < a->data.size(); ++n) {
    differing += a->data[n] != b->data[n];
    labelled += a->data[n] != 0;
  }
  EXPECT_EQ(differing, 0);
  EXPECT_GT(labelled, 1000);  // a real result, not two empty volumes
}

// Two touching labels on the 4-slice series, drawn on slices 0 and 3 only:
// bone (>= 300 HU) and the soft tissue next to it (0..300 HU) in a box.
std::string WriteLabelMap(const std::string& path) {
  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries({kSeries}, {}, ComputeContext{.threads = 1});
  EXPECT_TRUE(series.ok()) << series.status();
  Volume<uint16_t> labels;
  labels.grid = series->image.grid;
  labels.data.assign(labels.grid.VoxelCount(), 0);
  for (int64_t k : {int64_t{0}, labels.grid.size[2] - 1}) {
    for (int64_t j = 150; j < 350; ++j) {
      for (int64_t i = 150; i < 350; ++i) {
        const float hu = series->image.at(i, j, k);
        labels.at(i, j, k) = hu >= 300 ? 1 : hu >= 0 ? 2 : 0;
      }
    }
  }
  EXPECT_TRUE(WriteVolume(labels, path).ok());
  return path;
}

TEST(FillServerTest, LabelMapFilledByTheServerEqualsInProcess) {
  TempDir dir;
  const std::string labels = WriteLabelMap(dir / "drawn.nii.gz");
  const FillJobReport local = RunLocally(labels, kSeries, dir / "local");
  ASSERT_EQ(local.per_label.size(), 2u);
  // One worker, two solver threads: the results must not depend on the
  // thread count.
  ServerProcess server({.spool = dir / "spool", .log = dir / "server.log"});
  ASSERT_TRUE(server.Start());

  // One call: `interslice fill --server` writes the same files.
  CommandResult r =
      Cli(Cat({"fill", labels, "--reference", kSeries, "--method", "direct",
               "--volume", "nii,nrrd", "--mesh", "stl", "--out", dir / "remote",
               "--report", dir / "remote.json"},
              server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err << server.Log();
  ExpectSameResults(dir / "local", dir / "remote");
  // The report is `interslice fill --report`'s, paths in the output folder.
  std::ifstream in(dir / "remote.json");
  const nlohmann::json report = nlohmann::json::parse(in);
  EXPECT_EQ(report["input"], "label-map");
  EXPECT_EQ(report["method"], "direct");
  ASSERT_EQ(report["labels"].size(), 2u);
  EXPECT_EQ(report["labels"][0]["key_slices"],
            nlohmann::json(local.per_label[0].key_slices));
  for (const auto& a : report["artifacts"]) {
    EXPECT_TRUE(fs::exists(a["path"].get<std::string>())) << a;
  }

  // Detached: Submit (the segmentation file named like any other), then
  // `interslice fetch`.
  v1::JobSpec spec;
  spec.set_method(v1::SOLVER_METHOD_DIRECT);
  spec.mutable_outputs()->add_volume_formats(v1::VOLUME_FORMAT_NIFTI);
  spec.mutable_outputs()->add_volume_formats(v1::VOLUME_FORMAT_NRRD);
  spec.mutable_outputs()->add_mesh_formats(v1::MESH_FORMAT_STL);
  spec.mutable_fill()->set_segmentation_file("drawn.nii.gz");
  std::vector<UploadFile> files = SeriesFiles(kSeries);
  files.insert(files.begin() + 1, {labels, "drawn.nii.gz"});
  std::string id;
  const grpc::Status submitted = Submit(server, spec, files, &id);
  ASSERT_TRUE(submitted.ok()) << submitted.error_message();
  const v1::JobStatus status = WaitForEnd(server, id);
  ASSERT_EQ(status.state(), v1::JOB_STATE_SUCCEEDED)
      << status.error_message() << server.Log();
  std::vector<std::string> kinds;
  for (const v1::ArtifactInfo& a : status.artifacts())
    kinds.push_back(a.kind());
  EXPECT_THAT(kinds, ::testing::Contains("labels"));
  EXPECT_THAT(kinds, ::testing::Contains("surface"));
  r = Cli(Cat({"fetch", id, "--out", dir / "fetched"}, server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err;
  ExpectSameResults(dir / "local", dir / "fetched");
}

// A DICOM SEG (written by `interslice run --seg` on a region of the series)
// uploaded with the series it references, every 5th slice a key slice.
TEST(FillServerTest, DicomSegFilledByTheServerEqualsInProcess) {
  TempDir dir;
  CommandResult r =
      Cli({"run", kSeries, "--threshold", "300", "--roi", "200,40,0,296,136,4",
           "--method", "direct", "--factor", "5", "--seg", "--volume", "nrrd",
           "--mesh", "none", "--quiet", "--out", dir / "run"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const std::string seg = dir / "run/seg.dcm";
  const std::string reference = dir / "run/series-intensity";
  const FillJobReport local =
      RunLocally(seg, reference, dir / "local", {0, 5, 10, 15});
  EXPECT_EQ(local.input_kind, "seg-binary");
  // One worker, two solver threads: the results must not depend on the
  // thread count.
  ServerProcess server({.spool = dir / "spool", .log = dir / "server.log"});
  ASSERT_TRUE(server.Start());
  // The SEG sits in the series' folder: the client must not upload it as a
  // slice of the series too.
  fs::copy_file(seg, reference + "/seg.dcm");
  r = Cli(Cat({"fill", reference + "/seg.dcm", "--reference", reference,
               "--key-slices", "0-15:5", "--method", "direct", "--volume",
               "nii,nrrd", "--mesh", "stl", "--out", dir / "remote"},
              server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err << server.Log();
  ExpectSameResults(dir / "local", dir / "remote");
}

// Admission: a fill spec the server cannot run is refused before the job
// exists, INVALID_ARGUMENT naming the field; a label that is not drawn fails
// the job with a message naming it.
TEST(FillServerTest, BadFillSpecsAreRefusedWithTheReason) {
  TempDir dir;
  const std::string labels = WriteLabelMap(dir / "drawn.nii.gz");
  // One worker, two solver threads: the results must not depend on the
  // thread count.
  ServerProcess server({.spool = dir / "spool", .log = dir / "server.log"});
  ASSERT_TRUE(server.Start());
  std::vector<UploadFile> files = SeriesFiles(kSeries);
  files.push_back({labels, "drawn.nii.gz"});
  v1::JobSpec good;
  good.mutable_fill()->set_segmentation_file("drawn.nii.gz");

  struct Case {
    std::string what;
    v1::JobSpec spec;
    std::vector<UploadFile> files;
    std::string message;
  };
  std::vector<Case> cases;
  {
    v1::JobSpec s = good;
    s.mutable_fill()->set_segmentation_file("other.nii.gz");
    cases.push_back({"missing segmentation", s, files,
                     "spec.fill.segmentation_file names none of the 5 "
                     "uploaded files"});
  }
  {
    v1::JobSpec s = good;
    s.mutable_fill()->clear_segmentation_file();
    cases.push_back(
        {"no segmentation named", s, files, "segmentation_file is required"});
  }
  {
    v1::JobSpec s = good;
    s.mutable_fill()->add_labels(0);
    cases.push_back(
        {"label 0", s, files, "spec.fill.labels: 0 is not a label (1..65535)"});
  }
  {
    v1::JobSpec s = good;
    s.mutable_fill()->add_labels(70000);
    cases.push_back({"label 70000", s, files,
                     "spec.fill.labels: 70000 is not a label (1..65535)"});
  }
  {
    v1::JobSpec s = good;
    s.mutable_fill()->add_key_slices(2);
    s.mutable_fill()->add_key_slices(2);
    cases.push_back({"repeated key slice", s, files,
                     "spec.fill.key_slices: slice 2 is repeated"});
  }
  {
    v1::JobSpec s = good;
    s.set_threshold(300);
    cases.push_back(
        {"threshold", s, files, "spec.threshold is not used by fill jobs"});
  }
  {
    v1::JobSpec s = good;
    s.set_method(static_cast<v1::SolverMethod>(42));
    cases.push_back({"method 42", s, files, "spec.method: unknown method 42"});
  }
  cases.push_back(
      {"segmentation only", good, {files.back()}, "file_count must be >= 2"});
  {
    // Two files under the segmentation's name.
    std::vector<UploadFile> twice = files;
    twice.push_back({labels, "drawn.nii.gz"});
    cases.push_back({"two segmentations", good, twice,
                     "two uploaded files carry the name"});
  }
  // Label names: named but not uploaded, uploaded twice, not a colour
  // table or JSON, the segmentation's own file.
  const std::string names = dir / "names.csv";
  std::ofstream(names) << "1,Bone\n2,Soft tissue\n";
  {
    v1::JobSpec s = good;
    s.mutable_fill()->set_label_names_file("names.csv");
    cases.push_back({"label names not uploaded", s, files,
                     "spec.fill.label_names_file names none of the 5 "
                     "uploaded files"});
    std::vector<UploadFile> twice = files;
    twice.push_back({names, "names.csv"});
    twice.push_back({names, "names.csv"});
    cases.push_back({"label names twice", s, twice,
                     "two uploaded files carry the name given as "
                     "spec.fill.label_names_file"});
    // Only the segmentation and its names: no series.
    cases.push_back({"no series",
                     s,
                     {files.back(), {names, "names.csv"}},
                     "file_count must be >= 3"});
  }
  {
    v1::JobSpec s = good;
    s.mutable_fill()->set_label_names_file("names.xlsx");
    cases.push_back({"label names as a spreadsheet", s, files,
                     "spec.fill.label_names_file: must name a colour table"});
    s.mutable_fill()->set_label_names_file("drawn.nii.gz");
    cases.push_back({"label names = segmentation", s, files,
                     "spec.fill.label_names_file names the segmentation's "
                     "file"});
  }
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    std::string id;
    const grpc::Status s = Submit(server, c.spec, c.files, &id);
    EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << s.error_message();
    EXPECT_THAT(s.error_message(), HasSubstr(c.message));
  }

  // Accepted, but label 9 is not drawn: the job fails naming it, and the
  // client says so in one line.
  CommandResult r = Cli(Cat({"fill", labels, "--reference", kSeries, "--labels",
                             "1,9", "--mesh", "none", "--out", dir / "out"},
                            server.ServerFlag()));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_THAT(r.err, HasSubstr("9"));
  EXPECT_THAT(r.err, HasSubstr("interslice: error:"));
  // Accepted, but the label names name label 9, which the map does not
  // hold: the job fails naming it, nothing to fetch.
  const std::string unknown = dir / "unknown.csv";
  std::ofstream(unknown) << "1,Bone\n9,Nothing\n";
  r = Cli(Cat({"fill", labels, "--reference", kSeries, "--label-names", unknown,
               "--seg", "--mesh", "none", "--out", dir / "unknown"},
              server.ServerFlag()));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_THAT(r.err, HasSubstr("interslice: error: the label names name label "
                               "9, which the label map does not hold"));
  EXPECT_FALSE(fs::exists(dir / "unknown/seg.dcm"));
  // A bad row names the line, not the server's or the client's path.
  const std::string bad_row = dir / "bad-row.csv";
  std::ofstream(bad_row) << "1,Bone,0,0\n";
  r = Cli(Cat({"fill", labels, "--reference", kSeries, "--label-names", bad_row,
               "--seg", "--mesh", "none", "--out", dir / "bad-row"},
              server.ServerFlag()));
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_THAT(r.err, HasSubstr("label-names.csv line 1: expected "
                               "label,name[,R,G,B[,code]] (4 fields)"));
  EXPECT_THAT(r.err, ::testing::Not(HasSubstr(dir / "")));
  EXPECT_THAT(server.Log(), ::testing::Not(HasSubstr("bad-row.csv")));
  // The server carries on.
  r = Cli(Cat({"fill", labels, "--reference", kSeries, "--mesh", "none",
               "--out", dir / "ok"},
              server.ServerFlag()));
  EXPECT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(fs::exists(dir / "ok/labels.nii.gz"));
}

// --label-names over the wire: the sidecar is uploaded with the job (and
// not read as a slice of the series even when it sits in the series'
// folder); its names and colours reach seg.dcm's SegmentLabel and
// rtstruct.dcm's ROIName and ROIDisplayColor as in the in-process fill.
TEST(FillServerTest, LabelNamesReachTheServersSegAndRtStruct) {
  TempDir dir;
  const std::string labels = WriteLabelMap(dir / "drawn.nii.gz");
  fs::create_directories(dir / "series");
  for (const auto& e : fs::directory_iterator(kSeries)) {
    fs::copy_file(e.path(), fs::path(dir / "series") / e.path().filename());
  }
  const std::string names = dir / "series/names.json";
  std::ofstream(names)
      << R"([{"label": 1, "name": "Bone", "rgb": [250, 250, 210]},
             {"label": 2, "name": "Soft tissue", "rgb": [200, 90, 80],
              "type": {"scheme": "SCT", "value": "85756007",
                       "meaning": "Tissue"}}])";
  const std::vector<std::string> job = {
      "fill",   labels,  "--reference", dir / "series", "--label-names",
      names,    "--seg", "--rtstruct",  "--method",     "linear",
      "--mesh", "none",  "--volume",    "nrrd",         "--quiet"};
  CommandResult local = Cli(Cat(job, {"--out", dir / "local"}));
  ASSERT_EQ(local.exit_code, 0) << local.err;
  ServerProcess server({.spool = dir / "spool", .log = dir / "server.log"});
  ASSERT_TRUE(server.Start());
  CommandResult r =
      Cli(Cat(Cat(job, {"--out", dir / "remote"}), server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err << server.Log();

  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries({kSeries}, {}, ComputeContext{.threads = 1});
  ASSERT_TRUE(series.ok()) << series.status();
  const ReferenceSeries reference{series->image.grid,
                                  series->series_instance_uid,
                                  series->frame_of_reference_uid};
  for (const std::string out : {dir / "local", dir / "remote"}) {
    SCOPED_TRACE(out);
    absl::StatusOr<SegmentationInput> seg =
        ReadDicomSegmentation(out + "/seg.dcm", reference);
    ASSERT_TRUE(seg.ok()) << seg.status();
    ASSERT_EQ(seg->segments.size(), 2u);
    EXPECT_EQ(seg->segments[0].label, "Bone");
    EXPECT_EQ(seg->segments[1].label, "Soft tissue");
    EXPECT_EQ(seg->segments[1].type.meaning, "Tissue");
    absl::StatusOr<SegmentationInput> rt =
        ReadRtStruct(out + "/rtstruct.dcm", reference);
    ASSERT_TRUE(rt.ok()) << rt.status();
    ASSERT_EQ(rt->segments.size(), 2u);
    EXPECT_EQ(rt->segments[0].label, "Bone");
    EXPECT_EQ(*rt->segments[0].rgb, (std::array<uint8_t, 3>{250, 250, 210}));
    EXPECT_EQ(rt->segments[1].label, "Soft tissue");
    // The same filled labels as in-process: the sidecar was not taken for
    // a slice, and the label map is the same.
    EXPECT_TRUE(ReadFileOrEmpty(out + "/labels.nrrd") ==
                ReadFileOrEmpty(dir / "local/labels.nrrd"));
  }
}

// The detached form: `fill --server --submit` prints the job's id; list,
// watch, fetch and cancel then work as for an interpolation job, and fetch
// gives the in-process fill's files.
TEST(FillServerTest, SubmittedFillIsWatchedListedAndFetched) {
  TempDir dir;
  const std::string labels = WriteLabelMap(dir / "drawn.nii.gz");
  RunLocally(labels, kSeries, dir / "local");
  ServerProcess server({.spool = dir / "spool", .log = dir / "server.log"});
  ASSERT_TRUE(server.Start());
  CommandResult r =
      Cli(Cat({"fill", labels, "--reference", kSeries, "--method", "direct",
               "--volume", "nii,nrrd", "--mesh", "stl", "--submit", "--label",
               "fill of the week", "--deadline", "600"},
              server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err << server.Log();
  std::string id = r.out;
  while (!id.empty() && (id.back() == '\n' || id.back() == '\r')) id.pop_back();
  ASSERT_FALSE(id.empty());
  EXPECT_EQ(id.find('\n'), std::string::npos) << "one line: the id";

  CommandResult list = Cli(Cat({"list", "--all"}, server.ServerFlag()));
  ASSERT_EQ(list.exit_code, 0) << list.err;
  EXPECT_THAT(list.out, HasSubstr(id));
  EXPECT_THAT(list.out, HasSubstr("fill of the week"));
  CommandResult watch = Cli(Cat({"watch", id}, server.ServerFlag()));
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  EXPECT_THAT(watch.out, HasSubstr("job " + id + " succeeded"));
  r = Cli(Cat(
      {"fetch", id, "--out", dir / "fetched", "--report", dir / "fetched.json"},
      server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err;
  ExpectSameResults(dir / "local", dir / "fetched");
  std::ifstream in(dir / "fetched.json");
  const nlohmann::json report = nlohmann::json::parse(in);
  EXPECT_EQ(report["input"], "label-map");
  EXPECT_EQ(report["method"], "direct");
  // A finished job cannot be cancelled any more: it says so.
  CommandResult cancel = Cli(Cat({"cancel", id}, server.ServerFlag()));
  EXPECT_EQ(cancel.exit_code, 0) << cancel.err;
  EXPECT_THAT(cancel.out, HasSubstr("job " + id + ": succeeded"));

  // A queued or running one can: a second job, cancelled at once, ends
  // cancelled (or, on a fast machine, succeeded before the cancel arrived).
  r = Cli(Cat({"fill", labels, "--reference", kSeries, "--method", "auto",
               "--factor", "4", "--submit"},
              server.ServerFlag()));
  ASSERT_EQ(r.exit_code, 0) << r.err;
  std::string second = r.out;
  while (!second.empty() && second.back() == '\n') second.pop_back();
  cancel = Cli(Cat({"cancel", second}, server.ServerFlag()));
  EXPECT_EQ(cancel.exit_code, 0) << cancel.err;
  const v1::JobStatus ended = WaitForEnd(server, second);
  EXPECT_TRUE(ended.state() == v1::JOB_STATE_CANCELLED ||
              ended.state() == v1::JOB_STATE_SUCCEEDED)
      << ended.state();
  watch = Cli(Cat({"watch", second, "--quiet"}, server.ServerFlag()));
  if (ended.state() == v1::JOB_STATE_CANCELLED) {
    EXPECT_EQ(watch.exit_code, 1);
    EXPECT_THAT(watch.err, HasSubstr("cancelled"));
  }

  // The detached form's own mistakes: one line each, before any upload.
  for (const auto& [args, message] :
       std::vector<std::pair<std::vector<std::string>, std::string>>{
           {{"--submit", "--report", dir / "r.json"},
            "--report: a detached job's report is written by `interslice "
            "fetch JOB --report FILE`"},
           {{"--submit", "--out", dir / "nowhere"},
            "--out: a detached job's files are written by `interslice fetch "
            "JOB --out DIR`"},
           {{"--label", "x"}, "--label needs --submit"},
           {{}, "--out is required (or --submit for a detached job)"},
       }) {
    r = Cli(Cat(Cat({"fill", labels, "--reference", kSeries}, args),
                server.ServerFlag()));
    EXPECT_EQ(r.exit_code, 1) << message;
    EXPECT_THAT(r.err, HasSubstr(message));
  }
}

}  // namespace
}  // namespace interslice::testing
