#include "core/dicom/series_reader.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
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
#include "core/common/status_macros.h"
#include "core/dicom/dicom_header.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdatset.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcrledrg.h"
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

// Files of `paths`, directories searched recursively, sorted and without
// duplicates so that results do not depend on directory listing order.
absl::StatusOr<std::vector<std::string>> CollectFiles(
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
  DicomSeriesSummary summary;
};

// Image series by SeriesInstanceUID (ordered by UID for stable messages).
std::map<std::string, Series> GroupSeries(
    const std::vector<FileHeader>& headers) {
  std::map<std::string, Series> series;
  for (size_t i = 0; i < headers.size(); ++i) {
    const FileHeader& h = headers[i];
    if (h.kind != FileKind::kImage) continue;
    Series& s = series[h.series_uid];
    if (s.members.empty()) {
      s.summary.series_instance_uid = h.series_uid;
      s.summary.modality = h.modality;
    }
    s.members.push_back(i);
    ++s.summary.image_count;
  }
  return series;
}

std::string DescribeSeries(const std::map<std::string, Series>& series) {
  std::vector<std::string> parts;
  for (const auto& [uid, s] : series) {
    parts.push_back(absl::StrFormat(
        "%s (%s, %d image%s)", uid,
        s.summary.modality.empty() ? "no modality" : s.summary.modality,
        s.summary.image_count, s.summary.image_count == 1 ? "" : "s"));
  }
  return absl::StrJoin(parts, ", ");
}

std::string DescribeSkipped(const std::vector<FileHeader>& headers) {
  int64_t not_dicom = 0, dicomdir = 0, not_image = 0;
  for (const FileHeader& h : headers) {
    if (h.kind == FileKind::kNotDicom) ++not_dicom;
    if (h.kind == FileKind::kDicomDir) ++dicomdir;
    if (h.kind == FileKind::kNotImage) ++not_image;
  }
  return absl::StrFormat(
      "%d file(s) skipped: %d not DICOM or unreadable, %d DICOMDIR, %d DICOM "
      "objects that are not image slices with position and orientation",
      headers.size(), not_dicom, dicomdir, not_image);
}

// The geometry of the stack and the order of its slices.
struct StackLayout {
  std::vector<size_t> order;      // header indices, sorted along the normal
  std::vector<double> positions;  // along the normal, in `order`
  Grid grid;
};

absl::Status CheckConsistent(const FileHeader& ref, const FileHeader& h) {
  if (h.rows != ref.rows || h.columns != ref.columns) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "inconsistent Rows/Columns: %s is %d x %d (columns x rows) but %s is "
        "%d x %d",
        BaseName(h.path), h.columns, h.rows, BaseName(ref.path), ref.columns,
        ref.rows));
  }
  for (int c = 0; c < 6; ++c) {
    if (std::abs(h.orientation[c] - ref.orientation[c]) >
        kOrientationTolerance) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "inconsistent ImageOrientationPatient: %s differs from %s",
          BaseName(h.path), BaseName(ref.path)));
    }
  }
  for (int c = 0; c < 2; ++c) {
    const double a = h.pixel_spacing[c], b = ref.pixel_spacing[c];
    if (std::abs(a - b) >
        kPixelSpacingRelativeTolerance * std::max(std::abs(a), std::abs(b))) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "inconsistent PixelSpacing: %s has %g\\%g mm but %s has %g\\%g mm",
          BaseName(h.path), h.pixel_spacing[0], h.pixel_spacing[1],
          BaseName(ref.path), ref.pixel_spacing[0], ref.pixel_spacing[1]));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<StackLayout> LayOutStack(const std::vector<FileHeader>& headers,
                                        const std::vector<size_t>& members) {
  const FileHeader& ref = headers[members.front()];
  for (size_t m : members) {
    INTERSLICE_RETURN_IF_ERROR(CheckConsistent(ref, headers[m]));
  }

  Vec3 row = {ref.orientation[0], ref.orientation[1], ref.orientation[2]};
  Vec3 col = {ref.orientation[3], ref.orientation[4], ref.orientation[5]};
  if (std::abs(Norm(row) - 1) > kOrthonormalTolerance ||
      std::abs(Norm(col) - 1) > kOrthonormalTolerance ||
      std::abs(Dot(row, col)) > kOrthonormalTolerance) {
    return absl::InvalidArgumentError(absl::StrCat(
        BaseName(ref.path),
        ": ImageOrientationPatient is not two orthogonal unit vectors"));
  }
  // Gram-Schmidt, so that the grid's direction is orthonormal to rounding.
  row = Scale(row, 1 / Norm(row));
  col = Sub(col, Scale(row, Dot(row, col)));
  col = Scale(col, 1 / Norm(col));
  const Vec3 normal = Cross(row, col);

  StackLayout stack;
  stack.order = members;
  std::vector<double> along(headers.size(), 0.0);
  for (size_t m : members) along[m] = Dot(headers[m].position, normal);
  std::sort(stack.order.begin(), stack.order.end(), [&](size_t a, size_t b) {
    if (along[a] != along[b]) return along[a] < along[b];
    return headers[a].path < headers[b].path;
  });
  for (size_t m : stack.order) stack.positions.push_back(along[m]);

  const size_t n = stack.order.size();
  for (size_t k = 0; k + 1 < n; ++k) {
    if (stack.positions[k + 1] - stack.positions[k] < kSamePositionTolerance) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s and %s are at the same slice position (%.3f mm along the slice "
          "normal); the series holds duplicate or overlapping slices",
          BaseName(headers[stack.order[k]].path),
          BaseName(headers[stack.order[k + 1]].path), stack.positions[k]));
    }
  }

  // Gantry tilt: successive positions move within the image plane as well as
  // along the normal, so the voxels are sheared, not a rectilinear grid.
  double max_tilt_degrees = 0;
  bool tilted = false;
  for (size_t k = 0; k + 1 < n; ++k) {
    const Vec3 step = Sub(headers[stack.order[k + 1]].position,
                          headers[stack.order[k]].position);
    const double along_step = Dot(step, normal);
    const double in_plane = Norm(Sub(step, Scale(normal, along_step)));
    if (in_plane > kTiltTolerance * along_step) tilted = true;
    max_tilt_degrees = std::max(
        max_tilt_degrees, std::atan2(in_plane, along_step) * 180.0 / M_PI);
  }
  if (tilted) {
    return absl::UnimplementedError(absl::StrFormat(
        "gantry tilt of %.1f degrees (slice positions do not follow the slice "
        "normal); tilted series are not supported yet",
        max_tilt_degrees));
  }

  double spacing = 1;
  if (n == 1) {
    // One slice has no spacing of its own; its thickness is the best
    // extent for the single voxel layer.
    if (ref.slice_thickness > 0) {
      spacing = ref.slice_thickness;
    } else if (ref.spacing_between_slices > 0) {
      spacing = ref.spacing_between_slices;
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
    if (std::abs(sorted.front() - spacing) > tolerance ||
        std::abs(sorted.back() - spacing) > tolerance) {
      return absl::UnimplementedError(absl::StrFormat(
          "non-uniform slice spacing (%.3f .. %.3f mm); missing slices?",
          sorted.front(), sorted.back()));
    }
  }

  Grid& grid = stack.grid;
  grid.size = {ref.columns, ref.rows, static_cast<int64_t>(n)};
  // PixelSpacing is (between rows, between columns) = (along j, along i).
  grid.spacing = {ref.pixel_spacing[1], ref.pixel_spacing[0], spacing};
  grid.origin = headers[stack.order.front()].position;
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

// Decodes one slice into `out` (Columns x Rows floats).
absl::Status LoadSlice(const FileHeader& h, float* out) {
  const std::string name = BaseName(h.path);
  DcmFileFormat file;
  // The default read limit leaves the pixel data on disk until it is
  // accessed below, which is all that is needed.
  OFCondition cond = file.loadFile(OFFilename(h.path.c_str()));
  if (cond.bad()) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": truncated or unreadable DICOM file (", cond.text(), ")"));
  }
  DcmDataset& ds = *file.getDataset();
  const E_TransferSyntax xfer = ds.getOriginalXfer();
  if (DcmXfer(xfer).isEncapsulated()) {
    cond = ds.chooseRepresentation(EXS_LittleEndianExplicit, nullptr);
    if (cond.bad() || !ds.canWriteXfer(EXS_LittleEndianExplicit)) {
      return absl::UnimplementedError(
          absl::StrCat(name, ": cannot decode pixel data in transfer syntax '",
                       DcmXfer(xfer).getXferName(), "'",
                       cond.bad() ? absl::StrCat(" (", cond.text(), ")") : ""));
    }
  }
  // The file may have changed since its header was scanned, and decoders
  // may rewrite the pixel module: check again against what was planned.
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  if (rows != h.rows || columns != h.columns) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": Rows/Columns changed while reading"));
  }
  INTERSLICE_ASSIGN_OR_RETURN(const PixelLayout layout,
                              dicom_internal::ReadPixelLayout(ds, name));
  DcmElement* pixels = nullptr;
  Uint8* bytes = nullptr;
  if (ds.findAndGetElement(DCM_PixelData, pixels).bad() || pixels == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": no pixel data"));
  }
  cond = pixels->getUint8Array(bytes);
  if (cond.bad() || bytes == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": cannot read pixel data (",
        cond.bad() ? cond.text() : "no value", "); truncated file?"));
  }
  const int64_t count = int64_t{h.rows} * h.columns;
  const int64_t needed = count * (layout.bits_allocated / 8);
  const Uint32 length = pixels->getLength();
  if (length == DCM_UndefinedLength || int64_t{length} < needed) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: pixel data is too short: %d bytes, but %d x %d pixels of %d "
        "bits need %d",
        name, length == DCM_UndefinedLength ? 0 : int64_t{length}, h.columns,
        h.rows, layout.bits_allocated, needed));
  }
  switch (layout.bits_allocated) {
    case 8:
      ConvertPixels<1>(bytes, count, layout, h.rescale_slope,
                       h.rescale_intercept, out);
      break;
    case 16:
      ConvertPixels<2>(bytes, count, layout, h.rescale_slope,
                       h.rescale_intercept, out);
      break;
    default:
      ConvertPixels<4>(bytes, count, layout, h.rescale_slope,
                       h.rescale_intercept, out);
      break;
  }
  return absl::OkStatus();
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

void QuietDicomToolkitLogging() {
  // Errors reach the caller as absl::Status; DCMTK's own "E: ..." lines for
  // files it cannot parse would only duplicate them on stderr.
  OFLog::configure(OFLogger::FATAL_LOG_LEVEL);
}

absl::StatusOr<std::vector<DicomSeriesSummary>> ListDicomSeries(
    const std::vector<std::string>& paths) {
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<std::string> files,
                              CollectFiles(paths));
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
                              CollectFiles(paths));
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
                       DescribeSeries(all_series)));
    }
    chosen = &all_series.begin()->second;
  } else {
    auto it = all_series.find(options.series_instance_uid);
    if (it == all_series.end()) {
      return absl::FailedPreconditionError(
          absl::StrCat("SeriesInstanceUID ", options.series_instance_uid,
                       " is not in the input; image series present: ",
                       DescribeSeries(all_series)));
    }
    chosen = &it->second;
  }

  // Broken files of the chosen series fail the read, in path order.
  for (size_t m : chosen->members) {
    INTERSLICE_RETURN_IF_ERROR(headers[m].problem);
  }
  INTERSLICE_ASSIGN_OR_RETURN(StackLayout stack,
                              LayOutStack(headers, chosen->members));

  const int64_t voxels = stack.grid.VoxelCount();
  if (voxels > options.max_voxels) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the series has %d x %d x %d = %d voxels, more than the limit of %d "
        "(max_voxels)",
        stack.grid.size[0], stack.grid.size[1], stack.grid.size[2], voxels,
        options.max_voxels));
  }

  DicomSeries result;
  result.image.grid = stack.grid;
  result.image.data.resize(voxels);
  const int64_t slice_voxels = stack.grid.SliceVoxelCount();
  const size_t n = stack.order.size();
  std::vector<absl::Status> statuses(n);
  // Slices after the first failing one are skipped, but every slice before
  // it is still tried, so the error reported is the same whatever the
  // scheduling (the first failing slice along the stack).
  std::atomic<size_t> first_failed{n};
  size_t done = 0;  // guarded by progress_mutex
  std::mutex progress_mutex;
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, n, 1),
        [&](const tbb::blocked_range<size_t>& range) {
          for (size_t k = range.begin(); k != range.end(); ++k) {
            if (k > first_failed.load(std::memory_order_relaxed)) return;
            absl::Status status = context.CheckCancelled();
            if (status.ok()) {
              status = LoadSlice(headers[stack.order[k]],
                                 result.image.data.data() + k * slice_voxels);
            }
            if (!status.ok()) {
              statuses[k] = std::move(status);
              size_t expected = first_failed.load();
              while (k < expected &&
                     !first_failed.compare_exchange_weak(expected, k)) {
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

  for (size_t k = 0; k < n; ++k) {
    const FileHeader& h = headers[stack.order[k]];
    DicomSliceInfo& slice = result.slices.emplace_back();
    slice.path = h.path;
    slice.sop_instance_uid = h.sop_instance_uid;
    slice.image_position = h.position;
    slice.position_along_normal = stack.positions[k];
    slice.rescale_slope = h.rescale_slope;
    slice.rescale_intercept = h.rescale_intercept;
  }
  const FileHeader& first = headers[stack.order.front()];
  result.series_instance_uid = first.series_uid;
  result.study_instance_uid = first.study_uid;
  result.frame_of_reference_uid = first.frame_of_reference_uid;
  result.modality = first.modality;
  result.sop_class_uid = first.sop_class_uid;
  result.skipped_files =
      static_cast<int64_t>(headers.size() - chosen->members.size());
  return result;
}

}  // namespace interslice
