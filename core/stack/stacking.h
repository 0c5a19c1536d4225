// Linear stacking of per-slice distance maps onto the refined z grid
// (paper section 3, step 3; classic shape-based interpolation, Herman 1992).
//
// The original slices land on output grid nodes: with N inserted intervals
// per gap, original slice s sits at output slice s * N, giving
// Z' = (Z - 1) * N + 1 slices of spacing slice_spacing / N. Slices between
// two originals are linear blends of them.
#ifndef INTERSLICE_CORE_STACK_STACKING_H_
#define INTERSLICE_CORE_STACK_STACKING_H_

#include <cstdint>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

// How the user asks for the output z resolution. At most one is set; with
// neither, the output is (as nearly as integer N allows) isotropic: the
// target spacing is the smaller in-plane spacing.
struct ZResolution {
  std::optional<int> factor;         // N, >= 1
  std::optional<double> spacing_mm;  // target output z spacing, > 0
};

// N for a series of `slice_spacing_mm` and in-plane spacing
// `inplane_spacing_mm`: factor if given, else max(1, round(slice / target)).
// INVALID_ARGUMENT for both set, factor < 1 or > 1024, non-positive or
// non-finite spacing.
absl::StatusOr<int> ChooseInsertionFactor(double slice_spacing_mm,
                                          double inplane_spacing_mm,
                                          const ZResolution& resolution);

struct StackedField {
  // Refined grid: same x/y and direction as the input, z spacing divided by
  // N, Z' slices, origin unchanged (output slice 0 is original slice 0).
  Volume<float> field;
  // fixed_slices[k] != 0 where output slice k is an original slice.
  std::vector<uint8_t> fixed_slices;
  int factor = 1;
};

// Linear stacking of `slice_maps` (one 2D map per original slice, uniformly
// spaced along z) with factor N. INVALID_ARGUMENT for N < 1 or an invalid
// grid; RESOURCE_EXHAUSTED if the output would exceed max_voxels.
absl::StatusOr<StackedField> StackLinear(const Volume<float>& slice_maps,
                                         int factor, int64_t max_voxels,
                                         const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_STACK_STACKING_H_
