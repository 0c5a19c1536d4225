// Volume geometry in DICOM patient space and dense voxel volumes.
//
// Conventions (all modules follow them):
// - Index axes: i (column, fastest in memory), j (row), k (slice). A voxel
//   (i, j, k) lives at data[i + size[0] * (j + size[1] * k)].
// - Physical space is DICOM patient space, LPS, in millimetres.
// - origin is the centre of voxel (0, 0, 0); spacing is the centre-to-centre
//   distance along each index axis (mm, > 0); direction holds the unit LPS
//   vector of index axis c in column c (row-major 3x3, like ITK).
//   physical = origin + direction * (spacing .* index).
#ifndef INTERSLICE_CORE_GEOMETRY_VOLUME_H_
#define INTERSLICE_CORE_GEOMETRY_VOLUME_H_

#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace interslice {

using Vec3 = std::array<double, 3>;
using Index3 = std::array<int64_t, 3>;
using Mat3 = std::array<double, 9>;  // row-major

constexpr Mat3 kIdentityDirection = {1, 0, 0, 0, 1, 0, 0, 0, 1};

struct Grid {
  Index3 size = {0, 0, 0};
  Vec3 spacing = {1, 1, 1};
  Vec3 origin = {0, 0, 0};
  Mat3 direction = kIdentityDirection;

  int64_t VoxelCount() const { return size[0] * size[1] * size[2]; }
  int64_t SliceVoxelCount() const { return size[0] * size[1]; }
  int64_t LinearIndex(int64_t i, int64_t j, int64_t k) const {
    return i + size[0] * (j + size[1] * k);
  }
  // Continuous index -> LPS mm.
  Vec3 IndexToPhysical(const Vec3& index) const;
  // LPS mm -> continuous index (exact inverse of IndexToPhysical for an
  // orthonormal direction).
  Vec3 PhysicalToIndex(const Vec3& point) const;
  // Column c of direction.
  Vec3 Axis(int c) const {
    return {direction[c], direction[3 + c], direction[6 + c]};
  }

  // INVALID_ARGUMENT unless sizes are positive, spacings positive and finite,
  // and the direction matrix is orthonormal (to 1e-4).
  absl::Status Validate() const;
  std::string DebugString() const;
};

// A half-open box of voxel indices [begin, end) in some grid's index space.
struct VoxelBox {
  Index3 begin = {0, 0, 0};
  Index3 end = {0, 0, 0};
  Index3 Size() const {
    return {end[0] - begin[0], end[1] - begin[1], end[2] - begin[2]};
  }
};

// An axis-aligned box in LPS patient space, in mm.
struct PhysicalBox {
  Vec3 min = {0, 0, 0};
  Vec3 max = {0, 0, 0};
};

// INVALID_ARGUMENT (naming the offending axis and bounds) unless
// 0 <= begin < end <= grid.size on every axis.
absl::Status ValidateVoxelBox(const VoxelBox& box, const Grid& grid);

// The smallest voxel box (clipped to the grid) whose voxel centres cover
// every voxel centre inside `box`, for any orientation of the grid: the box
// is an axis-aligned box in LPS mm, which may cut the grid's index axes
// obliquely; the result is exact (each row of voxel centres is intersected
// with the box), not the bounding box of the box's corners.
// slice_offsets_mm: where slice k lies along the grid's third axis, mm from
// slice 0's plane (DicomSeries::slices[k].position_along_normal minus that
// of slice 0: the truth for non-uniform or tilt-corrected series), one per
// slice, increasing; empty = k * spacing[2].
// INVALID_ARGUMENT if the box is not finite or min > max on some axis; if it
// misses the series, naming the index axis and by how many mm; if it holds
// no voxel centre although it overlaps the series' extent.
absl::StatusOr<VoxelBox> PhysicalBoxToVoxelBox(
    const PhysicalBox& box, const Grid& grid,
    std::span<const double> slice_offsets_mm = {});

// The geometry of the sub-grid `box` of `grid` (same spacing and direction,
// origin moved to voxel box.begin). `box` must be valid for `grid`.
Grid CropGrid(const Grid& grid, const VoxelBox& box);

// A dense volume with its geometry. data.size() == grid.VoxelCount().
template <typename T>
struct Volume {
  Grid grid;
  std::vector<T> data;

  T& at(int64_t i, int64_t j, int64_t k) {
    return data[grid.LinearIndex(i, j, k)];
  }
  const T& at(int64_t i, int64_t j, int64_t k) const {
    return data[grid.LinearIndex(i, j, k)];
  }
};

// Copies the voxels of `box` out of `volume`. `box` must be valid.
template <typename T>
Volume<T> CropVolume(const Volume<T>& volume, const VoxelBox& box) {
  Volume<T> out;
  out.grid = CropGrid(volume.grid, box);
  out.data.resize(out.grid.VoxelCount());
  const Index3 n = out.grid.size;
  for (int64_t k = 0; k < n[2]; ++k) {
    for (int64_t j = 0; j < n[1]; ++j) {
      const T* src =
          &volume.at(box.begin[0], box.begin[1] + j, box.begin[2] + k);
      T* dst = &out.data[out.grid.LinearIndex(0, j, k)];
      std::copy(src, src + n[0], dst);
    }
  }
  return out;
}

}  // namespace interslice

#endif  // INTERSLICE_CORE_GEOMETRY_VOLUME_H_
