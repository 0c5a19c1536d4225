#include "tools/eval/reconstruct.h"

#include <chrono>

#include "core/common/status_macros.h"
#include "core/stack/stacking.h"

namespace interslice::eval {

absl::StatusOr<Stacked> ContourAndStack(const Volume<float>& originals,
                                        const ContourOptions& contour,
                                        int factor,
                                        const ComputeContext& context) {
  INTERSLICE_ASSIGN_OR_RETURN(
      Volume<float> maps,
      ComputeSliceDistanceMaps(originals, contour, context));
  INTERSLICE_ASSIGN_OR_RETURN(
      StackedField stacked,
      StackLinear(maps, factor, int64_t{1} << 31, context));
  Stacked out;
  out.maps = std::move(maps);
  out.field = std::move(stacked.field);
  out.fixed_slices = std::move(stacked.fixed_slices);
  out.factor = stacked.factor;
  return out;
}

absl::StatusOr<Refined> Refine(const Stacked& stacked,
                               const SolverOptions& options,
                               const ComputeContext& context) {
  Refined out;
  out.field = stacked.field;
  const auto start = std::chrono::steady_clock::now();
  INTERSLICE_ASSIGN_OR_RETURN(
      out.result, Solve(out.field, stacked.fixed_slices, options, context));
  out.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  return out;
}

}  // namespace interslice::eval
