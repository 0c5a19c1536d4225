// Part of the DICOM series reader (series_reader.h): from input paths to the
// image series they hold, reading headers only (never pixel data).
//
//   CollectInputFiles   paths -> the files to look at
//   IndexDicomFiles     files -> one scanned header per file, grouped into
//                       image series (IndexDicomHeaders: the grouping alone)
//   FindDicomSeries     the series a read is about (by UID or name)
//   DescribeDicomSeries the listing of series used in error messages
//
// Grouping (see series_reader.h for why): by SeriesInstanceUID, or for files
// without one by FileHeader::series_key (what a series keeps constant: frame
// of reference, modality, series number, orientation, size, pixel spacing).
// Such a series is named "no-uid-1", "no-uid-2", ... in the order of its key,
// and the name selects it like a UID. Only FileKind::kImage files are
// members; secondary captures that share a series with acquired images
// (screenshots, dose reports) are left out of it. Files whose header has a
// problem are members of their series all the same: the problem surfaces
// when that series is laid out (series_layout.h), so a broken file of another
// series never prevents reading a good one.
//
// Messages name files by base name only and never show patient data; UIDs
// appear only in the series listing, which exists to let the user choose
// one.
#ifndef INTERSLICE_CORE_DICOM_SERIES_INDEX_H_
#define INTERSLICE_CORE_DICOM_SERIES_INDEX_H_

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/dicom/dicom_header.h"

namespace interslice {

// The files of `paths` (files, and folders searched recursively; entries
// that are neither are skipped), sorted and without duplicates (a file
// reached twice, e.g. through its folder and by its own name, is listed
// once, under the name it was first reached by), so that results do not
// depend on directory listing order. Errors: INVALID_ARGUMENT when
// `paths` is empty or a folder cannot be listed; NOT_FOUND when a path does
// not exist. Messages name the path by its base name only. Folders without
// files give an empty list, not an error.
absl::StatusOr<std::vector<std::string>> CollectInputFiles(
    const std::vector<std::string>& paths);

// One series found in the input (for listings and error messages).
struct DicomSeriesSummary {
  // The UID, or for a series without one its name ("no-uid-1", ...).
  std::string series_instance_uid;
  std::string modality;
  int64_t image_count = 0;
};

// One image series of an index.
struct DicomSeriesGroup {
  // summary.series_instance_uid is the UID, or for a series grouped without
  // one the name that selects it ("no-uid-1", ...); image_count is
  // members.size().
  DicomSeriesSummary summary;
  std::vector<size_t> members;  // indices into DicomFileIndex::headers
  bool inferred = false;        // grouped without a SeriesInstanceUID
};

struct DicomFileIndex {
  // One per scanned file, in the order of the files given (sorted, from
  // CollectInputFiles); members of every series are listed in that order.
  std::vector<dicom_internal::FileHeader> headers;
  // Image series ordered by their UID (or inferred key): a stable order for
  // messages and for the "no-uid-N" names.
  std::vector<DicomSeriesGroup> series;
};

// Groups scanned headers into image series (no I/O).
DicomFileIndex IndexDicomHeaders(
    std::vector<dicom_internal::FileHeader> headers);

// Scans the header of every file (dicom_header.h ScanFile: values longer
// than 4 KiB stay on disk, so pixel data is never read) and groups them
// (IndexDicomHeaders). Unreadable, non-DICOM and non-image files are kept
// in `headers` with their kind; no file on its own makes this fail.
// Threading: context.threads workers (0 = all cores); headers come out in
// file order whatever the number. Progress: ProgressEvent{stage "read",
// fraction = files scanned / files}, never decreasing, reported once per
// file. Cancellation: polled before each file; returns context's CANCELLED
// or DEADLINE_EXCEEDED status.
absl::StatusOr<DicomFileIndex> IndexDicomFiles(
    const std::vector<std::string>& files, const ComputeContext& context);

// The series a read is about. `series_uid` names one (a UID, or a "no-uid-N"
// name); empty means "the only one". Errors:
// - NOT_FOUND "no files in the input" when the index holds no file;
//   NOT_FOUND "no DICOM image slices in the input (...)", with
//   DescribeSkippedFiles, when it holds no image series.
// - FAILED_PRECONDITION when `series_uid` is empty and there are several
//   series, or when no series has that UID or name; both list the series
//   present (DescribeDicomSeries).
// The result points into `index`.
absl::StatusOr<const DicomSeriesGroup*> FindDicomSeries(
    const DicomFileIndex& index, const std::string& series_uid);

// "UID (MODALITY, N images), ..." for every series of the index, in index
// order; a series without a UID is shown by name with "no SeriesInstanceUID",
// its Columns x Rows and one file's base name, which tell such series apart.
std::string DescribeDicomSeries(const DicomFileIndex& index);

// "N file(s) skipped: a not DICOM or unreadable, b DICOMDIR, c DICOM objects
// that are not image slices with position and orientation", counting every
// header of the index (called when no image series is left, so all of them
// were skipped), plus "; refused: <reason>" for the first file refused
// before parsing (e.g. sequences nested too deeply).
std::string DescribeSkippedFiles(const DicomFileIndex& index);

// What was inferred or found missing in the series' files, one sentence each
// (DicomSeries::notes in series_reader.h); never UIDs or patient data.
std::vector<std::string> DicomSeriesNotes(const DicomFileIndex& index,
                                          const DicomSeriesGroup& series);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_SERIES_INDEX_H_
