#include "core/dicom/series_reader.h"

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/sha256.h"
#include "core/common/status_macros.h"
#include "core/dicom/dicom_header.h"
#include "core/dicom/pixel_decode.h"
#include "core/dicom/series_index.h"
#include "core/dicom/series_layout.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/oflog/oflog.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using dicom_internal::FileHeader;

// The frames of one file that the stack uses, and where they go.
struct FileFrames {
  size_t header = 0;
  std::vector<DicomFrameTarget> frames;
};

// Decodes every file of the stack into `image` (pixel_decode.h), one file
// per task, reporting the second half of the read stage's progress. Files
// after the first failing one (along the stack) are skipped, but every file
// before it is still tried, so the error reported is the same whatever the
// scheduling.
absl::Status DecodeStack(const std::vector<FileHeader>& headers,
                         const std::vector<FileFrames>& files,
                         const ComputeContext& context) {
  const size_t n = files.size();
  std::vector<absl::Status> statuses(n);
  std::atomic<size_t> first_failed{n};
  size_t done = 0;  // guarded by progress_mutex
  std::mutex progress_mutex;
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, n, 1),
        [&](const tbb::blocked_range<size_t>& range) {
          for (size_t t = range.begin(); t != range.end(); ++t) {
            if (t > first_failed.load(std::memory_order_relaxed)) return;
            absl::Status status = context.CheckCancelled();
            if (status.ok()) {
              status =
                  DecodeDicomFrames(headers[files[t].header], files[t].frames);
            }
            if (!status.ok()) {
              statuses[t] = std::move(status);
              size_t expected = first_failed.load();
              while (t < expected &&
                     !first_failed.compare_exchange_weak(expected, t)) {
              }
              return;
            }
            if (context.progress) {
              std::lock_guard<std::mutex> lock(progress_mutex);
              const size_t loaded = ++done;
              context.Report(
                  {.stage = "read", .fraction = 0.5 + 0.5 * loaded / n});
            }
          }
        });
  });
  for (const absl::Status& status : statuses) {
    INTERSLICE_RETURN_IF_ERROR(status);
  }
  return absl::OkStatus();
}

// The sentence on a stack whose FrameOfReferenceUIDs differ (see the header):
// counts only, never a UID.
std::string FrameOfReferenceNote(const DicomStackLayout& stack,
                                 const FileHeader& first) {
  std::string counts =
      stack.frame_of_reference_uids == 1
          ? std::string("1 UID")
          : absl::StrFormat("%d different UIDs", stack.frame_of_reference_uids);
  absl::StrAppendFormat(&counts, " among the %d slices", stack.order.size());
  if (stack.slices_without_frame_of_reference > 0) {
    absl::StrAppendFormat(&counts, ", %d without one",
                          stack.slices_without_frame_of_reference);
  }
  const std::string used =
      first.frame_of_reference_uid.empty()
          ? "the first slice (k = 0) has none, so the outputs get one named "
            "from the source"
          : "the outputs use the first slice's (k = 0)";
  return absl::StrCat(
      "FrameOfReferenceUID not the same on every slice (", counts,
      "): read as one stack because the geometry was checked (same "
      "orientation, Rows/Columns and PixelSpacing, distinct positions along "
      "one slice normal); ",
      used);
}

}  // namespace

void QuietDicomToolkitLogging() {
  // Errors reach the caller as absl::Status; DCMTK's own "E: ..." lines for
  // files it cannot parse would only duplicate them on stderr.
  OFLog::configure(OFLogger::FATAL_LOG_LEVEL);
}

absl::StatusOr<std::vector<DicomSeriesSummary>> ListDicomSeries(
    const std::vector<std::string>& paths) {
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<std::string> files,
                              CollectInputFiles(paths));
  INTERSLICE_ASSIGN_OR_RETURN(const DicomFileIndex index,
                              IndexDicomFiles(files, ComputeContext{}));
  std::vector<DicomSeriesSummary> result;
  for (const DicomSeriesGroup& s : index.series) result.push_back(s.summary);
  return result;
}

absl::StatusOr<DicomSeries> ReadDicomSeries(
    const std::vector<std::string>& paths, const DicomReadOptions& options,
    const ComputeContext& context) {
  RegisterDicomDecoders();
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // Index (headers only): the first half of the read stage's progress.
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<std::string> files,
                              CollectInputFiles(paths));
  if (files.empty()) {
    return absl::NotFoundError("no files in the input");
  }
  ComputeContext index_context = context;
  if (context.progress) {
    index_context.progress = [&context](const ProgressEvent& event) {
      context.Report({.stage = "read", .fraction = 0.5 * event.fraction});
    };
  }
  INTERSLICE_ASSIGN_OR_RETURN(const DicomFileIndex index,
                              IndexDicomFiles(files, index_context));
  INTERSLICE_ASSIGN_OR_RETURN(
      const DicomSeriesGroup* chosen,
      FindDicomSeries(index, options.series_instance_uid));
  const std::vector<FileHeader>& headers = index.headers;

  // Layout (headers only).
  INTERSLICE_ASSIGN_OR_RETURN(
      const DicomStackLayout stack,
      LayOutDicomStack(headers, chosen->members, options.volume,
                       options.strict_frame_of_reference));
  const int64_t voxels = stack.grid.VoxelCount();
  if (voxels > options.max_voxels) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the series has %d x %d x %d = %d voxels, more than the limit of %d "
        "(max_voxels)",
        stack.grid.size[0], stack.grid.size[1], stack.grid.size[2], voxels,
        options.max_voxels));
  }
  // Decoders (DCMTK's) decode every frame of a file, including those of
  // other volumes: the limit bounds each file's decoded size too, before
  // anything is allocated.
  std::vector<FileFrames> by_file;
  std::vector<std::pair<size_t, int>> frame_of_slice;  // (file, frame) per k
  {
    std::map<size_t, size_t> file_of_header;  // header -> index in by_file
    for (const DicomSliceRef& s : stack.order) {
      auto [it, inserted] = file_of_header.emplace(s.header, by_file.size());
      if (inserted) by_file.push_back({s.header, {}});
      frame_of_slice.emplace_back(it->second, s.frame);
    }
  }
  for (const FileFrames& f : by_file) {
    INTERSLICE_RETURN_IF_ERROR(
        CheckDecodedSize(headers[f.header], options.max_voxels));
  }

  // Decode: the second half of the read stage's progress.
  DicomSeries result;
  result.image.grid = stack.grid;
  result.image.data.resize(voxels);
  const int64_t plane = stack.grid.SliceVoxelCount();
  for (size_t k = 0; k < frame_of_slice.size(); ++k) {
    const auto [file, frame] = frame_of_slice[k];
    by_file[file].frames.push_back(
        {.frame = frame, .out = result.image.data.data() + k * plane});
  }
  INTERSLICE_RETURN_IF_ERROR(DecodeStack(headers, by_file, context));

  if (!stack.tilt_shift.empty()) {
    INTERSLICE_RETURN_IF_ERROR(CorrectGantryTilt(stack, result.image, context));
    result.gantry_tilt_degrees = stack.tilt_degrees;
  }

  for (size_t k = 0; k < stack.order.size(); ++k) {
    const DicomSliceRef& s = stack.order[k];
    const FileHeader& h = headers[s.header];
    DicomSliceInfo& slice = result.slices.emplace_back();
    slice.path = h.path;
    slice.frame = s.frame;
    slice.sop_instance_uid = h.sop_instance_uid;
    slice.image_position = s.position;
    slice.position_along_normal = stack.positions[k];
    slice.rescale_slope = s.rescale_slope;
    slice.rescale_intercept = s.rescale_intercept;
  }
  // An anonymiser that blanked the SOP Instance UIDs leaves the pixels as
  // what identifies the series (core/dicom_out names the study, frame of
  // reference and derived objects of such a source from it).
  if (std::any_of(
          result.slices.begin(), result.slices.end(),
          [](const DicomSliceInfo& s) { return s.sop_instance_uid.empty(); })) {
    Sha256 digest;
    digest.Update(std::string_view(
        reinterpret_cast<const char*>(result.image.data.data()),
        result.image.data.size() * sizeof(float)));
    result.pixel_digest = HexString(digest.Finish());
  }
  const FileHeader& first = headers[stack.order.front().header];
  result.series_instance_uid = first.series_uid;
  result.study_instance_uid = first.study_uid;
  result.frame_of_reference_uid = first.frame_of_reference_uid;
  result.modality = first.modality;
  result.sop_class_uid = first.sop_class_uid;
  result.volume = stack.order.front().volume;
  result.slice_thickness_mm = first.slice_thickness;
  result.notes = DicomSeriesNotes(index, *chosen);
  if (stack.frames_of_reference_differ) {
    result.warnings.push_back(FrameOfReferenceNote(stack, first));
    result.notes.push_back(result.warnings.back());
  }
  result.uniform_spacing = stack.uniform;
  result.min_gap_mm = stack.min_gap;
  result.max_gap_mm = stack.max_gap;
  result.skipped_files = static_cast<int64_t>(headers.size() - by_file.size());
  return result;
}

}  // namespace interslice
