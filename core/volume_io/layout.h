// Volume files whose voxels are a reference grid's voxels in another index
// layout (issue 24): the axes permuted and/or running the other way, as
// nibabel, dcm2niix and segmentation models write them (RAS, rows flipped,
// sometimes axes swapped) next to a DICOM series read in its own order.
//
// A file grid F lies on a reference grid R when every index axis a of F is
// parallel or antiparallel to one index axis b = axis[a] of R, with the same
// number of voxels and the same spacing, and F's voxel centres are R's
// voxel centres. Then file index f and reference index r of the same voxel
// are related by r[axis[a]] = flipped[a] ? n_b - 1 - f[a] : f[a]: a signed
// permutation, applied exactly (no resampling, no interpolation).
#ifndef INTERSLICE_CORE_VOLUME_IO_LAYOUT_H_
#define INTERSLICE_CORE_VOLUME_IO_LAYOUT_H_

#include <array>
#include <cstdint>
#include <string>

#include "absl/status/statusor.h"
#include "core/geometry/volume.h"

namespace interslice {

// File index axis a is reference index axis axis[a]; flipped[a] when it runs
// the other way.
struct AxisMapping {
  std::array<int, 3> axis = {0, 1, 2};
  std::array<bool, 3> flipped = {false, false, false};

  bool IsIdentity() const {
    return axis == std::array<int, 3>{0, 1, 2} &&
           flipped == std::array<bool, 3>{false, false, false};
  }
  // E.g. "(-i, j, k)": for each file axis, the reference axis it runs along
  // (i columns, j rows, k slices) and "-" when flipped.
  std::string Describe() const;
};

// The mapping of `grid` (a file's, LPS as ITK reads it) onto `reference`.
// Tolerances (those of a grid "up to rounding"): axes parallel within 1e-3
// (direction cosines), spacing within 0.1%, voxel centres within 0.01 mm +
// 1% of the smallest reference spacing. INVALID_ARGUMENT with `what` (e.g.
// "the label map") as subject, saying what differs, in this order:
// - an axis not parallel to any reference axis ("axis 2 of the label map is
//   tilted 12.0 degrees against the nearest axis of the reference series");
//   two file axes on the same reference axis;
// - the voxel count or the spacing along an axis;
// - voxel centres that do not coincide: by how many mm, along which
//   reference axis ("... are 1.250 mm off the reference series' voxel
//   centres along its slice axis (k)").
absl::StatusOr<AxisMapping> MatchGridToReference(const Grid& grid,
                                                 const Grid& reference,
                                                 const std::string& what);

// The voxels of `volume` (on a file grid that MatchGridToReference mapped
// onto `reference` with `mapping`) in the reference's layout, on `reference`
// itself.
template <typename T>
Volume<T> ToReferenceLayout(const Volume<T>& volume, const AxisMapping& mapping,
                            const Grid& reference);

// The inverse, for results: `volume` on a grid with the reference's axes
// (the reference grid, or one with more slices over the same extent, as the
// fill's finer output grid) in the layout of `file_grid` (the file's grid
// as read): the file's axis order, directions and origin (the same physical
// first voxel: a finer grid spans the same extent), its voxel counts and
// spacings replaced by `volume`'s along the corresponding axes.
template <typename T>
Volume<T> ToFileLayout(const Volume<T>& volume, const AxisMapping& mapping,
                       const Grid& file_grid);

}  // namespace interslice

#endif  // INTERSLICE_CORE_VOLUME_IO_LAYOUT_H_
