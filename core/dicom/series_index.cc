#include "core/dicom/series_index.h"

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <map>
#include <mutex>
#include <string>
#include <system_error>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using dicom_internal::BaseName;
using dicom_internal::FileHeader;
using dicom_internal::FileKind;

bool IsSecondaryCapture(const std::string& sop_class_uid) {
  // 1.2.840.10008.5.1.4.1.1.7 and its multi-frame variants .7.1 - .7.4.
  const std::string root = UID_SecondaryCaptureImageStorage;
  return sop_class_uid.compare(0, root.size(), root) == 0;
}

}  // namespace

absl::StatusOr<std::vector<std::string>> CollectInputFiles(
    const std::vector<std::string>& paths) {
  namespace fs = std::filesystem;
  if (paths.empty()) {
    return absl::InvalidArgumentError("no input files or folders given");
  }
  std::vector<std::string> files;
  for (const std::string& path : paths) {
    std::error_code ec;
    const fs::file_status status = fs::status(path, ec);
    if (ec || !fs::exists(status)) {
      return absl::NotFoundError(
          absl::StrCat("input '", BaseName(path), "' does not exist"));
    }
    if (fs::is_directory(status)) {
      fs::recursive_directory_iterator it(
          path, fs::directory_options::skip_permission_denied, ec);
      for (; !ec && it != fs::recursive_directory_iterator();
           it.increment(ec)) {
        std::error_code type_ec;
        if (it->is_regular_file(type_ec)) files.push_back(it->path().string());
      }
      if (ec) {
        return absl::InvalidArgumentError(absl::StrCat(
            "cannot list folder '", BaseName(path), "': ", ec.message()));
      }
    } else if (fs::is_regular_file(status)) {
      files.push_back(path);
    }
  }
  // The same file reached twice (a folder and a file in it) would otherwise
  // look like two slices at the same position.
  std::map<std::string, std::string> by_identity;
  for (const std::string& file : files) {
    std::error_code ec;
    fs::path key = fs::weakly_canonical(file, ec);
    by_identity.emplace(ec ? file : key.string(), file);
  }
  files.clear();
  for (auto& [key, file] : by_identity) files.push_back(std::move(file));
  std::sort(files.begin(), files.end());
  return files;
}

DicomFileIndex IndexDicomHeaders(std::vector<FileHeader> headers) {
  DicomFileIndex index;
  index.headers = std::move(headers);
  const std::vector<FileHeader>& all = index.headers;
  // Keyed by FileHeader::series_key (the UID, or the inferred key), so that
  // the order, and with it the "no-uid-N" names, is stable.
  std::map<std::string, DicomSeriesGroup> by_key;
  std::map<std::string, bool> has_acquired;
  for (const FileHeader& h : all) {
    if (h.kind == FileKind::kImage && !IsSecondaryCapture(h.sop_class_uid)) {
      has_acquired[h.series_key] = true;
    }
  }
  for (size_t i = 0; i < all.size(); ++i) {
    const FileHeader& h = all[i];
    if (h.kind != FileKind::kImage) continue;
    if (IsSecondaryCapture(h.sop_class_uid) && has_acquired[h.series_key]) {
      continue;
    }
    DicomSeriesGroup& s = by_key[h.series_key];
    if (s.members.empty()) {
      s.summary.series_instance_uid = h.series_uid;
      s.summary.modality = h.modality;
      s.inferred = h.series_uid.empty();
    }
    s.members.push_back(i);
    ++s.summary.image_count;
  }
  int unnamed = 0;
  for (auto& [key, s] : by_key) {
    if (s.inferred) {
      s.summary.series_instance_uid = absl::StrCat("no-uid-", ++unnamed);
    }
    index.series.push_back(std::move(s));
  }
  return index;
}

absl::StatusOr<DicomFileIndex> IndexDicomFiles(
    const std::vector<std::string>& files, const ComputeContext& context) {
  std::vector<FileHeader> headers(files.size());
  std::atomic<bool> cancelled{false};
  size_t done = 0;  // guarded by progress_mutex
  std::mutex progress_mutex;
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, files.size(), 1),
        [&](const tbb::blocked_range<size_t>& range) {
          for (size_t i = range.begin(); i != range.end(); ++i) {
            if (cancelled.load(std::memory_order_relaxed)) return;
            if (!context.CheckCancelled().ok()) {
              cancelled = true;
              return;
            }
            headers[i] = dicom_internal::ScanFile(files[i]);
            if (context.progress) {
              // Counted under the lock so that fractions never go back.
              std::lock_guard<std::mutex> lock(progress_mutex);
              const size_t n = ++done;
              context.Report({.stage = "read",
                              .fraction = static_cast<double>(n) /
                                          static_cast<double>(files.size())});
            }
          }
        });
  });
  if (cancelled) return context.CheckCancelled();
  return IndexDicomHeaders(std::move(headers));
}

absl::StatusOr<const DicomSeriesGroup*> FindDicomSeries(
    const DicomFileIndex& index, const std::string& series_uid) {
  if (index.headers.empty()) {
    return absl::NotFoundError("no files in the input");
  }
  if (index.series.empty()) {
    return absl::NotFoundError(
        absl::StrCat("no DICOM image slices in the input (",
                     DescribeSkippedFiles(index), ")"));
  }
  if (series_uid.empty()) {
    if (index.series.size() > 1) {
      return absl::FailedPreconditionError(
          absl::StrCat("the input holds ", index.series.size(),
                       " image series; choose one by its SeriesInstanceUID "
                       "(--series-uid): ",
                       DescribeDicomSeries(index)));
    }
    return &index.series.front();
  }
  // A hostile file may carry a UID that reads like a "no-uid-N" name: then
  // the last series of that name in index order is taken.
  const DicomSeriesGroup* chosen = nullptr;
  for (const DicomSeriesGroup& s : index.series) {
    if (s.summary.series_instance_uid == series_uid) chosen = &s;
  }
  if (chosen == nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat("SeriesInstanceUID ", series_uid,
                     " is not in the input; image series present: ",
                     DescribeDicomSeries(index)));
  }
  return chosen;
}

std::string DescribeDicomSeries(const DicomFileIndex& index) {
  std::vector<std::string> parts;
  for (const DicomSeriesGroup& s : index.series) {
    std::string described = absl::StrFormat(
        "%s (%s, %d image%s", s.summary.series_instance_uid,
        s.summary.modality.empty() ? "no modality" : s.summary.modality,
        s.summary.image_count, s.summary.image_count == 1 ? "" : "s");
    if (s.inferred) {
      // Without a UID, a file name and the size tell the series apart.
      const FileHeader& h = index.headers[s.members.front()];
      absl::StrAppend(
          &described,
          absl::StrFormat(", no SeriesInstanceUID, %d x %d, e.g. %s", h.columns,
                          h.rows, BaseName(h.path)));
    }
    parts.push_back(absl::StrCat(described, ")"));
  }
  return absl::StrJoin(parts, ", ");
}

std::string DescribeSkippedFiles(const DicomFileIndex& index) {
  int64_t not_dicom = 0, dicomdir = 0, not_image = 0;
  std::string refused;
  for (const FileHeader& h : index.headers) {
    if (h.kind == FileKind::kNotDicom) {
      ++not_dicom;
      if (!h.problem.ok() && refused.empty()) {
        refused = absl::StrCat("; refused: ", h.problem.message());
      }
    }
    if (h.kind == FileKind::kDicomDir) ++dicomdir;
    if (h.kind == FileKind::kNotImage) ++not_image;
  }
  return absl::StrFormat(
      "%d file(s) skipped: %d not DICOM or unreadable, %d DICOMDIR, %d DICOM "
      "objects that are not image slices with position and orientation%s",
      index.headers.size(), not_dicom, dicomdir, not_image, refused);
}

std::vector<std::string> DicomSeriesNotes(const DicomFileIndex& index,
                                          const DicomSeriesGroup& series) {
  int64_t no_series = 0, class_from_meta = 0, no_class = 0, no_instance = 0,
          no_study = 0, no_frame = 0;
  std::vector<std::string> grouped_by;
  for (size_t m : series.members) {
    const FileHeader& h = index.headers[m];
    if (h.series_uid.empty()) {
      if (no_series++ == 0) {
        if (!h.frame_of_reference_uid.empty()) {
          grouped_by.push_back("frame of reference");
        }
        if (!h.modality.empty()) grouped_by.push_back("modality");
        if (!h.series_number.empty()) grouped_by.push_back("series number");
        grouped_by.push_back("orientation");
        grouped_by.push_back("size");
      }
    }
    if (h.sop_class_from_meta) ++class_from_meta;
    if (h.sop_class_uid.empty()) ++no_class;
    if (h.sop_instance_uid.empty()) ++no_instance;
    if (h.study_uid.empty()) ++no_study;
    if (h.frame_of_reference_uid.empty()) ++no_frame;
  }
  std::vector<std::string> notes;
  auto files = [](int64_t n) {
    return absl::StrCat(n, n == 1 ? " file" : " files");
  };
  if (no_series > 0) {
    notes.push_back(absl::StrCat("SeriesInstanceUID missing on ",
                                 files(no_series), ": series grouped by ",
                                 absl::StrJoin(grouped_by, ", "),
                                 " and pixel spacing"));
  }
  if (class_from_meta > 0) {
    notes.push_back(absl::StrCat(
        "SOPClassUID missing on ", files(class_from_meta),
        ": taken from the file meta header (MediaStorageSOPClassUID)"));
  }
  if (no_class > 0) {
    notes.push_back(absl::StrCat(
        "SOPClassUID missing on ", files(no_class),
        ", also in the file meta header: read as image slices by their "
        "geometry"));
  }
  if (no_instance > 0) {
    notes.push_back(
        absl::StrCat("SOPInstanceUID missing on ", files(no_instance)));
  }
  if (no_study > 0) {
    notes.push_back(
        absl::StrCat("StudyInstanceUID missing on ", files(no_study)));
  }
  if (no_frame > 0) {
    notes.push_back(
        absl::StrCat("FrameOfReferenceUID missing on ", files(no_frame)));
  }
  return notes;
}

}  // namespace interslice
