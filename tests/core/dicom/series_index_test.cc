// The index on its own (core/dicom/series_index.h): collecting input files,
// grouping headers into series (in memory), scanning real files with
// progress and cancellation, and the listings used in messages.
#include "core/dicom/series_index.h"

#include <sys/stat.h>
#include <sys/types.h>

#include <cstddef>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"
#include "tests/testing/temp_dir.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using dicom_internal::FileHeader;
using dicom_internal::FileKind;
using ::testing::AnyOf;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::Not;

const fs::path kThick =
    fs::path(::interslice::testing::TestDataDir()) / "ct-thick";
const char kSecondaryCapture[] = "1.2.840.10008.5.1.4.1.1.7";
const char kCtImage[] = "1.2.840.10008.5.1.4.1.1.2";

class TempDir : public testing::TempDir {
 public:
  TempDir() : testing::TempDir("interslice_index_") {}
};

void Touch(const fs::path& path) { std::ofstream(path) << "not DICOM\n"; }

TEST(CollectInputFilesTest, FoldersAreSearchedRecursivelyAndSorted) {
  TempDir dir;
  fs::create_directories(dir.path() / "b" / "deeper");
  Touch(dir.path() / "c.txt");
  Touch(dir.path() / "b" / "deeper" / "a.txt");
  Touch(dir.path() / "a.txt");
  const auto files = CollectInputFiles({dir.str()});
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_THAT(*files, ElementsAre((dir.path() / "a.txt").string(),
                                  (dir.path() / "b/deeper/a.txt").string(),
                                  (dir.path() / "c.txt").string()));
}

TEST(CollectInputFilesTest, AFileReachedTwiceIsListedOnce) {
  TempDir dir;
  Touch(dir.path() / "one.txt");
  Touch(dir.path() / "two.txt");
  // The folder, a file of it by name, and the same file by another path.
  const std::string again =
      (dir.path() / "." / "one.txt").string();  // same file, other spelling
  const auto files =
      CollectInputFiles({(dir.path() / "one.txt").string(), dir.str(), again});
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_THAT(*files, ElementsAre((dir.path() / "one.txt").string(),
                                  (dir.path() / "two.txt").string()));
}

TEST(CollectInputFilesTest, ALinkAndItsTargetAreOneFile) {
  TempDir dir;
  Touch(dir.path() / "target.txt");
  fs::create_symlink(dir.path() / "target.txt", dir.path() / "link.txt");
  const auto files = CollectInputFiles({dir.str()});
  ASSERT_TRUE(files.ok()) << files.status();
  ASSERT_EQ(files->size(), 1u);
  EXPECT_THAT(files->front(),
              AnyOf(HasSubstr("target.txt"), HasSubstr("link.txt")));
}

TEST(CollectInputFilesTest, EntriesThatAreNeitherFilesNorFoldersAreSkipped) {
  TempDir dir;
  Touch(dir.path() / "file.txt");
  const fs::path fifo = dir.path() / "pipe";
  ASSERT_EQ(mkfifo(fifo.c_str(), 0600), 0);
  auto files = CollectInputFiles({dir.str()});
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_THAT(*files, ElementsAre((dir.path() / "file.txt").string()));
  // Given by name, too: skipped, not an error.
  files = CollectInputFiles({fifo.string()});
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_THAT(*files, IsEmpty());
}

TEST(CollectInputFilesTest, AnEmptyFolderGivesNoFiles) {
  TempDir dir;
  const auto files = CollectInputFiles({dir.str()});
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_THAT(*files, IsEmpty());
}

TEST(CollectInputFilesTest, NoPathsOrAMissingPathAreErrors) {
  EXPECT_EQ(CollectInputFiles({}).status().code(),
            absl::StatusCode::kInvalidArgument);
  TempDir dir;
  Touch(dir.path() / "file.txt");
  const auto missing = CollectInputFiles(
      {dir.str(), (dir.path() / "Doe^Jane" / "gone.dcm").string()});
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  // Only the base name: folder names of exports often hold patient names.
  EXPECT_EQ(missing.status().message(), "input 'gone.dcm' does not exist");
}

// A header of an image slice of `series_key` (the UID unless `inferred`).
FileHeader Image(const std::string& path, const std::string& series_key,
                 bool inferred = false) {
  FileHeader h;
  h.path = "/exports/Doe^Jane/" + path;
  h.kind = FileKind::kImage;
  h.series_key = series_key;
  h.series_uid = inferred ? "" : series_key;
  h.sop_class_uid = kCtImage;
  h.sop_instance_uid = "1.2.3." + path;
  h.study_uid = "1.2.3";
  h.frame_of_reference_uid = "1.2.3.4";
  h.modality = "CT";
  h.rows = 4;
  h.columns = 5;
  return h;
}

FileHeader Other(const std::string& path, FileKind kind) {
  FileHeader h;
  h.path = path;
  h.kind = kind;
  return h;
}

TEST(IndexDicomHeadersTest, GroupsImagesBySeriesInKeyOrder) {
  const DicomFileIndex index = IndexDicomHeaders(
      {Image("a", "1.9"), Other("notes.txt", FileKind::kNotDicom),
       Image("b", "1.10"), Image("c", "1.9"),
       Other("DICOMDIR", FileKind::kDicomDir),
       Other("sr.dcm", FileKind::kNotImage)});
  ASSERT_EQ(index.headers.size(), 6u);
  ASSERT_EQ(index.series.size(), 2u);
  // "1.10" < "1.9" as strings: the order of the keys, not of the files.
  EXPECT_EQ(index.series[0].summary.series_instance_uid, "1.10");
  EXPECT_THAT(index.series[0].members, ElementsAre(2));
  EXPECT_EQ(index.series[1].summary.series_instance_uid, "1.9");
  EXPECT_THAT(index.series[1].members, ElementsAre(0, 3));
  EXPECT_EQ(index.series[1].summary.image_count, 2);
  EXPECT_EQ(index.series[1].summary.modality, "CT");
  EXPECT_FALSE(index.series[1].inferred);
}

TEST(IndexDicomHeadersTest, SeriesWithoutUidAreNamedInKeyOrder) {
  const DicomFileIndex index =
      IndexDicomHeaders({Image("x", "key-b", true), Image("y", "key-a", true),
                         Image("z", "1.2.5")});
  ASSERT_EQ(index.series.size(), 3u);
  EXPECT_EQ(index.series[0].summary.series_instance_uid, "1.2.5");
  EXPECT_EQ(index.series[1].summary.series_instance_uid, "no-uid-1");
  EXPECT_THAT(index.series[1].members, ElementsAre(1));  // key-a
  EXPECT_TRUE(index.series[1].inferred);
  EXPECT_EQ(index.series[2].summary.series_instance_uid, "no-uid-2");
  EXPECT_THAT(index.series[2].members, ElementsAre(0));  // key-b
}

TEST(IndexDicomHeadersTest, SecondaryCapturesBesideAcquiredImagesAreLeftOut) {
  FileHeader screenshot = Image("shot", "1.5");
  screenshot.sop_class_uid = kSecondaryCapture;
  FileHeader multi_frame_capture = Image("shot2", "1.5");
  multi_frame_capture.sop_class_uid = std::string(kSecondaryCapture) + ".4";
  FileHeader lone_capture = Image("alone", "1.6");
  lone_capture.sop_class_uid = kSecondaryCapture;
  const DicomFileIndex index = IndexDicomHeaders(
      {screenshot, Image("a", "1.5"), multi_frame_capture, lone_capture});
  ASSERT_EQ(index.series.size(), 2u);
  EXPECT_THAT(index.series[0].members, ElementsAre(1));
  EXPECT_EQ(index.series[0].summary.image_count, 1);
  // A series of secondary captures only is still a series.
  EXPECT_THAT(index.series[1].members, ElementsAre(3));
}

TEST(IndexDicomHeadersTest, BrokenImagesStayMembersOfTheirSeries) {
  FileHeader broken = Image("b", "1.5");
  broken.problem = absl::InvalidArgumentError("b: truncated");
  const DicomFileIndex index = IndexDicomHeaders({Image("a", "1.5"), broken});
  ASSERT_EQ(index.series.size(), 1u);
  EXPECT_THAT(index.series[0].members, ElementsAre(0, 1));
}

TEST(FindDicomSeriesTest, NoFilesAndNoImagesAreNotFound) {
  auto found = FindDicomSeries(IndexDicomHeaders({}), "");
  EXPECT_EQ(found.status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(found.status().message(), "no files in the input");

  found = FindDicomSeries(
      IndexDicomHeaders({Other("a.txt", FileKind::kNotDicom),
                         Other("DICOMDIR", FileKind::kDicomDir)}),
      "");
  EXPECT_EQ(found.status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(found.status().message(),
            "no DICOM image slices in the input (2 file(s) skipped: 1 not "
            "DICOM or unreadable, 1 DICOMDIR, 0 DICOM objects that are not "
            "image slices with position and orientation)");
}

TEST(FindDicomSeriesTest, TheOnlySeriesOrTheOneNamed) {
  const DicomFileIndex one = IndexDicomHeaders({Image("a", "1.5")});
  auto found = FindDicomSeries(one, "");
  ASSERT_TRUE(found.ok()) << found.status();
  EXPECT_EQ(*found, &one.series[0]);

  const DicomFileIndex two = IndexDicomHeaders(
      {Image("a", "1.5"), Image("b", "1.6"), Image("c", "key", true)});
  found = FindDicomSeries(two, "1.6");
  ASSERT_TRUE(found.ok()) << found.status();
  EXPECT_EQ(*found, &two.series[1]);
  found = FindDicomSeries(two, "no-uid-1");
  ASSERT_TRUE(found.ok()) << found.status();
  EXPECT_EQ(*found, &two.series[2]);
}

TEST(FindDicomSeriesTest, SeveralOrAbsentListTheSeriesPresent) {
  const DicomFileIndex index = IndexDicomHeaders(
      {Image("a", "1.5"), Image("b", "1.5"), Image("c.dcm", "key", true)});
  const std::string listing =
      "1.5 (CT, 2 images), no-uid-1 (CT, 1 image, no SeriesInstanceUID, 5 x "
      "4, e.g. c.dcm)";
  EXPECT_EQ(DescribeDicomSeries(index), listing);

  auto found = FindDicomSeries(index, "");
  EXPECT_EQ(found.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(found.status().message(),
            "the input holds 2 image series; choose one by its "
            "SeriesInstanceUID (--series-uid): " +
                listing);

  found = FindDicomSeries(index, "1.7");
  EXPECT_EQ(found.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(found.status().message(),
            "SeriesInstanceUID 1.7 is not in the input; image series "
            "present: " +
                listing);
  EXPECT_THAT(found.status().message(), Not(HasSubstr("Doe^Jane")));
}

TEST(DescribeSkippedFilesTest, CountsEachKindAndTheFirstRefusal) {
  FileHeader refused = Other("deep.dcm", FileKind::kNotDicom);
  refused.problem = absl::InvalidArgumentError("deep.dcm: nested too deeply");
  FileHeader also_refused = Other("deeper.dcm", FileKind::kNotDicom);
  also_refused.problem = absl::InvalidArgumentError("deeper.dcm: too");
  EXPECT_EQ(DescribeSkippedFiles(IndexDicomHeaders(
                {Other("a.txt", FileKind::kNotDicom), refused, also_refused,
                 Other("sr.dcm", FileKind::kNotImage),
                 Other("pr.dcm", FileKind::kNotImage)})),
            "5 file(s) skipped: 3 not DICOM or unreadable, 0 DICOMDIR, 2 "
            "DICOM objects that are not image slices with position and "
            "orientation; refused: deep.dcm: nested too deeply");
}

TEST(DicomSeriesNotesTest, SaySentencesAboutMissingUidsWithoutValues) {
  const DicomFileIndex complete = IndexDicomHeaders({Image("a", "1.5")});
  EXPECT_THAT(DicomSeriesNotes(complete, complete.series[0]), IsEmpty());

  FileHeader a = Image("a", "key", true);
  a.series_number = "4";
  a.sop_class_uid = "1.2.840.10008.5.1.4.1.1.4";
  a.sop_class_from_meta = true;
  FileHeader b = Image("b", "key", true);
  b.series_number = "4";
  b.sop_class_uid.clear();
  b.sop_instance_uid.clear();
  b.study_uid.clear();
  b.frame_of_reference_uid.clear();
  const DicomFileIndex index = IndexDicomHeaders({a, b});
  ASSERT_EQ(index.series.size(), 1u);
  const std::vector<std::string> notes =
      DicomSeriesNotes(index, index.series[0]);
  EXPECT_THAT(
      notes,
      ElementsAre("SeriesInstanceUID missing on 2 files: series grouped by "
                  "frame of reference, modality, series number, orientation, "
                  "size and pixel spacing",
                  "SOPClassUID missing on 1 file: taken from the file meta "
                  "header (MediaStorageSOPClassUID)",
                  "SOPClassUID missing on 1 file, also in the file meta "
                  "header: read as image slices by their geometry",
                  "SOPInstanceUID missing on 1 file",
                  "StudyInstanceUID missing on 1 file",
                  "FrameOfReferenceUID missing on 1 file"));
  for (const std::string& note : notes) {
    EXPECT_THAT(note, Not(HasSubstr("1.2.")));
  }
}

// Four vendored CT slices, a text file and an empty file.
std::vector<std::string> ScannableFolder(const fs::path& dir) {
  for (const char* name : {"I10.dcm", "I20.dcm", "I30.dcm", "I40.dcm"}) {
    fs::copy_file(kThick / name, dir / name);
  }
  Touch(dir / "readme.txt");
  std::ofstream(dir / "empty.dcm").close();
  auto files = CollectInputFiles({dir.string()});
  EXPECT_TRUE(files.ok()) << files.status();
  return files.ok() ? *files : std::vector<std::string>{};
}

TEST(IndexDicomFilesTest, ScansEveryFileInFileOrder) {
  TempDir dir;
  const std::vector<std::string> files = ScannableFolder(dir.path());
  ASSERT_EQ(files.size(), 6u);
  for (int threads : {1, 2}) {
    ComputeContext context;
    context.threads = threads;
    const auto index = IndexDicomFiles(files, context);
    ASSERT_TRUE(index.ok()) << index.status();
    ASSERT_EQ(index->headers.size(), files.size());
    for (size_t i = 0; i < files.size(); ++i) {
      EXPECT_EQ(index->headers[i].path, files[i]);
    }
    // Sorted: I10..I40, empty.dcm, readme.txt.
    EXPECT_EQ(index->headers[0].kind, FileKind::kImage);
    EXPECT_EQ(index->headers[4].kind, FileKind::kNotDicom);
    EXPECT_EQ(index->headers[5].kind, FileKind::kNotDicom);
    ASSERT_EQ(index->series.size(), 1u);
    EXPECT_THAT(index->series[0].members, ElementsAre(0, 1, 2, 3));
    EXPECT_EQ(index->series[0].summary.modality, "CT");
    EXPECT_EQ(index->headers[0].rows, 512);
  }
}

TEST(IndexDicomFilesTest, ReportsOneRisingFractionPerFile) {
  TempDir dir;
  const std::vector<std::string> files = ScannableFolder(dir.path());
  std::mutex mutex;
  std::vector<double> fractions;
  ComputeContext context;
  context.threads = 2;
  context.progress = [&](const ProgressEvent& event) {
    std::lock_guard<std::mutex> lock(mutex);
    EXPECT_EQ(event.stage, "read");
    fractions.push_back(event.fraction);
  };
  ASSERT_TRUE(IndexDicomFiles(files, context).ok());
  ASSERT_EQ(fractions.size(), files.size());
  for (size_t i = 0; i < fractions.size(); ++i) {
    EXPECT_DOUBLE_EQ(fractions[i], (i + 1.0) / files.size()) << i;
  }
}

TEST(IndexDicomFilesTest, CancellationStopsTheScan) {
  TempDir dir;
  const std::vector<std::string> files = ScannableFolder(dir.path());
  CancellationToken token;
  token.Cancel();
  int reports = 0;
  ComputeContext context;
  context.cancel = &token;
  context.progress = [&reports](const ProgressEvent&) { ++reports; };
  const auto index = IndexDicomFiles(files, context);
  EXPECT_EQ(index.status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(reports, 0);
}

}  // namespace
}  // namespace interslice
