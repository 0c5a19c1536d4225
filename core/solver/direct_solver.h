// Private to core/solver: the exact direct solver (DESIGN.md section 1,
// "Beyond the paper").
#ifndef INTERSLICE_CORE_SOLVER_DIRECT_SOLVER_H_
#define INTERSLICE_CORE_SOLVER_DIRECT_SOLVER_H_

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/solver/curvature_operator.h"
#include "core/solver/solver.h"

namespace interslice::solver_internal {

// Replaces the free slices of `field` by the exact constrained minimiser of
// E + sum over free slices k of fidelity[k] * |f_k - g_k|^2 (g = the free
// slices of `field` on entry; fidelity empty or one weight >= 0 per slice,
// empty = plain E). Fills result.{initial_energy, energy, initial_residual,
// relative_residual, converged}. Runs inside the caller's task arena.
absl::Status DirectSolve(Volume<float>& field,
                         const std::vector<uint8_t>& fixed,
                         const CurvatureWeights& weights,
                         const StencilCoefficients& stencil,
                         const std::vector<double>& fidelity,
                         const ComputeContext& context, SolverResult& result);

}  // namespace interslice::solver_internal

#endif  // INTERSLICE_CORE_SOLVER_DIRECT_SOLVER_H_
