// Refinement of a stacked distance field by global curvature minimisation
// with the original slices held fixed (paper sections 3-4, and DESIGN.md
// section 1 "Beyond the paper: an exact direct solver").
//
// The energy (paper eq. (1)-(2), with the eq. (2) typo fixed: E is the plain
// sum of c, which is quadratic in f) is
//   E(f) = sum over voxels of  wxx f_xx^2 + wyy f_yy^2 + wzz f_zz^2
//                            + 2 wxy f_xy^2 + 2 wxz f_xz^2 + 2 wyz f_yz^2
//   f_xx = f(i+1) - 2 f(i) + f(i-1),
//   f_xy = (f(i+1,j+1) + f(i-1,j-1) - f(i+1,j-1) - f(i-1,j+1)) / 4,
// with mirror (half-sample symmetric) extension at every face: f(-1) = f(0),
// f(-2) = f(1), f(n) = f(n-1), f(n+1) = f(n-2). In voxel units (the paper's,
// and the default) every w is 1; in millimetre units wxx = 1/hx^4 and
// wxy = 1/(hx^2 hy^2), with h the grid spacing in mm.
//
// The operator A = grad(E)/2 is the paper's Appendix 5x5x5 kernel (centre
// 19.5, -4 on the faces, 0.5 at distance 2 on the axes, 0.125 on the in-plane
// (+-2, +-2) diagonals) applied to the mirror-extended field; it is symmetric
// positive semi-definite and E(f) = f . A f. With at least one fixed slice the
// constrained minimiser is unique: A restricted to the free voxels is SPD.
//
// Methods:
// - kLinear: leave the linear stacking as it is.
// - kConjugateGradient: the paper's projected CG (residual zeroed on fixed
//   slices; alpha = r.r / d.Ad, Fletcher-Reeves beta, which equals the paper's
//   Polak-Ribiere beta on this quadratic), started from the linear stacking.
// - kDirect: the exact minimiser: a 2D DCT-II in x and y (FFTW) diagonalises
//   A, leaving one pentadiagonal SPD system along z per in-plane frequency.
//
// - kMorph (beyond the paper, issue 14): the field is a registration-based
//   stacking (core/morph StackMorph, chosen by the pipeline for this
//   method). With MorphOptions' defaults (cubic, C1-in-z trajectory,
//   monotone values, refine = false) the pipeline calls Solve() with kLinear
//   (the energy only): the field is used as stacked and core/morph's component
//   filter is applied. With MorphOptions::refine, Solve() runs the direct
//   solver exactly as for kDirect, with the fidelity term of SolverOptions
//   (MorphOptions' fidelity and taper), before the filter.
//
// Fixed slices are never written: their voxels come out bit-identical.
// Non-convergence is not an error: SolverResult says how far CG got.
// Results do not depend on the thread count (fixed partitioning, per-slice
// partial sums added in slice order).
#ifndef INTERSLICE_CORE_SOLVER_SOLVER_H_
#define INTERSLICE_CORE_SOLVER_SOLVER_H_

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

enum class SolverMethod { kLinear, kConjugateGradient, kDirect, kMorph };
enum class EnergyUnits { kVoxel, kMillimetre };

std::string_view SolverMethodName(
    SolverMethod method);  // "linear", "cg", "direct", "morph"
std::string_view EnergyUnitsName(EnergyUnits units);  // "voxel", "mm"

// Weights of the six terms of E (see above).
struct CurvatureWeights {
  double xx = 1, yy = 1, zz = 1, xy = 1, xz = 1, yz = 1;
  static CurvatureWeights For(EnergyUnits units, const Vec3& spacing_mm);
};

struct SolverOptions {
  SolverMethod method = SolverMethod::kConjugateGradient;
  // CG: at most this many iterations (the paper uses 15). >= 0.
  int max_iterations = 15;
  // CG: stop once |r_k| / |r_0| <= tolerance (r_0: residual of the linear
  // stacking). 0 disables the test, so exactly max_iterations run (or fewer
  // if the residual becomes exactly zero).
  double tolerance = 0;
  EnergyUnits units = EnergyUnits::kVoxel;
  // Weight lambda >= 0 of a fidelity term added to E:
  //   E_lambda(f) = E(f) + lambda * sum over free voxels (f - g)^2,
  // g = the field passed in (e.g. a registration-based stacking, core/morph).
  // 0 (default) is the paper's energy. lambda > 0 keeps the result close to
  // g while the curvature term removes its creases at the original slices;
  // the minimiser is still exact with the direct solver (lambda adds to the
  // diagonal of every per-frequency pentadiagonal system: the identity
  // commutes with the DCT). Only kDirect supports it: INVALID_ARGUMENT for
  // CG. With lambda > 0, SolverResult's residual is that of the curvature
  // term alone (|P A f|, not zero at the optimum of E_lambda), and energy is
  // E(f) without the fidelity term.
  double fidelity = 0;
  // With fidelity_taper, the weight of a free slice k between fixed slices a
  // and b is fidelity * (2 min(k - a, b - k) / (b - a))^2: zero next to the
  // original slices (where piecewise interpolations crease), full mid-gap.
  // Free slices beyond the first or last fixed slice get the full weight.
  bool fidelity_taper = false;
};

struct SolverResult {
  SolverMethod method = SolverMethod::kLinear;
  int iterations = 0;            // CG iterations done (0 for linear/direct)
  double initial_residual = 0;   // |P A f_0|, f_0 = linear stacking
  double relative_residual = 0;  // |P A f| / |P A f_0| of the result (1 for
                                 // linear; 0 if f_0 was already optimal)
  double initial_energy = 0;     // E(f_0)
  double energy = 0;             // E(f) of the result
  bool converged = false;        // tolerance reached (direct: always true)
};

// Refines `field` in place. fixed_slices[k] != 0 marks original slice k;
// at least one must be set. INVALID_ARGUMENT for a size mismatch, no fixed
// slice, negative iterations or tolerance; CANCELLED / DEADLINE_EXCEEDED
// from context.cancel (polled every CG iteration and per slice block of the
// direct solver; the field is then left partially refined).
absl::StatusOr<SolverResult> Solve(Volume<float>& field,
                                   const std::vector<uint8_t>& fixed_slices,
                                   const SolverOptions& options,
                                   const ComputeContext& context);

// out = A in, for a field of `size` voxels (i fastest). `out` must not
// alias `in`. Runs on `threads` threads (0 = all).
void ApplyCurvatureOperator(const float* in, float* out, const Index3& size,
                            const CurvatureWeights& weights, int threads = 0);

// E(f) evaluated term by term from its definition (second differences of the
// mirror-extended field), in double. An independent check of f . A f.
double CurvatureEnergy(const float* field, const Index3& size,
                       const CurvatureWeights& weights);

}  // namespace interslice

#endif  // INTERSLICE_CORE_SOLVER_SOLVER_H_
