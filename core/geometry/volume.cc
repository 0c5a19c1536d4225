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

absl::StatusOr<VoxelBox> PhysicalBoxToVoxelBox(const PhysicalBox& box,
                                               const Grid& grid) {
  // Map the 8 corners into index space; the box may be rotated there.
  Vec3 lo = {INFINITY, INFINITY, INFINITY};
  Vec3 hi = {-INFINITY, -INFINITY, -INFINITY};
  for (int corner = 0; corner < 8; ++corner) {
    const Vec3 p = {(corner & 1) ? box.max[0] : box.min[0],
                    (corner & 2) ? box.max[1] : box.min[1],
                    (corner & 4) ? box.max[2] : box.min[2]};
    const Vec3 index = grid.PhysicalToIndex(p);
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min(lo[a], index[a]);
      hi[a] = std::max(hi[a], index[a]);
    }
  }
  VoxelBox out;
  for (int a = 0; a < 3; ++a) {
    constexpr double kEps = 1e-6;
    const int64_t b = std::max<int64_t>(0, std::ceil(lo[a] - kEps));
    const int64_t e =
        std::min<int64_t>(grid.size[a], std::floor(hi[a] + kEps) + 1);
    if (b >= e) {
      return absl::InvalidArgumentError(
          "the physical region of interest contains no voxel centre");
    }
    out.begin[a] = b;
    out.end[a] = e;
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
