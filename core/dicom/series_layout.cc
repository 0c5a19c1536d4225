#include "core/dicom/series_layout.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status_macros.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using dicom_internal::BaseName;
using dicom_internal::FileHeader;

// Tolerances of the stack checks (see the header).
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

std::vector<DicomSliceRef> SlicesOf(const std::vector<FileHeader>& headers,
                                    const std::vector<size_t>& members) {
  std::vector<DicomSliceRef> slices;
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
                      const DicomSliceRef& s) {
  const FileHeader& h = headers[s.header];
  if (h.frames.empty()) return BaseName(h.path);
  return absl::StrCat(BaseName(h.path), " frame ", s.frame + 1);
}

std::string VolumeLabel(const std::string& volume) {
  return volume.empty() ? "single-frame images" : volume;
}

// Frames of different volumes (stacks, temporal positions, frame types such
// as magnitude and phase) share slice positions; one volume is laid out at a
// time: the only one, or `volume`.
absl::StatusOr<std::vector<DicomSliceRef>> ChooseVolume(
    std::vector<DicomSliceRef> slices, const std::string& volume) {
  std::map<std::string, int64_t> counts;
  for (const DicomSliceRef& s : slices) ++counts[s.volume];
  if (counts.size() == 1 && volume.empty()) return slices;
  std::vector<std::string> listing;
  for (const auto& [name, count] : counts) {
    listing.push_back(absl::StrFormat("\"%s\" (%d slice%s)", VolumeLabel(name),
                                      count, count == 1 ? "" : "s"));
  }
  if (volume.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the series holds ", counts.size(),
        " volumes that share slice positions (stacks, temporal positions or "
        "frame types of multi-frame images); choose one (volume option): ",
        absl::StrJoin(listing, ", ")));
  }
  if (counts.count(volume) == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "volume \"", volume, "\" is not in the series; volumes present: ",
        absl::StrJoin(listing, ", ")));
  }
  std::vector<DicomSliceRef> chosen;
  for (DicomSliceRef& s : slices) {
    if (s.volume == volume) chosen.push_back(std::move(s));
  }
  return chosen;
}

absl::Status CheckConsistent(const std::vector<FileHeader>& headers,
                             const DicomSliceRef& ref, const DicomSliceRef& s) {
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
// value most slices have, and one that has it; when no value is shared by
// two slices, says that each has its own (a "majority" of one slice would
// read as if one slice were odd); with more than two values, how many.
// `show` prints a value for the message; null when values must not appear
// (UIDs).
absl::Status CheckSameForAll(
    const std::vector<FileHeader>& headers,
    const std::vector<DicomSliceRef>& slices, const std::string& attribute,
    const std::function<std::string(const FileHeader&)>& value,
    const std::function<std::string(const std::string&)>& show) {
  std::map<std::string, int64_t> counts;
  for (const DicomSliceRef& s : slices) ++counts[value(headers[s.header])];
  if (counts.size() <= 1) return absl::OkStatus();
  auto text = [&show](const std::string& v) {
    return v.empty() ? std::string("none") : show(v);
  };
  if (counts.size() == slices.size()) {
    const DicomSliceRef& a = slices[0];
    const DicomSliceRef& b = slices[1];
    std::string example = absl::StrCat(SliceName(headers, a), " and ",
                                       SliceName(headers, b), " differ");
    if (show) {
      example = absl::StrCat(
          SliceName(headers, a), " has ", text(value(headers[a.header])), ", ",
          SliceName(headers, b), " has ", text(value(headers[b.header])));
    }
    return absl::InvalidArgumentError(absl::StrFormat(
        "inconsistent %s: each of the %d slices has a different one (e.g. "
        "%s); the files do not form one series",
        attribute, slices.size(), example));
  }
  std::string majority;
  int64_t most = 0;
  for (const auto& [v, count] : counts) {
    if (count > most) {
      most = count;
      majority = v;
    }
  }
  const DicomSliceRef* odd = nullptr;
  const DicomSliceRef* typical = nullptr;
  for (const DicomSliceRef& s : slices) {
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
    difference = absl::StrCat("has ", text(odd_value), ", but ", others,
                              " have ", text(majority));
  } else if (odd_value.empty()) {
    difference = absl::StrCat("has none, but ", others, " have one");
  } else if (majority.empty()) {
    difference = absl::StrCat("has one, but ", others, " have none");
  } else {
    difference = absl::StrCat("has a different one from ", others);
  }
  if (counts.size() > 2) {
    absl::StrAppend(&difference, ", ", counts.size(),
                    " different values in all");
  }
  return absl::InvalidArgumentError(
      absl::StrCat("inconsistent ", attribute, ": ", SliceName(headers, *odd),
                   " ", difference, "; the files do not form one series"));
}

// FrameOfReferenceUIDs of the slices (step 3 of the header), their counts
// into `stack`; with `strict`, INVALID_ARGUMENT when they differ.
absl::Status CountFramesOfReference(const std::vector<FileHeader>& headers,
                                    const std::vector<DicomSliceRef>& slices,
                                    bool strict, DicomStackLayout& stack) {
  std::set<std::string> uids;
  int64_t without = 0;
  for (const DicomSliceRef& s : slices) {
    const std::string& uid = headers[s.header].frame_of_reference_uid;
    if (uid.empty()) {
      ++without;
    } else {
      uids.insert(uid);
    }
  }
  stack.frame_of_reference_uids = static_cast<int64_t>(uids.size());
  stack.slices_without_frame_of_reference = without;
  stack.frames_of_reference_differ =
      uids.size() > 1 || (uids.size() == 1 && without > 0);
  if (!strict || !stack.frames_of_reference_differ) return absl::OkStatus();
  return CheckSameForAll(
      headers, slices, "FrameOfReferenceUID",
      [](const FileHeader& h) { return h.frame_of_reference_uid; }, nullptr);
}

// Attributes the stack relies on that must not change from slice to slice
// (the Frame of Reference is CountFramesOfReference's). Each would otherwise
// be accepted silently: a slice of another modality is not part of this
// volume, and another pixel layout means another acquisition or a broken
// export.
absl::Status CheckSeriesConsistent(const std::vector<FileHeader>& headers,
                                   const std::vector<DicomSliceRef>& slices) {
  auto as_is = [](const std::string& v) { return v; };
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

// Steps 4 to 7 of the header: `slices` are those of one volume, checked for
// the attributes of step 3.
absl::Status LayOutSlices(const std::vector<FileHeader>& headers,
                          std::vector<DicomSliceRef> slices,
                          DicomStackLayout& stack) {
  const DicomSliceRef& ref = slices.front();
  for (const DicomSliceRef& s : slices) {
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

  std::sort(slices.begin(), slices.end(),
            [&](const DicomSliceRef& a, const DicomSliceRef& b) {
              const double pa = Dot(a.position, normal);
              const double pb = Dot(b.position, normal);
              if (pa != pb) return pa < pb;
              const std::string& fa = headers[a.header].path;
              const std::string& fb = headers[b.header].path;
              if (fa != fb) return fa < fb;
              return a.frame < b.frame;
            });
  stack.order = std::move(slices);
  for (const DicomSliceRef& s : stack.order) {
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
  return grid.Validate();
}

}  // namespace

absl::StatusOr<DicomStackLayout> LayOutDicomStack(
    const std::vector<FileHeader>& headers, const std::vector<size_t>& members,
    const std::string& volume, bool strict_frame_of_reference) {
  if (members.empty()) {
    return absl::InvalidArgumentError("no slices to lay out");
  }
  // Broken files of the series fail the layout, in index order.
  for (size_t m : members) {
    INTERSLICE_RETURN_IF_ERROR(headers[m].problem);
  }
  INTERSLICE_ASSIGN_OR_RETURN(std::vector<DicomSliceRef> slices,
                              ChooseVolume(SlicesOf(headers, members), volume));
  DicomStackLayout stack;
  INTERSLICE_RETURN_IF_ERROR(CountFramesOfReference(
      headers, slices, strict_frame_of_reference, stack));
  INTERSLICE_RETURN_IF_ERROR(CheckSeriesConsistent(headers, slices));
  const absl::Status laid_out = LayOutSlices(headers, std::move(slices), stack);
  if (!laid_out.ok() && stack.frames_of_reference_differ) {
    // Differing UIDs were let through for the geometry to decide; say that
    // they differ too, since that alone would have refused the series.
    std::string frames =
        stack.frame_of_reference_uids == 1
            ? std::string("1 UID")
            : absl::StrCat(stack.frame_of_reference_uids, " different UIDs");
    if (stack.slices_without_frame_of_reference > 0) {
      absl::StrAppend(&frames, ", ", stack.slices_without_frame_of_reference,
                      " slice(s) without one");
    }
    return absl::Status(
        laid_out.code(),
        absl::StrCat(laid_out.message(),
                     "; the slices' FrameOfReferenceUIDs differ as well (",
                     frames,
                     "), which is accepted only when the geometry is one "
                     "stack"));
  }
  INTERSLICE_RETURN_IF_ERROR(laid_out);
  return stack;
}

absl::Status CorrectGantryTilt(const DicomStackLayout& layout,
                               Volume<float>& image,
                               const ComputeContext& context) {
  if (layout.tilt_shift.empty()) return absl::OkStatus();
  const std::vector<std::array<double, 2>>& shifts = layout.tilt_shift;
  if (image.grid.size[2] != static_cast<int64_t>(shifts.size()) ||
      static_cast<int64_t>(image.data.size()) != image.grid.VoxelCount()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "gantry tilt correction: the image has %d slices (%d voxels) but the "
        "layout %d",
        image.grid.size[2], image.data.size(), shifts.size()));
  }
  // The darkest value keeps the padded border outside any object defined by
  // a lower threshold (air for CT).
  const float background =
      *std::min_element(image.data.begin(), image.data.end());
  const int64_t nx = image.grid.size[0], ny = image.grid.size[1];
  const int64_t plane = nx * ny;
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, shifts.size(), 1),
        [&](const tbb::blocked_range<size_t>& range) {
          std::vector<float> original(plane);
          for (size_t k = range.begin(); k != range.end(); ++k) {
            const double di = shifts[k][0], dj = shifts[k][1];
            if (di == 0 && dj == 0) continue;
            float* slice = image.data.data() + k * plane;
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
  return absl::OkStatus();
}

}  // namespace interslice
