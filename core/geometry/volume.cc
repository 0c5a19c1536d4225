#include "core/geometry/volume.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace interslice {

Vec3 Grid::IndexToPhysical(const Vec3& index) const {
  Vec3 p = origin;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      p[r] += direction[3 * r + c] * spacing[c] * index[c];
    }
  }
  return p;
}

Vec3 Grid::PhysicalToIndex(const Vec3& point) const {
  // direction is orthonormal, so its inverse is its transpose.
  Vec3 index = {0, 0, 0};
  for (int c = 0; c < 3; ++c) {
    double dot = 0;
    for (int r = 0; r < 3; ++r)
      dot += direction[3 * r + c] * (point[r] - origin[r]);
    index[c] = dot / spacing[c];
  }
  return index;
}

absl::Status Grid::Validate() const {
  for (int a = 0; a < 3; ++a) {
    if (size[a] <= 0) {
      return absl::InvalidArgumentError(absl::StrCat("grid size along axis ", a,
                                                     " is ", size[a],
                                                     "; it must be positive"));
    }
    if (!(spacing[a] > 0) || !std::isfinite(spacing[a])) {
      return absl::InvalidArgumentError(
          absl::StrCat("grid spacing along axis ", a, " is ", spacing[a],
                       " mm; it must be positive and finite"));
    }
    if (!std::isfinite(origin[a])) {
      return absl::InvalidArgumentError("grid origin is not finite");
    }
  }
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      const Vec3 u = Axis(a), v = Axis(b);
      const double dot = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
      if (std::abs(dot - (a == b ? 1.0 : 0.0)) > 1e-4) {
        return absl::InvalidArgumentError(
            "grid direction cosines are not orthonormal");
      }
    }
  }
  return absl::OkStatus();
}

std::string Grid::DebugString() const {
  return absl::StrFormat(
      "size %dx%dx%d, spacing %.4gx%.4gx%.4g mm, origin (%.4f, %.4f, %.4f) mm",
      size[0], size[1], size[2], spacing[0], spacing[1], spacing[2], origin[0],
      origin[1], origin[2]);
}

absl::Status ValidateVoxelBox(const VoxelBox& box, const Grid& grid) {
  static constexpr char kAxis[] = "xyz";
  for (int a = 0; a < 3; ++a) {
    if (box.begin[a] < 0 || box.end[a] > grid.size[a] ||
        box.begin[a] >= box.end[a]) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "region of interest along %c is [%d, %d) but must satisfy "
          "0 <= begin < end <= %d",
          kAxis[a], box.begin[a], box.end[a], grid.size[a]));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<VoxelBox> PhysicalBoxToVoxelBox(
    const PhysicalBox& box, const Grid& grid,
    std::span<const double> slice_offsets_mm) {
  static constexpr const char* kAxisName[] = {"x (columns)", "y (rows)",
                                              "z (slices)"};
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(box.min[a]) || !std::isfinite(box.max[a]) ||
        box.min[a] > box.max[a]) {
      return absl::InvalidArgumentError(
          "the region of interest in mm must be finite with min <= max on "
          "every axis");
    }
  }
  if (!slice_offsets_mm.empty() &&
      static_cast<int64_t>(slice_offsets_mm.size()) != grid.size[2]) {
    return absl::InvalidArgumentError(
        absl::StrFormat("%d slice positions for a grid of %d slices",
                        slice_offsets_mm.size(), grid.size[2]));
  }
  const auto offset = [&](int64_t k) {
    return slice_offsets_mm.empty() ? k * grid.spacing[2] : slice_offsets_mm[k];
  };
  // Voxel centres on the box's surface count as inside (rounding of mm
  // values typed by a person or a viewer).
  constexpr double kEpsMm = 1e-6;
  const Vec3 row = grid.Axis(0), column = grid.Axis(1), normal = grid.Axis(2);
  const auto dot = [](const Vec3& u, const Vec3& v) {
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
  };
  // The box's corners in the grid's frame, mm from the origin along each
  // index axis; its extent there, against the voxel centres' extent.
  Vec3 lo = {INFINITY, INFINITY, INFINITY};
  Vec3 hi = {-INFINITY, -INFINITY, -INFINITY};
  for (int corner = 0; corner < 8; ++corner) {
    const Vec3 d = {((corner & 1) ? box.max[0] : box.min[0]) - grid.origin[0],
                    ((corner & 2) ? box.max[1] : box.min[1]) - grid.origin[1],
                    ((corner & 4) ? box.max[2] : box.min[2]) - grid.origin[2]};
    const Vec3 t = {dot(row, d), dot(column, d), dot(normal, d)};
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min(lo[a], t[a]);
      hi[a] = std::max(hi[a], t[a]);
    }
  }
  const Vec3 first = {0, 0, std::min(offset(0), offset(grid.size[2] - 1))};
  const Vec3 last = {(grid.size[0] - 1) * grid.spacing[0],
                     (grid.size[1] - 1) * grid.spacing[1],
                     std::max(offset(0), offset(grid.size[2] - 1))};
  for (int a = 0; a < 3; ++a) {
    if (hi[a] < first[a] - kEpsMm) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "the region of interest in mm misses the series: along %s it ends "
          "%.2f mm before the first voxel centre",
          kAxisName[a], first[a] - hi[a]));
    }
    if (lo[a] > last[a] + kEpsMm) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "the region of interest in mm misses the series: along %s it "
          "starts %.2f mm beyond the last voxel centre",
          kAxisName[a], lo[a] - last[a]));
    }
  }
  // Every row of voxel centres (j, k) that the corners' extent reaches,
  // intersected with the box: the centres of row (j, k) are
  // p(i) = origin + column * j * spacing[1] + normal * offset(k)
  //        + row * i * spacing[0],
  // and min <= p(i) <= max on each LPS axis bounds i to an interval.
  const int64_t j_begin =
      std::max<int64_t>(0, std::ceil((lo[1] - kEpsMm) / grid.spacing[1]));
  const int64_t j_end = std::min<int64_t>(
      grid.size[1], std::floor((hi[1] + kEpsMm) / grid.spacing[1]) + 1);
  VoxelBox out{{grid.size[0], grid.size[1], grid.size[2]}, {0, 0, 0}};
  for (int64_t k = 0; k < grid.size[2]; ++k) {
    const double t = offset(k);
    if (t < lo[2] - kEpsMm || t > hi[2] + kEpsMm) continue;
    for (int64_t j = j_begin; j < j_end; ++j) {
      double i_lo = 0;
      double i_hi = static_cast<double>(grid.size[0] - 1);
      for (int a = 0; a < 3 && i_lo <= i_hi; ++a) {
        const double p =
            grid.origin[a] + column[a] * j * grid.spacing[1] + normal[a] * t;
        const double step = row[a] * grid.spacing[0];
        const double min = box.min[a] - kEpsMm, max = box.max[a] + kEpsMm;
        if (std::abs(step) < 1e-12) {
          if (p < min || p > max) i_hi = -1;
          continue;
        }
        double from = (min - p) / step, to = (max - p) / step;
        if (from > to) std::swap(from, to);
        i_lo = std::max(i_lo, std::ceil(from));
        i_hi = std::min(i_hi, std::floor(to));
      }
      if (i_lo > i_hi) continue;
      const Index3 first_voxel = {static_cast<int64_t>(i_lo), j, k};
      const Index3 last_voxel = {static_cast<int64_t>(i_hi), j, k};
      for (int a = 0; a < 3; ++a) {
        out.begin[a] = std::min(out.begin[a], first_voxel[a]);
        out.end[a] = std::max(out.end[a], last_voxel[a] + 1);
      }
    }
  }
  if (out.begin[0] >= out.end[0]) {
    return absl::InvalidArgumentError(
        "the region of interest in mm overlaps the series' extent but "
        "contains no voxel centre (it is thinner than the voxel spacing, or "
        "the series is oblique to it and it lies beyond a corner)");
  }
  return out;
}

Grid CropGrid(const Grid& grid, const VoxelBox& box) {
  Grid out = grid;
  out.size = box.Size();
  out.origin = grid.IndexToPhysical({static_cast<double>(box.begin[0]),
                                     static_cast<double>(box.begin[1]),
                                     static_cast<double>(box.begin[2])});
  return out;
}

}  // namespace interslice
