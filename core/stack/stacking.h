// Linear stacking of per-slice distance maps onto the refined z grid
// (paper section 3, step 3; classic shape-based interpolation, Herman 1992).
//
// The original slices land on output grid nodes. A StackPlan says which:
// original slice s sits at output slice nodes[s] (nodes[0] == 0, strictly
// increasing), and output slices between two originals are linear blends of
// them. For a uniformly spaced series with N inserted intervals per gap,
// nodes[s] = s * N, giving Z' = (Z - 1) * N + 1 slices of spacing
// slice_spacing / N. For non-uniform spacing or missing slices, each original
// is snapped to the nearest node of a uniform output grid (see PlanStack).
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

// Where the original slices go on the output z grid.
struct StackPlan {
  // Output z spacing, mm: the median gap between originals divided by
  // `factor`.
  double spacing_mm = 1;
  // N of ChooseInsertionFactor for the median gap.
  int factor = 1;
  // Output slice index of each original slice; nodes[0] == 0, strictly
  // increasing.
  std::vector<int64_t> nodes;
  int64_t output_slices = 1;  // nodes.back() + 1
  // Largest |true position - node position| over the originals, mm; never
  // more than spacing_mm / 2.
  double max_snap_mm = 0;
  // Whether every gap is within 1% (or 0.01 mm) of the median gap.
  bool uniform = true;
  double min_gap_mm = 0, max_gap_mm = 0, median_gap_mm = 0;
};

// Plans the output grid for originals at `positions_mm` (along the slice
// normal, strictly increasing, at least one). The output spacing is
// median_gap / N, N from ChooseInsertionFactor(median_gap, ...), so a
// uniform series gets exactly the factor-based grid (nodes[s] = s * N).
// Otherwise each original goes to the nearest node, round((p_s - p_0) / h);
// a missing slice in an otherwise regular series (a gap that is a multiple
// of the median) lands exactly on a node. One original needs a spacing of
// its own: `single_slice_spacing_mm` (e.g. the slice thickness).
// INVALID_ARGUMENT for unsorted or non-finite positions, a bad resolution,
// two originals on the same node (names them and suggests a smaller
// --spacing or larger --factor), or an absurd number of output slices.
absl::StatusOr<StackPlan> PlanStack(const std::vector<double>& positions_mm,
                                    double inplane_spacing_mm,
                                    const ZResolution& resolution,
                                    double single_slice_spacing_mm = 1);

// The plan of a uniformly spaced series with Z slices and factor N.
StackPlan UniformStackPlan(int64_t slices, double slice_spacing_mm, int factor);

struct StackedField {
  // Refined grid: same x/y and direction as the input, z spacing
  // plan.spacing_mm, Z' slices, origin unchanged (output slice 0 is
  // original slice 0).
  Volume<float> field;
  // fixed_slices[k] != 0 where output slice k is an original slice.
  std::vector<uint8_t> fixed_slices;
  int factor = 1;
};

// Linear stacking of `slice_maps` (one 2D map per original slice, in order;
// its z spacing is ignored) by `plan`: output slice k between nodes[s] and
// nodes[s+1] is (1 - t) map[s] + t map[s+1], t = (k - nodes[s]) /
// (nodes[s+1] - nodes[s]). INVALID_ARGUMENT for an invalid grid or a plan
// that does not match it; RESOURCE_EXHAUSTED if the output would exceed
// max_voxels (checked before allocating).
absl::StatusOr<StackedField> StackLinear(const Volume<float>& slice_maps,
                                         const StackPlan& plan,
                                         int64_t max_voxels,
                                         const ComputeContext& context);

// The same for a uniformly spaced series and factor N (the plan of
// UniformStackPlan with the grid's z spacing). INVALID_ARGUMENT for N < 1.
absl::StatusOr<StackedField> StackLinear(const Volume<float>& slice_maps,
                                         int factor, int64_t max_voxels,
                                         const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_STACK_STACKING_H_
