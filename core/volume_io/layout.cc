#include "core/volume_io/layout.h"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"

namespace interslice {
namespace {

// Reference index axes as named in messages.
constexpr const char* kAxisName[] = {"column axis (i)", "row axis (j)",
                                     "slice axis (k)"};

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

// Strides of the reference layout, per file axis: moving one voxel along
// file axis a moves stride[a] voxels in the reference's linear order;
// `first` is the reference linear index of file voxel (0, 0, 0).
struct Strides {
  std::array<int64_t, 3> stride;
  int64_t first = 0;
};

Strides ReferenceStrides(const AxisMapping& mapping, const Index3& ref_size) {
  const std::array<int64_t, 3> ref_stride = {1, ref_size[0],
                                             ref_size[0] * ref_size[1]};
  Strides s;
  for (int a = 0; a < 3; ++a) {
    const int b = mapping.axis[a];
    if (mapping.flipped[a]) {
      s.stride[a] = -ref_stride[b];
      s.first += (ref_size[b] - 1) * ref_stride[b];
    } else {
      s.stride[a] = ref_stride[b];
    }
  }
  return s;
}

}  // namespace

std::string AxisMapping::Describe() const {
  std::vector<std::string> parts;
  for (int a = 0; a < 3; ++a) {
    parts.push_back(
        absl::StrCat(flipped[a] ? "-" : "", std::string(1, "ijk"[axis[a]])));
  }
  return absl::StrCat("(", absl::StrJoin(parts, ", "), ")");
}

absl::StatusOr<AxisMapping> MatchGridToReference(const Grid& grid,
                                                 const Grid& reference,
                                                 const std::string& what) {
  AxisMapping mapping;
  std::array<int, 3> owner = {-1, -1, -1};
  for (int a = 0; a < 3; ++a) {
    const Vec3 axis = grid.Axis(a);
    int best = 0;
    double best_dot = 0;
    for (int b = 0; b < 3; ++b) {
      const double d = Dot(axis, reference.Axis(b));
      if (std::abs(d) > std::abs(best_dot)) {
        best_dot = d;
        best = b;
      }
    }
    const double sign = best_dot < 0 ? -1 : 1;
    const Vec3 ref_axis = reference.Axis(best);
    double deviation = 0;
    for (int c = 0; c < 3; ++c) {
      deviation = std::max(deviation, std::abs(axis[c] - sign * ref_axis[c]));
    }
    if (deviation > 1e-3) {
      const double degrees =
          std::acos(std::min(1.0, std::abs(best_dot))) * 180 / std::numbers::pi;
      return absl::InvalidArgumentError(absl::StrFormat(
          "axis %d of %s is tilted %.2f degrees against the nearest axis of "
          "the reference series (its voxels are not the reference's voxels)",
          a, what, degrees));
    }
    if (owner[best] >= 0) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "axes %d and %d of %s both run along the reference series' %s",
          owner[best], a, what, kAxisName[best]));
    }
    owner[best] = a;
    mapping.axis[a] = best;
    mapping.flipped[a] = best_dot < 0;
  }
  for (int a = 0; a < 3; ++a) {
    const int b = mapping.axis[a];
    if (grid.size[a] != reference.size[b]) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s is %d x %d x %d voxels: %d along its axis %d, where the "
          "reference series (%d x %d x %d) has %d along its %s",
          what, grid.size[0], grid.size[1], grid.size[2], grid.size[a], a,
          reference.size[0], reference.size[1], reference.size[2],
          reference.size[b], kAxisName[b]));
    }
    if (std::abs(grid.spacing[a] - reference.spacing[b]) >
        1e-3 * reference.spacing[b]) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s has spacing %g mm along its axis %d but the reference series %g "
          "mm along its %s",
          what, grid.spacing[a], a, reference.spacing[b], kAxisName[b]));
    }
  }
  // Where the file's first voxel centre lies in the reference's index space,
  // against where it must lie (index 0, or the last index of a flipped axis).
  const Vec3 first = reference.PhysicalToIndex(grid.origin);
  Vec3 off_mm = {0, 0, 0};
  for (int a = 0; a < 3; ++a) {
    const int b = mapping.axis[a];
    const double expected =
        mapping.flipped[a] ? static_cast<double>(reference.size[b] - 1) : 0.0;
    off_mm[b] = (first[b] - expected) * reference.spacing[b];
  }
  const double tolerance =
      0.01 + 0.01 * std::min({reference.spacing[0], reference.spacing[1],
                              reference.spacing[2]});
  int worst = 0;
  for (int b = 1; b < 3; ++b) {
    if (std::abs(off_mm[b]) > std::abs(off_mm[worst])) worst = b;
  }
  if (std::abs(off_mm[worst]) > tolerance) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the voxel centres of %s are %.3f mm off the reference series' along "
        "its %s (offsets i, j, k: %.3f, %.3f, %.3f mm)",
        what, std::abs(off_mm[worst]), kAxisName[worst], off_mm[0], off_mm[1],
        off_mm[2]));
  }
  return mapping;
}

template <typename T>
Volume<T> ToReferenceLayout(const Volume<T>& volume, const AxisMapping& mapping,
                            const Grid& reference) {
  Volume<T> out;
  out.grid = reference;
  out.data.resize(reference.VoxelCount());
  const Strides s = ReferenceStrides(mapping, reference.size);
  const Index3& n = volume.grid.size;
  const T* src = volume.data.data();
  for (int64_t c = 0; c < n[2]; ++c) {
    for (int64_t b = 0; b < n[1]; ++b) {
      int64_t dst = s.first + c * s.stride[2] + b * s.stride[1];
      for (int64_t a = 0; a < n[0]; ++a, dst += s.stride[0]) {
        out.data[dst] = *src++;
      }
    }
  }
  return out;
}

template <typename T>
Volume<T> ToFileLayout(const Volume<T>& volume, const AxisMapping& mapping,
                       const Grid& file_grid) {
  Volume<T> out;
  out.grid = file_grid;
  for (int a = 0; a < 3; ++a) {
    const int b = mapping.axis[a];
    const int64_t n = volume.grid.size[b];
    if (n != file_grid.size[a] && n > 1 && file_grid.size[a] > 1) {
      // More (or fewer) voxels over the same extent.
      out.grid.spacing[a] = file_grid.spacing[a] *
                            static_cast<double>(file_grid.size[a] - 1) /
                            static_cast<double>(n - 1);
    } else if (n != file_grid.size[a]) {
      out.grid.spacing[a] = volume.grid.spacing[b];
    }
    out.grid.size[a] = n;
  }
  out.data.resize(out.grid.VoxelCount());
  const Strides s = ReferenceStrides(mapping, volume.grid.size);
  const Index3& n = out.grid.size;
  T* dst = out.data.data();
  for (int64_t c = 0; c < n[2]; ++c) {
    for (int64_t b = 0; b < n[1]; ++b) {
      int64_t src = s.first + c * s.stride[2] + b * s.stride[1];
      for (int64_t a = 0; a < n[0]; ++a, src += s.stride[0]) {
        *dst++ = volume.data[src];
      }
    }
  }
  return out;
}

template Volume<uint8_t> ToReferenceLayout(const Volume<uint8_t>&,
                                           const AxisMapping&, const Grid&);
template Volume<uint16_t> ToReferenceLayout(const Volume<uint16_t>&,
                                            const AxisMapping&, const Grid&);
template Volume<float> ToReferenceLayout(const Volume<float>&,
                                         const AxisMapping&, const Grid&);
template Volume<uint8_t> ToFileLayout(const Volume<uint8_t>&,
                                      const AxisMapping&, const Grid&);
template Volume<uint16_t> ToFileLayout(const Volume<uint16_t>&,
                                       const AxisMapping&, const Grid&);
template Volume<float> ToFileLayout(const Volume<float>&, const AxisMapping&,
                                    const Grid&);

}  // namespace interslice
