// Private to core/solver: the stencil of A = grad(E)/2 applied slice by slice,
// shared by the CG and direct solvers. See solver.h for the definition.
#ifndef INTERSLICE_CORE_SOLVER_CURVATURE_OPERATOR_H_
#define INTERSLICE_CORE_SOLVER_CURVATURE_OPERATOR_H_

#include <cstdint>
#include <vector>

#include "core/geometry/volume.h"
#include "core/solver/solver.h"

namespace interslice::solver_internal {

// Coefficients of the 5x5x5 stencil for given weights. In voxel units they
// are the paper's Appendix kernel: centre 19.5, axis +-1: -4, axis +-2: 0.5,
// in-plane diagonals (+-2, +-2): 0.125.
struct StencilCoefficients {
  float centre;
  float x1, x2, y1, y2, z1, z2;  // axis neighbours at distance 1 and 2
  float xy, xz, yz;              // (+-2, +-2) diagonals in each plane
  static StencilCoefficients From(const CurvatureWeights& w);
};

// Half-sample symmetric index: maps any integer to [0, n).
inline int64_t Mirror(int64_t i, int64_t n) {
  const int64_t period = 2 * n;
  i %= period;
  if (i < 0) i += period;
  return i < n ? i : period - 1 - i;
}

// out_slice = (A in)[slice k], nx * ny floats.
void ApplyOperatorSlice(const float* in, const Index3& size, int64_t k,
                        const StencilCoefficients& c, float* out_slice);

// Hot loops are compiled for several instruction sets and dispatched at load
// time (GCC function multi-versioning); elsewhere they compile once.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define INTERSLICE_SIMD_CLONES \
  __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define INTERSLICE_SIMD_CLONES
#endif

// Reductions accumulate in double over this many independent lanes (element
// n goes to lane n % kReductionLanes), combined in lane order: vectorisable,
// and the same result whatever the instruction set or thread count.
inline constexpr int kReductionLanes = 16;

inline double SumLanes(const double (&lanes)[kReductionLanes]) {
  double sum = 0;
  for (double v : lanes) sum += v;
  return sum;
}

// sum a[n] * b[n] in double (lane order as above).
double DotProduct(const float* a, const float* b, int64_t n);

// Per-slice partial sums, added in slice order for determinism.
double OrderedSum(const std::vector<double>& partials);

struct FieldStatistics {
  double energy = 0;         // E(f) = f . A f
  double residual_norm = 0;  // |P A f|, P zeroing the fixed slices
};

// One streaming pass of the operator (no full-volume scratch). Must run
// inside the caller's task arena.
FieldStatistics MeasureField(const float* f, const Index3& size,
                             const std::vector<uint8_t>& fixed,
                             const StencilCoefficients& c);

}  // namespace interslice::solver_internal

#endif  // INTERSLICE_CORE_SOLVER_CURVATURE_OPERATOR_H_
