// The DICOM node's RTSTRUCT path end to end (issue 24), with a real Orthanc
// and a real interslice-server on loopback:
//   a CT series (tests/data/ct-thick) and then an RTSTRUCT drawn on it
//   arrive by C-STORE (DCMTK's storescu); the rule's `fill:` fills the
//   RTSTRUCT between its key slices; the filled RTSTRUCT and SEG go to
//   Orthanc (`send_to`), where they must sit in the source's study, on its
//   frame of reference, with the input's ROIs (numbers, names, colours), and
//   be the objects `interslice fill` makes in-process from the same files
//   with the same options. Then `interslice fill --server --submit
//   --send-to` stores a SEG in the same study through the gRPC door.
// The RTSTRUCT is made by the CLI itself (`interslice fill --rtstruct
// --label-names`) from a label map drawn on the series, so no outside file
// is needed.
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/dicom/series_reader.h"
#include "core/labels/segmentation_reader.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/made_elsewhere.h"
#include "tests/testing/orthanc.h"
#include "tests/testing/paths.h"
#include "tests/testing/process.h"
#include "tests/testing/server_process.h"
#include "tests/testing/temp_dir.h"
#include "tests/testing/wait_for.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcistrmb.h"

namespace interslice::testing {
namespace {

namespace fs = std::filesystem;
using ::testing::ElementsAre;
using ::testing::HasSubstr;

const std::string kCli = ::interslice::testing::CliPath();
const std::string kStoreScu = "/usr/bin/storescu";  // Debian's dcmtk
const std::string kSeries =
    std::string(::interslice::testing::TestDataDir()) + "/ct-thick";
// The node's fill: the RTSTRUCT's first and last slice are its key slices;
// the slices between are filled by the exact refinement.
const std::vector<std::string> kFill = {"--key-slices", "0,3",    "--method",
                                        "direct",       "--mesh", "none",
                                        "--volume",     "nrrd"};

std::string Tag(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  item.findAndGetOFStringArray(tag, value);
  return value.c_str();
}

std::unique_ptr<DcmFileFormat> Load(const std::string& path) {
  auto file = std::make_unique<DcmFileFormat>();
  EXPECT_TRUE(file->loadFile(OFFilename(path.c_str())).good()) << path;
  return file;
}

// An RTSTRUCT's ROIs: ROI number -> name.
std::map<std::string, std::string> Rois(DcmItem& dataset) {
  std::map<std::string, std::string> rois;
  DcmItem* item = nullptr;
  for (unsigned long n = 0;
       dataset.findAndGetSequenceItem(DCM_StructureSetROISequence, item, n)
           .good();
       ++n) {
    rois[Tag(*item, DCM_ROINumber)] = Tag(*item, DCM_ROIName);
  }
  return rois;
}

// ROI number -> ROIDisplayColor of an RTSTRUCT.
std::map<std::string, std::string> RoiColours(DcmItem& dataset) {
  std::map<std::string, std::string> colours;
  DcmItem* item = nullptr;
  for (unsigned long n = 0;
       dataset.findAndGetSequenceItem(DCM_ROIContourSequence, item, n).good();
       ++n) {
    colours[Tag(*item, DCM_ReferencedROINumber)] =
        Tag(*item, DCM_ROIDisplayColor);
  }
  return colours;
}

// Two touching labels drawn on the 4-slice series, on every slice: bone
// (>= 300 HU) and the soft tissue next to it (0..300 HU) in a box.
void WriteLabelMap(const std::string& path) {
  absl::StatusOr<DicomSeries> series =
      ReadDicomSeries({kSeries}, {}, ComputeContext{.threads = 1});
  ASSERT_TRUE(series.ok()) << series.status();
  Volume<uint16_t> labels;
  labels.grid = series->image.grid;
  labels.data.assign(labels.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < labels.grid.size[2]; ++k) {
    for (int64_t j = 150; j < 350; ++j) {
      for (int64_t i = 150; i < 350; ++i) {
        const float hu = series->image.at(i, j, k);
        labels.at(i, j, k) = hu >= 300 ? 1 : hu >= 0 ? 2 : 0;
      }
    }
  }
  ASSERT_TRUE(WriteVolume(labels, path).ok());
}

TEST(FillRtStructOrthancTest,
     RtStructAfterItsSeriesIsFilledAndStoredInOrthanc) {
  TempDir dir("interslice_fill_rtstruct_");
  const fs::path root = dir.path();

  // The input: an RTSTRUCT with named, coloured ROIs made by the CLI.
  const std::string labels = (root / "drawn.nii.gz").string();
  WriteLabelMap(labels);
  const std::string names = (root / "names.csv").string();
  std::ofstream(names) << "label,name,R,G,B\n1,Bone,250,250,210\n"
                          "2,Soft tissue,200,90,80\n";
  CommandResult made = RunCommand(
      {kCli, "fill", labels, "--reference", kSeries, "--label-names", names,
       "--rtstruct", "--method", "linear", "--mesh", "none", "--volume", "none",
       "--quiet", "--out", (root / "made").string()},
      300);
  ASSERT_EQ(made.exit_code, 0) << made.err;
  const std::string rtstruct = (root / "made" / "rtstruct.dcm").string();
  // It stands for a person's RTSTRUCT: the node takes its own results only
  // when a rule asks (issue 39).
  ASSERT_TRUE(MarkAsMadeElsewhere(rtstruct).ok());
  auto input = Load(rtstruct);
  const std::map<std::string, std::string> input_rois =
      Rois(*input->getDataset());
  ASSERT_EQ(input_rois.size(), 2u);
  EXPECT_EQ(input_rois.at("1"), "Bone");
  EXPECT_EQ(input_rois.at("2"), "Soft tissue");

  // What the node must make: `interslice fill` in this process's way.
  CommandResult local = RunCommand(
      Cat(Cat({kCli, "fill", rtstruct, "--reference", kSeries}, kFill),
          {"--seg", "--threads", "1", "--quiet", "--out",
           (root / "local").string()}),
      300);
  ASSERT_EQ(local.exit_code, 0) << local.err;
  ASSERT_TRUE(fs::exists(root / "local" / "seg.dcm"));
  ASSERT_TRUE(fs::exists(root / "local" / "rtstruct.dcm"));

  // The PACS holds the source study; the node stores its results there.
  const int node_port = FreeTcpPort();
  auto orthanc =
      Orthanc::Start((root / "orthanc").string(),
                     {{"interslice", "INTERSLICE", "127.0.0.1", node_port}});
  ASSERT_TRUE(orthanc.ok()) << orthanc.status();
  absl::StatusOr<int> uploaded = (*orthanc)->UploadFolder(kSeries);
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  ASSERT_EQ(*uploaded, 4);
  auto source = Load(kSeries + "/I10.dcm");
  const std::string study = Tag(*source->getDataset(), DCM_StudyInstanceUID);
  const std::string series = Tag(*source->getDataset(), DCM_SeriesInstanceUID);
  const std::string frame = Tag(*source->getDataset(), DCM_FrameOfReferenceUID);

  const std::string peers = (root / "peers.yaml").string();
  std::ofstream(peers) << "peers:\n  - {name: orthanc, ae_title: "
                       << (*orthanc)->ae_title() << ", host: 127.0.0.1, port: "
                       << (*orthanc)->dicom_port()
                       << "}\n  - {name: tools, ae_title: STORESCU, host: "
                          "127.0.0.1, port: 1}\n";
  const std::string rules = (root / "rules.yaml").string();
  std::ofstream(rules) << "stable_seconds: 1\n"
                          "rules:\n"
                          "  - name: fill-rt\n"
                          "    match: {modality: RTSTRUCT}\n"
                          "    fill: {key_slices: [0, 3], method: direct, "
                          "mesh: none, volume: [nrrd]}\n"
                          "    send_to: [orthanc]\n";
  ServerProcess server(ServerOptions{
      .spool = (root / "spool").string(),
      .log = (root / "server.log").string(),
      .extra = {"--dicom-listen", absl::StrCat("127.0.0.1:", node_port),
                "--dicom-ae", "INTERSLICE", "--dicom-peers", peers, "--rules",
                rules, "--delivery-retry", "0.2", "--delivery-retry-max", "1"},
      .threads_per_job = 1});
  ASSERT_TRUE(server.Start());
  const std::vector<std::string> client = server.ServerFlag();
  const auto store = [&](const std::vector<std::string>& options,
                         const std::vector<std::string>& files) {
    return RunCommand(
        Cat(Cat(Cat({kStoreScu}, options),
                {"-aec", "INTERSLICE", "127.0.0.1", std::to_string(node_port)}),
            files),
        120);
  };

  // The series first: no rule takes a CT series, so it is held for the
  // segmentations that may follow.
  std::vector<std::string> series_files;
  for (const auto& e : fs::directory_iterator(kSeries)) {
    if (e.path().extension() == ".dcm") {
      series_files.push_back(e.path().string());
    }
  }
  ASSERT_EQ(series_files.size(), 4u);
  CommandResult stored = store({}, series_files);
  ASSERT_EQ(stored.exit_code, 0) << stored.err << server.Log();
  ASSERT_TRUE(WaitFor(
      [&] {
        return server.Log().find("no rule of rule set") != std::string::npos;
      },
      std::chrono::seconds(60)))
      << server.Log();
  // Then the RTSTRUCT (-R: only its own SOP class is proposed).
  stored = store({"-R"}, {rtstruct});
  ASSERT_EQ(stored.exit_code, 0) << stored.err << server.Log();

  // The fill job, its results delivered to Orthanc.
  std::string job;
  ASSERT_TRUE(WaitFor(
      [&] {
        const CommandResult list =
            RunCommand(Cat({kCli, "list", "--all"}, client), 60);
        job = list.out.substr(0, list.out.find_first_of(" \n"));
        return list.exit_code == 0 && !job.empty();
      },
      std::chrono::seconds(120)))
      << server.Log();
  const CommandResult watch =
      RunCommand(Cat({kCli, "watch", job, "--wait-deliveries"}, client), 300);
  ASSERT_EQ(watch.exit_code, 0) << watch.err << server.Log();
  EXPECT_THAT(watch.out, HasSubstr("to orthanc: delivered, 2 of 2"));
  EXPECT_THAT(server.Log(), HasSubstr("(fill) made by rule fill-rt"));

  // In Orthanc: one study, the source's, now with the CT, the SEG and the
  // filled RTSTRUCT (the input RTSTRUCT went to the node, not the PACS).
  auto studies = (*orthanc)->GetJson("/studies?expand");
  ASSERT_TRUE(studies.ok()) << studies.status();
  ASSERT_EQ(studies->size(), 1u);
  EXPECT_EQ((*studies)[0]["MainDicomTags"]["StudyInstanceUID"], study);
  auto instances = (*orthanc)->GetJson("/instances?expand");
  ASSERT_TRUE(instances.ok()) << instances.status();
  std::map<std::string, std::string> by_modality;  // modality -> Orthanc id
  for (const auto& i : *instances) {
    auto file = (*orthanc)->InstanceFile(i["ID"].get<std::string>());
    ASSERT_TRUE(file.ok()) << file.status();
    DcmFileFormat format;
    DcmInputBufferStream stream;
    stream.setBuffer(file->data(), file->size());
    stream.setEos();
    format.transferInit();
    ASSERT_TRUE(format.read(stream).good());
    format.transferEnd();
    const std::string modality = Tag(*format.getDataset(), DCM_Modality);
    if (modality == "CT") continue;
    ASSERT_EQ(by_modality.count(modality), 0u) << "two " << modality;
    const std::string path = (root / (modality + ".dcm")).string();
    std::ofstream(path, std::ios::binary) << *file;
    by_modality[modality] = path;
  }
  ASSERT_EQ(by_modality.size(), 2u);
  ASSERT_EQ(by_modality.count("SEG"), 1u);
  ASSERT_EQ(by_modality.count("RTSTRUCT"), 1u);

  for (const auto& [modality, path] : by_modality) {
    SCOPED_TRACE(modality);
    auto result = Load(path);
    DcmDataset& ds = *result->getDataset();
    EXPECT_EQ(Tag(ds, DCM_StudyInstanceUID), study);
    EXPECT_EQ(Tag(ds, DCM_FrameOfReferenceUID), frame);
    // The node's object is the in-process fill's: same derived UIDs.
    auto expected =
        Load((root / "local" / (modality == "SEG" ? "seg.dcm" : "rtstruct.dcm"))
                 .string());
    EXPECT_EQ(Tag(ds, DCM_SOPInstanceUID),
              Tag(*expected->getDataset(), DCM_SOPInstanceUID));
    EXPECT_EQ(Tag(ds, DCM_SeriesInstanceUID),
              Tag(*expected->getDataset(), DCM_SeriesInstanceUID));
  }

  // The RTSTRUCT's ROIs are the input's, on the source series, and its
  // contours are the in-process fill's.
  auto result = Load(by_modality["RTSTRUCT"]);
  DcmDataset& rt = *result->getDataset();
  EXPECT_EQ(Rois(rt), input_rois);
  EXPECT_EQ(RoiColours(rt), RoiColours(*input->getDataset()));
  EXPECT_THAT(RoiColours(rt), ElementsAre(::testing::Pair("1", "250\\250\\210"),
                                          ::testing::Pair("2", "200\\90\\80")));
  absl::StatusOr<DicomSeries> reference =
      ReadDicomSeries({kSeries}, {}, ComputeContext{.threads = 1});
  ASSERT_TRUE(reference.ok()) << reference.status();
  const ReferenceSeries ref{reference->image.grid, series, frame};
  absl::StatusOr<SegmentationInput> node_rt =
      ReadRtStruct(by_modality["RTSTRUCT"], ref);
  absl::StatusOr<SegmentationInput> local_rt =
      ReadRtStruct((root / "local" / "rtstruct.dcm").string(), ref);
  ASSERT_TRUE(node_rt.ok()) << node_rt.status();
  ASSERT_TRUE(local_rt.ok()) << local_rt.status();
  EXPECT_TRUE(node_rt->labels.data == local_rt->labels.data);
  int64_t labelled = 0;
  for (uint16_t v : node_rt->labels.data) labelled += v != 0;
  EXPECT_GT(labelled, 1000);
  // The SEG's segments carry the same names.
  absl::StatusOr<SegmentationInput> node_seg =
      ReadDicomSegmentation(by_modality["SEG"], ref);
  ASSERT_TRUE(node_seg.ok()) << node_seg.status();
  ASSERT_EQ(node_seg->segments.size(), 2u);
  EXPECT_EQ(node_seg->segments[0].label, "Bone");
  EXPECT_EQ(node_seg->segments[1].label, "Soft tissue");

  // The command line's door to the same peer: `fill --server --submit
  // --send-to` stores its SEG in the source's study too, with the names of
  // its --label-names sidecar.
  const CommandResult sent = RunCommand(
      Cat({kCli, "fill", labels, "--reference", kSeries, "--label-names", names,
           "--seg", "--method", "linear", "--mesh", "none", "--volume", "none",
           "--submit", "--send-to", "orthanc"},
          client),
      300);
  ASSERT_EQ(sent.exit_code, 0) << sent.err << server.Log();
  std::string sent_job = sent.out;
  while (!sent_job.empty() && sent_job.back() == '\n') sent_job.pop_back();
  const CommandResult sent_watch = RunCommand(
      Cat({kCli, "watch", sent_job, "--wait-deliveries"}, client), 300);
  ASSERT_EQ(sent_watch.exit_code, 0) << sent_watch.err << server.Log();
  EXPECT_THAT(sent_watch.out, HasSubstr("to orthanc: delivered, 1 of 1"));
  auto after = (*orthanc)->GetJson("/instances?expand");
  ASSERT_TRUE(after.ok()) << after.status();
  int segs = 0;
  for (const auto& i : *after) {
    auto file = (*orthanc)->InstanceFile(i["ID"].get<std::string>());
    ASSERT_TRUE(file.ok()) << file.status();
    const std::string path = (root / "after.dcm").string();
    std::ofstream(path, std::ios::binary) << *file;
    auto loaded = Load(path);
    DcmDataset& ds = *loaded->getDataset();
    if (Tag(ds, DCM_Modality) != "SEG") continue;
    ++segs;
    EXPECT_EQ(Tag(ds, DCM_StudyInstanceUID), study);
    absl::StatusOr<SegmentationInput> one = ReadDicomSegmentation(path, ref);
    ASSERT_TRUE(one.ok()) << one.status();
    ASSERT_EQ(one->segments.size(), 2u);
    EXPECT_EQ(one->segments[0].label, "Bone");
  }
  EXPECT_EQ(segs, 2);  // the rule's and the command line's

  EXPECT_EQ(server.Stop(), 0) << server.Log();
}

}  // namespace
}  // namespace interslice::testing
