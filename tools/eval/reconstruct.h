// The one place where the evaluation harness calls the core pipeline stages
// contour -> stack -> solve (the same calls, in the same order, as
// core/pipeline/pipeline_stages.cc). If the stacking API changes (e.g. to
// position-based stacking), only reconstruct.cc needs to follow.
#ifndef INTERSLICE_TOOLS_EVAL_RECONSTRUCT_H_
#define INTERSLICE_TOOLS_EVAL_RECONSTRUCT_H_

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/sdf/signed_distance.h"
#include "core/solver/solver.h"

namespace interslice::eval {

struct Stacked {
  // Output grid: original slice s is output slice s * factor; z spacing is
  // the originals' spacing / factor; origin of original slice 0.
  Volume<float> field;
  std::vector<uint8_t> fixed_slices;
  int factor = 1;
  Volume<float> maps;  // the 2D distance maps of the originals
};

// 2D signed distance maps of `originals` (uniformly spaced grey slices,
// ComputeSliceDistanceMaps) stacked linearly with `factor` (StackLinear).
absl::StatusOr<Stacked> ContourAndStack(const Volume<float>& originals,
                                        const ContourOptions& contour,
                                        int factor,
                                        const ComputeContext& context);

// Solve() on a copy of the stacked field.
struct Refined {
  Volume<float> field;
  SolverResult result;
  double seconds = 0;
};
absl::StatusOr<Refined> Refine(const Stacked& stacked,
                               const SolverOptions& options,
                               const ComputeContext& context);

}  // namespace interslice::eval

#endif  // INTERSLICE_TOOLS_EVAL_RECONSTRUCT_H_
