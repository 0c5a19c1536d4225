#include "core/dicom/series_reader.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <filesystem>
#include <functional>
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
#include "core/common/status_macros.h"
#include "core/dicom/dicom_header.h"
#include "core/dicom/gdcm_decode.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dccodec.h"
#include "dcmtk/dcmdata/dcdatset.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcpixel.h"
#include "dcmtk/dcmdata/dcpixseq.h"
#include "dcmtk/dcmdata/dcpxitem.h"
#include "dcmtk/dcmdata/dcrledrg.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcxfer.h"
#include "dcmtk/dcmjpeg/djdecode.h"
#include "dcmtk/dcmjpls/djdecode.h"
#include "dcmtk/oflog/oflog.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using dicom_internal::BaseName;
using dicom_internal::FileHeader;
using dicom_internal::FileKind;
using dicom_internal::PixelLayout;

// Tolerances of the stack checks (see the header and the issue).
constexpr double kOrientationTolerance = 1e-4;  // per component
constexpr double kPixelSpacingRelativeTolerance = 1e-4;
constexpr double kSamePositionTolerance = 1e-3;     // mm
constexpr double kSpacingAbsoluteTolerance = 0.01;  // mm
constexpr double kSpacingRelativeTolerance = 0.01;
constexpr double kTiltTolerance = 0.01;  // in-plane mm per mm along n
// ImageOrientationPatient is stored as decimal strings with a few digits;
// vectors this close to unit length and orthogonal are orthonormalised,
// anything further off is rejected.
constexpr double kOrthonormalTolerance = 1e-3;

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
Vec3 Cross(const Vec3& a, const Vec3& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
          a[0] * b[1] - a[1] * b[0]};
}
Vec3 Sub(const Vec3& a, const Vec3& b) {
  return {a[0] - b[0], a[1] - b[1], a[2] - b[2]};
}
Vec3 Scale(const Vec3& a, double s) { return {a[0] * s, a[1] * s, a[2] * s}; }
double Norm(const Vec3& a) { return std::sqrt(Dot(a, a)); }

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

namespace {

// Scans every header (in `arena` when given), reporting the first half of the
// read stage's progress.
absl::StatusOr<std::vector<FileHeader>> ScanHeaders(
    const std::vector<std::string>& files, tbb::task_arena* arena,
    const ComputeContext* context) {
  std::vector<FileHeader> headers(files.size());
  std::atomic<bool> cancelled{false};
  size_t done = 0;  // guarded by progress_mutex
  std::mutex progress_mutex;
  auto scan = [&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, files.size(), 1),
        [&](const tbb::blocked_range<size_t>& range) {
          for (size_t i = range.begin(); i != range.end(); ++i) {
            if (cancelled.load(std::memory_order_relaxed)) return;
            if (context != nullptr && !context->CheckCancelled().ok()) {
              cancelled = true;
              return;
            }
            headers[i] = dicom_internal::ScanFile(files[i]);
            if (context != nullptr && context->progress) {
              // Counted under the lock so that fractions never go back.
              std::lock_guard<std::mutex> lock(progress_mutex);
              const size_t n = ++done;
              context->Report(
                  {.stage = "read", .fraction = 0.5 * n / files.size()});
            }
          }
        });
  };
  if (arena != nullptr) {
    arena->execute(scan);
  } else {
    scan();
  }
  if (cancelled) return context->CheckCancelled();
  return headers;
}

struct Series {
  std::vector<size_t> members;  // indices into the headers, in path order
  // summary.series_instance_uid is the UID, or for series grouped without
  // one the name that selects it ("no-uid-1", ...).
  DicomSeriesSummary summary;
  bool inferred = false;  // grouped without a SeriesInstanceUID
};

bool IsSecondaryCapture(const std::string& sop_class_uid) {
  // 1.2.840.10008.5.1.4.1.1.7 and its multi-frame variants .7.1 - .7.4.
  const std::string root = UID_SecondaryCaptureImageStorage;
  return sop_class_uid.compare(0, root.size(), root) == 0;
}

// Image series by FileHeader::series_key: the SeriesInstanceUID, or the
// inferred key of files without one (ordered by key for stable messages and
// names). Secondary captures that share a series with acquired images
// (screenshots, dose reports, ...) are not slices of its stack and are left
// out.
std::map<std::string, Series> GroupSeries(
    const std::vector<FileHeader>& headers) {
  std::map<std::string, Series> series;
  std::map<std::string, bool> has_acquired;
  for (const FileHeader& h : headers) {
    if (h.kind == FileKind::kImage && !IsSecondaryCapture(h.sop_class_uid)) {
      has_acquired[h.series_key] = true;
    }
  }
  for (size_t i = 0; i < headers.size(); ++i) {
    const FileHeader& h = headers[i];
    if (h.kind != FileKind::kImage) continue;
    if (IsSecondaryCapture(h.sop_class_uid) && has_acquired[h.series_key]) {
      continue;
    }
    Series& s = series[h.series_key];
    if (s.members.empty()) {
      s.summary.series_instance_uid = h.series_uid;
      s.summary.modality = h.modality;
      s.inferred = h.series_uid.empty();
    }
    s.members.push_back(i);
    ++s.summary.image_count;
  }
  int unnamed = 0;
  for (auto& [key, s] : series) {
    if (s.inferred) {
      s.summary.series_instance_uid = absl::StrCat("no-uid-", ++unnamed);
    }
  }
  return series;
}

std::string DescribeSeries(const std::map<std::string, Series>& series,
                           const std::vector<FileHeader>& headers) {
  std::vector<std::string> parts;
  for (const auto& [key, s] : series) {
    std::string described = absl::StrFormat(
        "%s (%s, %d image%s", s.summary.series_instance_uid,
        s.summary.modality.empty() ? "no modality" : s.summary.modality,
        s.summary.image_count, s.summary.image_count == 1 ? "" : "s");
    if (s.inferred) {
      // Without a UID, a file name and the size tell the series apart.
      const FileHeader& h = headers[s.members.front()];
      absl::StrAppend(
          &described,
          absl::StrFormat(", no SeriesInstanceUID, %d x %d, e.g. %s", h.columns,
                          h.rows, BaseName(h.path)));
    }
    parts.push_back(absl::StrCat(described, ")"));
  }
  return absl::StrJoin(parts, ", ");
}

std::string DescribeSkipped(const std::vector<FileHeader>& headers) {
  int64_t not_dicom = 0, dicomdir = 0, not_image = 0;
  std::string refused;
  for (const FileHeader& h : headers) {
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
      headers.size(), not_dicom, dicomdir, not_image, refused);
}

// What the reader inferred about the chosen series' files (see
// DicomSeries::notes). Never UIDs or other patient data.
std::vector<std::string> InputNotes(const std::vector<FileHeader>& headers,
                                    const std::vector<size_t>& members) {
  int64_t no_series = 0, class_from_meta = 0, no_class = 0, no_instance = 0,
          no_study = 0, no_frame = 0;
  std::vector<std::string> grouped_by;
  for (size_t m : members) {
    const FileHeader& h = headers[m];
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

// One original slice: a single-frame file or one frame of an enhanced
// multi-frame file.
struct SliceRef {
  size_t header = 0;
  int frame = 0;  // 0-based frame number in the file
  Vec3 position = {0, 0, 0};
  std::array<double, 6> orientation = {1, 0, 0, 0, 1, 0};
  std::array<double, 2> pixel_spacing = {1, 1};
  double rescale_slope = 1, rescale_intercept = 0;
  std::string volume;  // FrameGeometry::volume; empty for single frames
};

std::vector<SliceRef> SlicesOf(const std::vector<FileHeader>& headers,
                               const std::vector<size_t>& members) {
  std::vector<SliceRef> slices;
  for (size_t m : members) {
    const FileHeader& h = headers[m];
    if (h.frames.empty()) {
      slices.push_back({m, 0, h.position, h.orientation, h.pixel_spacing,
                        h.rescale_slope, h.rescale_intercept, ""});
      continue;
    }
    for (size_t f = 0; f < h.frames.size(); ++f) {
      const dicom_internal::FrameGeometry& g = h.frames[f];
      slices.push_back({m, static_cast<int>(f), g.position, g.orientation,
                        g.pixel_spacing, g.rescale_slope, g.rescale_intercept,
                        g.volume});
    }
  }
  return slices;
}

std::string SliceName(const std::vector<FileHeader>& headers,
                      const SliceRef& s) {
  const FileHeader& h = headers[s.header];
  if (h.frames.empty()) return BaseName(h.path);
  return absl::StrCat(BaseName(h.path), " frame ", s.frame + 1);
}

std::string VolumeLabel(const std::string& volume) {
  return volume.empty() ? "single-frame images" : volume;
}

// Frames of different volumes (stacks, temporal positions, frame types such
// as magnitude and phase) share slice positions; one volume is read at a
// time: the only one, or options.volume.
absl::StatusOr<std::vector<SliceRef>> ChooseVolume(
    std::vector<SliceRef> slices, const DicomReadOptions& options) {
  std::map<std::string, int64_t> counts;
  for (const SliceRef& s : slices) ++counts[s.volume];
  if (counts.size() == 1 && options.volume.empty()) return slices;
  std::vector<std::string> listing;
  for (const auto& [volume, count] : counts) {
    listing.push_back(absl::StrFormat("\"%s\" (%d slice%s)",
                                      VolumeLabel(volume), count,
                                      count == 1 ? "" : "s"));
  }
  if (options.volume.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the series holds ", counts.size(),
        " volumes that share slice positions (stacks, temporal positions or "
        "frame types of multi-frame images); choose one (volume option): ",
        absl::StrJoin(listing, ", ")));
  }
  if (counts.count(options.volume) == 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("volume \"", options.volume,
                     "\" is not in the series; volumes present: ",
                     absl::StrJoin(listing, ", ")));
  }
  std::vector<SliceRef> chosen;
  for (SliceRef& s : slices) {
    if (s.volume == options.volume) chosen.push_back(std::move(s));
  }
  return chosen;
}

// The geometry of the stack and the order of its slices.
struct StackLayout {
  std::vector<SliceRef> order;    // sorted along the normal
  std::vector<double> positions;  // along the normal, in `order`
  Grid grid;
  bool uniform = true;
  double min_gap = 0, max_gap = 0;
  // Gantry tilt: the in-plane offset of each slice from the first, in
  // pixels along (i, j); empty when the stack is not tilted.
  std::vector<std::array<double, 2>> tilt_shift;
  double tilt_degrees = 0;
};

absl::Status CheckConsistent(const std::vector<FileHeader>& headers,
                             const SliceRef& ref, const SliceRef& s) {
  const FileHeader& rh = headers[ref.header];
  const FileHeader& h = headers[s.header];
  if (h.rows != rh.rows || h.columns != rh.columns) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "inconsistent Rows/Columns: %s is %d x %d (columns x rows) but %s is "
        "%d x %d",
        SliceName(headers, s), h.columns, h.rows, SliceName(headers, ref),
        rh.columns, rh.rows));
  }
  for (int c = 0; c < 6; ++c) {
    if (std::abs(s.orientation[c] - ref.orientation[c]) >
        kOrientationTolerance) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "inconsistent ImageOrientationPatient: %s differs from %s",
          SliceName(headers, s), SliceName(headers, ref)));
    }
  }
  for (int c = 0; c < 2; ++c) {
    const double a = s.pixel_spacing[c], b = ref.pixel_spacing[c];
    if (std::abs(a - b) >
        kPixelSpacingRelativeTolerance * std::max(std::abs(a), std::abs(b))) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "inconsistent PixelSpacing: %s has %g\\%g mm but %s has %g\\%g mm",
          SliceName(headers, s), s.pixel_spacing[0], s.pixel_spacing[1],
          SliceName(headers, ref), ref.pixel_spacing[0], ref.pixel_spacing[1]));
    }
  }
  return absl::OkStatus();
}

// INVALID_ARGUMENT when `value` (of a slice's file) is not the same for
// every slice: names the first slice, in path order, that differs from the
// value most slices have, and one that has it. `show` prints a value for the
// message; null when values must not appear (UIDs).
absl::Status CheckSameForAll(
    const std::vector<FileHeader>& headers, const std::vector<SliceRef>& slices,
    const std::string& attribute,
    const std::function<std::string(const FileHeader&)>& value,
    const std::function<std::string(const std::string&)>& show) {
  std::map<std::string, int64_t> counts;
  for (const SliceRef& s : slices) ++counts[value(headers[s.header])];
  if (counts.size() <= 1) return absl::OkStatus();
  std::string majority;
  int64_t most = 0;
  for (const auto& [v, count] : counts) {
    if (count > most) {
      most = count;
      majority = v;
    }
  }
  const SliceRef* odd = nullptr;
  const SliceRef* typical = nullptr;
  for (const SliceRef& s : slices) {
    const bool is_majority = value(headers[s.header]) == majority;
    if (!is_majority && odd == nullptr) odd = &s;
    if (is_majority && typical == nullptr) typical = &s;
  }
  const std::string odd_value = value(headers[odd->header]);
  const std::string others =
      absl::StrFormat("%d of the %d slices (e.g. %s)", most, slices.size(),
                      SliceName(headers, *typical));
  std::string difference;
  if (show) {
    auto text = [&show](const std::string& v) {
      return v.empty() ? std::string("none") : show(v);
    };
    difference = absl::StrCat("has ", text(odd_value), ", but ", others,
                              " have ", text(majority));
  } else if (odd_value.empty()) {
    difference = absl::StrCat("has none, but ", others, " have one");
  } else if (majority.empty()) {
    difference = absl::StrCat("has one, but ", others, " have none");
  } else {
    difference = absl::StrCat("has a different one from ", others);
  }
  return absl::InvalidArgumentError(
      absl::StrCat("inconsistent ", attribute, ": ", SliceName(headers, *odd),
                   " ", difference, "; the files do not form one series"));
}

// Attributes the stack relies on that must not change from slice to slice.
// Each would otherwise be accepted silently: a slice of another frame of
// reference or modality is not part of this volume, and another pixel
// layout means another acquisition or a broken export.
absl::Status CheckSeriesConsistent(const std::vector<FileHeader>& headers,
                                   const std::vector<SliceRef>& slices) {
  auto as_is = [](const std::string& v) { return v; };
  INTERSLICE_RETURN_IF_ERROR(CheckSameForAll(
      headers, slices, "FrameOfReferenceUID",
      [](const FileHeader& h) { return h.frame_of_reference_uid; }, nullptr));
  INTERSLICE_RETURN_IF_ERROR(CheckSameForAll(
      headers, slices, "Modality",
      [](const FileHeader& h) { return h.modality; }, as_is));
  INTERSLICE_RETURN_IF_ERROR(CheckSameForAll(
      headers, slices, "BitsAllocated",
      [](const FileHeader& h) { return absl::StrCat(h.layout.bits_allocated); },
      as_is));
  INTERSLICE_RETURN_IF_ERROR(CheckSameForAll(
      headers, slices, "BitsStored",
      [](const FileHeader& h) { return absl::StrCat(h.layout.bits_stored); },
      as_is));
  INTERSLICE_RETURN_IF_ERROR(CheckSameForAll(
      headers, slices, "PixelRepresentation",
      [](const FileHeader& h) {
        return std::string(h.layout.is_signed ? "1" : "0");
      },
      [](const std::string& v) {
        return std::string(v == "1" ? "1 (signed)" : "0 (unsigned)");
      }));
  return absl::OkStatus();
}

absl::StatusOr<StackLayout> LayOutStack(const std::vector<FileHeader>& headers,
                                        std::vector<SliceRef> slices) {
  const SliceRef& ref = slices.front();
  for (const SliceRef& s : slices) {
    INTERSLICE_RETURN_IF_ERROR(CheckConsistent(headers, ref, s));
  }
  const FileHeader& ref_header = headers[ref.header];

  Vec3 row = {ref.orientation[0], ref.orientation[1], ref.orientation[2]};
  Vec3 col = {ref.orientation[3], ref.orientation[4], ref.orientation[5]};
  if (std::abs(Norm(row) - 1) > kOrthonormalTolerance ||
      std::abs(Norm(col) - 1) > kOrthonormalTolerance ||
      std::abs(Dot(row, col)) > kOrthonormalTolerance) {
    return absl::InvalidArgumentError(absl::StrCat(
        SliceName(headers, ref),
        ": ImageOrientationPatient is not two orthogonal unit vectors"));
  }
  // Gram-Schmidt, so that the grid's direction is orthonormal to rounding.
  row = Scale(row, 1 / Norm(row));
  col = Sub(col, Scale(row, Dot(row, col)));
  col = Scale(col, 1 / Norm(col));
  const Vec3 normal = Cross(row, col);

  StackLayout stack;
  std::sort(slices.begin(), slices.end(),
            [&](const SliceRef& a, const SliceRef& b) {
              const double pa = Dot(a.position, normal);
              const double pb = Dot(b.position, normal);
              if (pa != pb) return pa < pb;
              const std::string& fa = headers[a.header].path;
              const std::string& fb = headers[b.header].path;
              if (fa != fb) return fa < fb;
              return a.frame < b.frame;
            });
  stack.order = std::move(slices);
  for (const SliceRef& s : stack.order) {
    stack.positions.push_back(Dot(s.position, normal));
  }

  const size_t n = stack.order.size();
  for (size_t k = 0; k + 1 < n; ++k) {
    if (stack.positions[k + 1] - stack.positions[k] < kSamePositionTolerance) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s and %s are at the same slice position (%.3f mm along the slice "
          "normal); the series holds duplicate or overlapping slices (or "
          "several images per position, e.g. echoes or diffusion directions)",
          SliceName(headers, stack.order[k]),
          SliceName(headers, stack.order[k + 1]), stack.positions[k]));
    }
  }

  // Gantry tilt: successive positions move within the image plane as well as
  // along the normal. Treatment (see the header): every slice is resampled
  // onto the in-plane grid of the first slice, shifted along the normal.
  bool tilted = false;
  for (size_t k = 0; k + 1 < n; ++k) {
    const Vec3 step = Sub(stack.order[k + 1].position, stack.order[k].position);
    const double along_step = Dot(step, normal);
    const double in_plane = Norm(Sub(step, Scale(normal, along_step)));
    if (in_plane > kTiltTolerance * along_step) tilted = true;
  }
  const double sx = ref.pixel_spacing[1], sy = ref.pixel_spacing[0];
  if (tilted) {
    const Vec3 total =
        Sub(stack.order.back().position, stack.order.front().position);
    const double along = Dot(total, normal);
    stack.tilt_degrees =
        std::atan2(Norm(Sub(total, Scale(normal, along))), along) * 180.0 /
        M_PI;
    for (size_t k = 0; k < n; ++k) {
      const Vec3 d = Sub(stack.order[k].position, stack.order[0].position);
      const std::array<double, 2> shift = {Dot(d, row) / sx, Dot(d, col) / sy};
      if (std::abs(shift[0]) >= ref_header.columns ||
          std::abs(shift[1]) >= ref_header.rows) {
        return absl::InvalidArgumentError(absl::StrFormat(
            "%s is offset by (%.1f, %.1f) pixels within the image plane from "
            "%s: the slices do not overlap, so they are not one stack",
            SliceName(headers, stack.order[k]), shift[0], shift[1],
            SliceName(headers, stack.order[0])));
      }
      stack.tilt_shift.push_back(shift);
    }
  }

  double spacing = 1;
  if (n == 1) {
    // One slice has no spacing of its own; its thickness is the best
    // extent for the single voxel layer.
    if (ref_header.slice_thickness > 0) {
      spacing = ref_header.slice_thickness;
    } else if (ref_header.spacing_between_slices > 0) {
      spacing = ref_header.spacing_between_slices;
    }
  } else {
    std::vector<double> gaps(n - 1);
    for (size_t k = 0; k + 1 < n; ++k) {
      gaps[k] = stack.positions[k + 1] - stack.positions[k];
    }
    std::vector<double> sorted = gaps;
    std::sort(sorted.begin(), sorted.end());
    const size_t mid = sorted.size() / 2;
    spacing = sorted.size() % 2 == 1 ? sorted[mid]
                                     : 0.5 * (sorted[mid - 1] + sorted[mid]);
    const double tolerance = std::max(kSpacingAbsoluteTolerance,
                                      kSpacingRelativeTolerance * spacing);
    stack.min_gap = sorted.front();
    stack.max_gap = sorted.back();
    stack.uniform = std::abs(sorted.front() - spacing) <= tolerance &&
                    std::abs(sorted.back() - spacing) <= tolerance;
  }

  Grid& grid = stack.grid;
  grid.size = {ref_header.columns, ref_header.rows, static_cast<int64_t>(n)};
  // PixelSpacing is (between rows, between columns) = (along j, along i).
  grid.spacing = {sx, sy, spacing};
  grid.origin = stack.order.front().position;
  for (int r = 0; r < 3; ++r) {
    grid.direction[3 * r + 0] = row[r];
    grid.direction[3 * r + 1] = col[r];
    grid.direction[3 * r + 2] = normal[r];
  }
  INTERSLICE_RETURN_IF_ERROR(grid.Validate());
  return stack;
}

// Stored values (little-endian bytes as DCMTK hands them out) to modality
// values.
template <int kBytes>
void ConvertPixels(const Uint8* bytes, int64_t count, const PixelLayout& l,
                   double slope, double intercept, float* out) {
  const int shift = l.high_bit + 1 - l.bits_stored;
  const uint32_t mask =
      l.bits_stored == 32 ? 0xffffffffu : (uint32_t{1} << l.bits_stored) - 1;
  const uint32_t sign_bit = uint32_t{1} << (l.bits_stored - 1);
  const int64_t wrap = int64_t{1} << l.bits_stored;
  for (int64_t i = 0; i < count; ++i) {
    const Uint8* p = bytes + i * kBytes;
    uint32_t raw = p[0];
    if constexpr (kBytes >= 2) raw |= uint32_t{p[1]} << 8;
    if constexpr (kBytes == 4) {
      raw |= uint32_t{p[2]} << 16 | uint32_t{p[3]} << 24;
    }
    // Bits outside BitsStored may hold overlays or garbage.
    const uint32_t value = (raw >> shift) & mask;
    int64_t stored = value;
    if (l.is_signed && (value & sign_bit) != 0) stored -= wrap;
    out[i] =
        static_cast<float>(static_cast<double>(stored) * slope + intercept);
  }
}

// Where the frames of one file go in the volume.
struct FileTarget {
  size_t header = 0;
  // (frame, k): frame `frame` of the file becomes slice k.
  std::vector<std::pair<int, size_t>> frames;
};

void ConvertFrame(const Uint8* src, int64_t samples, const PixelLayout& layout,
                  const SliceRef& s, float* out) {
  switch (layout.bits_allocated) {
    case 8:
      ConvertPixels<1>(src, samples, layout, s.rescale_slope,
                       s.rescale_intercept, out);
      break;
    case 16:
      ConvertPixels<2>(src, samples, layout, s.rescale_slope,
                       s.rescale_intercept, out);
      break;
    default:
      ConvertPixels<4>(src, samples, layout, s.rescale_slope,
                       s.rescale_intercept, out);
      break;
  }
}

// The JPEG 2000 codestream of frame `frame` (0-based) of `frames`: with one
// frame, all fragments together; with several, one fragment per frame (as
// GDCM requires, and as writers do; frames split over fragments are refused
// rather than guessed from the offset table).
absl::Status Jpeg2000FrameBytes(DcmDataset& ds, const std::string& name,
                                int64_t frames, int frame,
                                std::vector<uint8_t>& out) {
  out.clear();
  DcmElement* element = nullptr;
  ds.findAndGetElement(DCM_PixelData, element);
  DcmPixelData* pixels = dynamic_cast<DcmPixelData*>(element);
  DcmPixelSequence* sequence = nullptr;
  if (pixels != nullptr) {
    E_TransferSyntax xfer = EXS_Unknown;
    const DcmRepresentationParameter* param = nullptr;
    pixels->getOriginalRepresentationKey(xfer, param);
    pixels->getEncapsulatedRepresentation(xfer, param, sequence);
  }
  if (sequence == nullptr || sequence->card() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": no encapsulated JPEG 2000 pixel data"));
  }
  // The first item is the basic offset table.
  const unsigned long fragments = sequence->card() - 1;
  if (frames > 1 && fragments != static_cast<unsigned long>(frames)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: %d JPEG 2000 fragments for %d frames; frames split over several "
        "fragments are not supported",
        name, fragments, frames));
  }
  auto append = [&](unsigned long index) -> absl::Status {
    DcmPixelItem* item = nullptr;
    if (sequence->getItem(item, index).bad() || item == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat(name, ": missing pixel data fragment"));
    }
    const Uint32 length = item->getLength();
    if (length == 0) return absl::OkStatus();
    Uint8* bytes = nullptr;
    if (item->getUint8Array(bytes).bad() || bytes == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(
          name, ": cannot read a pixel data fragment; truncated file?"));
    }
    out.insert(out.end(), bytes, bytes + length);
    return absl::OkStatus();
  };
  if (frames > 1) return append(static_cast<unsigned long>(frame) + 1);
  for (unsigned long i = 1; i <= fragments; ++i) {
    INTERSLICE_RETURN_IF_ERROR(append(i));
  }
  return absl::OkStatus();
}

// Decodes the used frames of a JPEG 2000 file (GDCM, one frame at a time, so
// that memory stays bounded by one frame whatever NumberOfFrames says).
absl::Status LoadJpeg2000Frames(DcmDataset& ds, const FileHeader& h,
                                const FileTarget& target,
                                const std::vector<SliceRef>& order,
                                const PixelLayout& layout,
                                Volume<float>& volume) {
  const std::string name = BaseName(h.path);
  const int64_t frames = h.frames.empty() ? 1 : h.frames.size();
  const int64_t frame_samples = int64_t{h.rows} * h.columns;
  // Decoded samples are plain values: HighBit plays no part.
  PixelLayout decoded_layout = layout;
  decoded_layout.high_bit = layout.bits_stored - 1;
  const dicom_internal::Jpeg2000Target j2k = {
      .rows = h.rows,
      .columns = h.columns,
      .bits_allocated = layout.bits_allocated,
      .bits_stored = layout.bits_stored,
      .is_signed = layout.is_signed};
  std::vector<uint8_t> codestream;
  for (const auto& [frame, k] : target.frames) {
    const std::string frame_name =
        frames > 1 ? absl::StrCat(name, " frame ", frame + 1) : name;
    INTERSLICE_RETURN_IF_ERROR(
        Jpeg2000FrameBytes(ds, frame_name, frames, frame, codestream));
    INTERSLICE_ASSIGN_OR_RETURN(
        const std::vector<uint8_t> decoded,
        dicom_internal::DecodeJpeg2000Frame(
            codestream.data(), codestream.size(), frame_name, j2k));
    ConvertFrame(decoded.data(), frame_samples, decoded_layout, order[k],
                 volume.data.data() + k * frame_samples);
  }
  return absl::OkStatus();
}

// Decodes the frames of one file into their slices of `volume`.
absl::Status LoadFile(const FileHeader& h, const FileTarget& target,
                      const std::vector<SliceRef>& order,
                      Volume<float>& volume) {
  const std::string name = BaseName(h.path);
  // The file may have changed since its header was scanned.
  INTERSLICE_RETURN_IF_ERROR(dicom_internal::CheckSequenceDepth(h.path));
  DcmFileFormat file;
  // The default read limit leaves the pixel data on disk until it is
  // accessed below, which is all that is needed.
  OFCondition cond = file.loadFile(OFFilename(h.path.c_str()));
  if (cond.bad()) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": truncated or unreadable DICOM file (", cond.text(), ")"));
  }
  DcmDataset& ds = *file.getDataset();
  const int64_t frames = h.frames.empty() ? 1 : h.frames.size();
  const int64_t frame_samples = int64_t{h.rows} * h.columns;
  // Decoders may rewrite the pixel module: check again against what was
  // planned.
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  if (rows != h.rows || columns != h.columns) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": Rows/Columns changed while reading"));
  }
  INTERSLICE_ASSIGN_OR_RETURN(const PixelLayout layout,
                              dicom_internal::ReadPixelLayout(ds, name));
  const int64_t needed = frames * frame_samples * (layout.bits_allocated / 8);

  const E_TransferSyntax xfer = ds.getOriginalXfer();
  if (DcmXfer(xfer).isEncapsulated()) {
    cond = ds.chooseRepresentation(EXS_LittleEndianExplicit, nullptr);
    if (cond.bad() || !ds.canWriteXfer(EXS_LittleEndianExplicit)) {
      if (!dicom_internal::IsGdcmFallbackSyntax(h.transfer_syntax_uid)) {
        return absl::UnimplementedError(absl::StrCat(
            name, ": cannot decode pixel data in transfer syntax '",
            DcmXfer(xfer).getXferName(), "' (", h.transfer_syntax_uid, ")",
            cond.bad() ? absl::StrCat(": ", cond.text()) : ""));
      }
      return LoadJpeg2000Frames(ds, h, target, order, layout, volume);
    }
  }
  DcmElement* pixels = nullptr;
  if (ds.findAndGetElement(DCM_PixelData, pixels).bad() || pixels == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": no pixel data"));
  }
  Uint8* bytes = nullptr;
  cond = pixels->getUint8Array(bytes);
  if (cond.bad() || bytes == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": cannot read pixel data (",
        cond.bad() ? cond.text() : "no value", "); truncated file?"));
  }
  const Uint32 element_length = pixels->getLength();
  const int64_t length =
      element_length == DCM_UndefinedLength ? 0 : element_length;
  if (length < needed) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: pixel data is too short: %d bytes, but %d frame(s) of %d x %d "
        "pixels of %d bits need %d",
        name, length, frames, h.columns, h.rows, layout.bits_allocated,
        needed));
  }
  const int64_t frame_bytes = frame_samples * (layout.bits_allocated / 8);
  for (const auto& [frame, k] : target.frames) {
    const SliceRef& s = order[k];
    ConvertFrame(bytes + frame * frame_bytes, frame_samples, layout, s,
                 volume.data.data() + k * frame_samples);
  }
  return absl::OkStatus();
}

// Gantry tilt: resamples slice k at (i - shift_i, j - shift_j), bilinearly,
// so that it lies on the in-plane grid of the first slice. Samples outside
// the acquired slice get `background`.
void ResampleTiltedSlices(const std::vector<std::array<double, 2>>& shifts,
                          float background, Volume<float>& volume,
                          tbb::task_arena& arena) {
  const int64_t nx = volume.grid.size[0], ny = volume.grid.size[1];
  const int64_t plane = nx * ny;
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, shifts.size(), 1),
        [&](const tbb::blocked_range<size_t>& range) {
          std::vector<float> original(plane);
          for (size_t k = range.begin(); k != range.end(); ++k) {
            const double di = shifts[k][0], dj = shifts[k][1];
            if (di == 0 && dj == 0) continue;
            float* slice = volume.data.data() + k * plane;
            std::copy(slice, slice + plane, original.begin());
            auto at = [&](int64_t i, int64_t j) -> double {
              if (i < 0 || j < 0 || i >= nx || j >= ny) return background;
              return original[j * nx + i];
            };
            for (int64_t j = 0; j < ny; ++j) {
              const double y = j - dj;
              const double y0 = std::floor(y);
              const double ty = y - y0;
              for (int64_t i = 0; i < nx; ++i) {
                const double x = i - di;
                const double x0 = std::floor(x);
                const double tx = x - x0;
                const int64_t xi = static_cast<int64_t>(x0);
                const int64_t yi = static_cast<int64_t>(y0);
                const double v =
                    (1 - ty) * ((1 - tx) * at(xi, yi) + tx * at(xi + 1, yi)) +
                    ty * ((1 - tx) * at(xi, yi + 1) + tx * at(xi + 1, yi + 1));
                slice[j * nx + i] = static_cast<float>(v);
              }
            }
          }
        });
  });
}

}  // namespace

void RegisterDicomDecoders() {
  static std::once_flag once;
  // DCMTK's codec registry is process-wide; registering twice would add
  // duplicate codecs.
  std::call_once(once, [] {
    DJDecoderRegistration::registerCodecs();
    DJLSDecoderRegistration::registerCodecs();
    DcmRLEDecoderRegistration::registerCodecs();
  });
}

std::vector<TransferSyntaxInfo> DecodableTransferSyntaxes() {
  RegisterDicomDecoders();
  static constexpr E_TransferSyntax kNative[] = {
      EXS_LittleEndianImplicit, EXS_LittleEndianExplicit,
      EXS_DeflatedLittleEndianExplicit, EXS_BigEndianExplicit};
  static constexpr E_TransferSyntax kEncapsulated[] = {
      EXS_JPEGProcess1,     EXS_JPEGProcess2_4,       EXS_JPEGProcess14,
      EXS_JPEGProcess14SV1, EXS_JPEGLSLossless,       EXS_JPEGLSLossy,
      EXS_RLELossless,      EXS_JPEG2000LosslessOnly, EXS_JPEG2000};
  std::vector<TransferSyntaxInfo> out;
  auto add = [&out](E_TransferSyntax xfer) {
    const DcmXfer x(xfer);
    out.push_back({x.getXferID(), x.getXferName()});
  };
  for (E_TransferSyntax xfer : kNative) add(xfer);
  for (E_TransferSyntax xfer : kEncapsulated) {
    if (DcmCodecList::canChangeCoding(xfer, EXS_LittleEndianExplicit) ||
        dicom_internal::IsGdcmFallbackSyntax(DcmXfer(xfer).getXferID())) {
      add(xfer);
    }
  }
  return out;
}

void QuietDicomToolkitLogging() {
  // Errors reach the caller as absl::Status; DCMTK's own "E: ..." lines for
  // files it cannot parse would only duplicate them on stderr.
  OFLog::configure(OFLogger::FATAL_LOG_LEVEL);
}

absl::StatusOr<std::vector<DicomSeriesSummary>> ListDicomSeries(
    const std::vector<std::string>& paths) {
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<std::string> files,
                              CollectInputFiles(paths));
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<FileHeader> headers,
                              ScanHeaders(files, nullptr, nullptr));
  std::vector<DicomSeriesSummary> result;
  for (auto& [uid, s] : GroupSeries(headers)) result.push_back(s.summary);
  return result;
}

absl::StatusOr<DicomSeries> ReadDicomSeries(
    const std::vector<std::string>& paths, const DicomReadOptions& options,
    const ComputeContext& context) {
  RegisterDicomDecoders();
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);

  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<std::string> files,
                              CollectInputFiles(paths));
  if (files.empty()) {
    return absl::NotFoundError("no files in the input");
  }
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<FileHeader> headers,
                              ScanHeaders(files, &arena, &context));

  const std::map<std::string, Series> all_series = GroupSeries(headers);
  if (all_series.empty()) {
    return absl::NotFoundError(absl::StrCat(
        "no DICOM image slices in the input (", DescribeSkipped(headers), ")"));
  }
  const Series* chosen = nullptr;
  if (options.series_instance_uid.empty()) {
    if (all_series.size() > 1) {
      return absl::FailedPreconditionError(
          absl::StrCat("the input holds ", all_series.size(),
                       " image series; choose one by its SeriesInstanceUID "
                       "(--series-uid): ",
                       DescribeSeries(all_series, headers)));
    }
    chosen = &all_series.begin()->second;
  } else {
    for (const auto& [key, s] : all_series) {
      if (s.summary.series_instance_uid == options.series_instance_uid) {
        chosen = &s;
      }
    }
    if (chosen == nullptr) {
      return absl::FailedPreconditionError(
          absl::StrCat("SeriesInstanceUID ", options.series_instance_uid,
                       " is not in the input; image series present: ",
                       DescribeSeries(all_series, headers)));
    }
  }

  // Broken files of the chosen series fail the read, in path order.
  for (size_t m : chosen->members) {
    INTERSLICE_RETURN_IF_ERROR(headers[m].problem);
  }
  INTERSLICE_ASSIGN_OR_RETURN(
      std::vector<SliceRef> slices,
      ChooseVolume(SlicesOf(headers, chosen->members), options));
  INTERSLICE_RETURN_IF_ERROR(CheckSeriesConsistent(headers, slices));
  INTERSLICE_ASSIGN_OR_RETURN(StackLayout stack,
                              LayOutStack(headers, std::move(slices)));

  const int64_t voxels = stack.grid.VoxelCount();
  if (voxels > options.max_voxels) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the series has %d x %d x %d = %d voxels, more than the limit of %d "
        "(max_voxels)",
        stack.grid.size[0], stack.grid.size[1], stack.grid.size[2], voxels,
        options.max_voxels));
  }

  // Each file is decoded once, whatever number of its frames are used.
  std::vector<FileTarget> targets;
  {
    std::map<size_t, size_t> target_of;  // header -> index in targets
    for (size_t k = 0; k < stack.order.size(); ++k) {
      const SliceRef& s = stack.order[k];
      auto [it, inserted] = target_of.emplace(s.header, targets.size());
      if (inserted) targets.push_back({s.header, {}});
      targets[it->second].frames.emplace_back(s.frame, k);
    }
  }
  // Decoders (DCMTK's) decode every frame of a file, including those of
  // other volumes: the limit bounds each file's decoded size too.
  for (const FileTarget& t : targets) {
    const FileHeader& h = headers[t.header];
    const int64_t file_voxels =
        int64_t{h.rows} * h.columns * std::max<int64_t>(1, h.frames.size());
    if (file_voxels > options.max_voxels) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s holds %d x %d x %d = %d voxels in all its frames, more than the "
          "limit of %d (max_voxels)",
          BaseName(h.path), h.columns, h.rows, h.frames.size(), file_voxels,
          options.max_voxels));
    }
  }

  DicomSeries result;
  result.image.grid = stack.grid;
  result.image.data.resize(voxels);
  const size_t n = targets.size();
  std::vector<absl::Status> statuses(n);
  // Files after the first failing one are skipped, but every file before
  // it is still tried, so the error reported is the same whatever the
  // scheduling (the first failing file along the stack).
  std::atomic<size_t> first_failed{n};
  size_t done = 0;  // guarded by progress_mutex
  std::mutex progress_mutex;
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, n, 1),
        [&](const tbb::blocked_range<size_t>& range) {
          for (size_t t = range.begin(); t != range.end(); ++t) {
            if (t > first_failed.load(std::memory_order_relaxed)) return;
            absl::Status status = context.CheckCancelled();
            if (status.ok()) {
              status = LoadFile(headers[targets[t].header], targets[t],
                                stack.order, result.image);
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

  if (!stack.tilt_shift.empty()) {
    // Padding with the darkest value keeps the padded border outside any
    // object defined by a lower threshold (air for CT).
    const float background =
        *std::min_element(result.image.data.begin(), result.image.data.end());
    ResampleTiltedSlices(stack.tilt_shift, background, result.image, arena);
    result.gantry_tilt_degrees = stack.tilt_degrees;
  }

  for (size_t k = 0; k < stack.order.size(); ++k) {
    const SliceRef& s = stack.order[k];
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
  const FileHeader& first = headers[stack.order.front().header];
  result.series_instance_uid = first.series_uid;
  result.study_instance_uid = first.study_uid;
  result.frame_of_reference_uid = first.frame_of_reference_uid;
  result.modality = first.modality;
  result.sop_class_uid = first.sop_class_uid;
  result.volume = stack.order.front().volume;
  result.slice_thickness_mm = first.slice_thickness;
  result.notes = InputNotes(headers, chosen->members);
  result.uniform_spacing = stack.uniform;
  result.min_gap_mm = stack.min_gap;
  result.max_gap_mm = stack.max_gap;
  result.skipped_files = static_cast<int64_t>(headers.size() - targets.size());
  return result;
}

}  // namespace interslice
