#include "core/solver/curvature_operator.h"

#include <algorithm>
#include <cmath>

#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {

CurvatureWeights CurvatureWeights::For(EnergyUnits units,
                                       const Vec3& spacing_mm) {
  CurvatureWeights w;
  if (units == EnergyUnits::kVoxel) return w;
  // Physical second derivatives: f_xx / hx^2 and f_xy / (hx hy), squared.
  const double hx2 = spacing_mm[0] * spacing_mm[0];
  const double hy2 = spacing_mm[1] * spacing_mm[1];
  const double hz2 = spacing_mm[2] * spacing_mm[2];
  w.xx = 1 / (hx2 * hx2);
  w.yy = 1 / (hy2 * hy2);
  w.zz = 1 / (hz2 * hz2);
  w.xy = 1 / (hx2 * hy2);
  w.xz = 1 / (hx2 * hz2);
  w.yz = 1 / (hy2 * hz2);
  return w;
}

std::string_view SolverMethodName(SolverMethod method) {
  switch (method) {
    case SolverMethod::kLinear:
      return "linear";
    case SolverMethod::kConjugateGradient:
      return "cg";
    case SolverMethod::kDirect:
      return "direct";
    case SolverMethod::kMorph:
      return "morph";
  }
  return "unknown";
}

std::string_view EnergyUnitsName(EnergyUnits units) {
  return units == EnergyUnits::kVoxel ? "voxel" : "mm";
}

namespace solver_internal {

// A = sum_a w_aa L_a^2 + sum_{a<b} 2 w_ab P_a P_b on the mirror-extended
// field, where L = [1 -2 1] (so L^2 = [1 -4 6 -4 1]) and
// P = C^T C = [-1/4 0 1/2 0 -1/4] for the central difference C = [-1/2 0 1/2].
// Both L and P are symmetric under half-sample mirroring, which is why the
// plain stencil on the extended field equals D^T D (DESIGN.md section 1).
StencilCoefficients StencilCoefficients::From(const CurvatureWeights& w) {
  StencilCoefficients c;
  c.centre =
      static_cast<float>(6 * (w.xx + w.yy + w.zz) + 0.5 * (w.xy + w.xz + w.yz));
  c.x1 = static_cast<float>(-4 * w.xx);
  c.y1 = static_cast<float>(-4 * w.yy);
  c.z1 = static_cast<float>(-4 * w.zz);
  c.x2 = static_cast<float>(w.xx - 0.25 * (w.xy + w.xz));
  c.y2 = static_cast<float>(w.yy - 0.25 * (w.xy + w.yz));
  c.z2 = static_cast<float>(w.zz - 0.25 * (w.xz + w.yz));
  c.xy = static_cast<float>(w.xy / 8);
  c.xz = static_cast<float>(w.xz / 8);
  c.yz = static_cast<float>(w.yz / 8);
  return c;
}

namespace {

// Rows of the input that the stencil reads for output row (j, k).
struct StencilRows {
  const float* c;
  const float *ym1, *yp1, *ym2, *yp2;
  const float *zm1, *zp1, *zm2, *zp2;
  const float *ym2zm2, *ym2zp2, *yp2zm2, *yp2zp2;
};

// One output element at column i, with x neighbours taken at the given
// (already mirrored) columns.
inline float StencilAt(const StencilRows& r, const StencilCoefficients& c,
                       int64_t i, int64_t im1, int64_t ip1, int64_t im2,
                       int64_t ip2) {
  float v = c.centre * r.c[i];
  v += c.x1 * (r.c[im1] + r.c[ip1]) + c.x2 * (r.c[im2] + r.c[ip2]);
  v += c.y1 * (r.ym1[i] + r.yp1[i]) + c.y2 * (r.ym2[i] + r.yp2[i]);
  v += c.z1 * (r.zm1[i] + r.zp1[i]) + c.z2 * (r.zm2[i] + r.zp2[i]);
  v += c.xy * (r.ym2[im2] + r.ym2[ip2] + r.yp2[im2] + r.yp2[ip2]);
  v += c.xz * (r.zm2[im2] + r.zm2[ip2] + r.zp2[im2] + r.zp2[ip2]);
  v += c.yz * (r.ym2zm2[i] + r.ym2zp2[i] + r.yp2zm2[i] + r.yp2zp2[i]);
  return v;
}

// The interior of a row (no mirroring in x): the hot loop of every solver.
// Compiled for AVX-512, AVX2 and baseline x86-64 and picked at load time.
// Without -ffp-contract the clones round identically (no fused multiply-add
// is formed in ISO C++ mode), so results do not depend on the machine.
INTERSLICE_SIMD_CLONES
void StencilRowInterior(const StencilRows& r, const StencilCoefficients& c,
                        int64_t begin, int64_t end, float* __restrict out) {
  const float* __restrict p = r.c;
  const float* __restrict ym1 = r.ym1;
  const float* __restrict yp1 = r.yp1;
  const float* __restrict ym2 = r.ym2;
  const float* __restrict yp2 = r.yp2;
  const float* __restrict zm1 = r.zm1;
  const float* __restrict zp1 = r.zp1;
  const float* __restrict zm2 = r.zm2;
  const float* __restrict zp2 = r.zp2;
  const float* __restrict d0 = r.ym2zm2;
  const float* __restrict d1 = r.ym2zp2;
  const float* __restrict d2 = r.yp2zm2;
  const float* __restrict d3 = r.yp2zp2;
  const StencilCoefficients k = c;
  for (int64_t i = begin; i < end; ++i) {
    float v = k.centre * p[i];
    v += k.x1 * (p[i - 1] + p[i + 1]) + k.x2 * (p[i - 2] + p[i + 2]);
    v += k.y1 * (ym1[i] + yp1[i]) + k.y2 * (ym2[i] + yp2[i]);
    v += k.z1 * (zm1[i] + zp1[i]) + k.z2 * (zm2[i] + zp2[i]);
    v += k.xy * (ym2[i - 2] + ym2[i + 2] + yp2[i - 2] + yp2[i + 2]);
    v += k.xz * (zm2[i - 2] + zm2[i + 2] + zp2[i - 2] + zp2[i + 2]);
    v += k.yz * (d0[i] + d1[i] + d2[i] + d3[i]);
    out[i] = v;
  }
}

}  // namespace

void ApplyOperatorSlice(const float* in, const Index3& size, int64_t k,
                        const StencilCoefficients& c, float* out_slice) {
  const int64_t nx = size[0], ny = size[1], nz = size[2];
  // The five slices the stencil reads, mirrored once per slice (Mirror's
  // divisions per row cost as much as the arithmetic at 256^3).
  const float* slice[5];
  for (int m = -2; m <= 2; ++m) slice[m + 2] = in + nx * ny * Mirror(k + m, nz);
  auto row = [&](int64_t j, int dk) {
    const int64_t mj = j >= 0 && j < ny ? j : Mirror(j, ny);
    return slice[dk + 2] + nx * mj;
  };
  for (int64_t j = 0; j < ny; ++j) {
    StencilRows r;
    r.c = row(j, 0);
    r.ym1 = row(j - 1, 0);
    r.yp1 = row(j + 1, 0);
    r.ym2 = row(j - 2, 0);
    r.yp2 = row(j + 2, 0);
    r.zm1 = row(j, -1);
    r.zp1 = row(j, 1);
    r.zm2 = row(j, -2);
    r.zp2 = row(j, 2);
    r.ym2zm2 = row(j - 2, -2);
    r.ym2zp2 = row(j - 2, 2);
    r.yp2zm2 = row(j + 2, -2);
    r.yp2zp2 = row(j + 2, 2);
    float* out = out_slice + nx * j;
    if (nx < 5) {
      for (int64_t i = 0; i < nx; ++i) {
        out[i] = StencilAt(r, c, i, Mirror(i - 1, nx), Mirror(i + 1, nx),
                           Mirror(i - 2, nx), Mirror(i + 2, nx));
      }
      continue;
    }
    // Mirrored columns at the two ends (nx >= 5): f(-1) = f(0), f(-2) = f(1),
    // f(nx) = f(nx-1), f(nx+1) = f(nx-2).
    out[0] = StencilAt(r, c, 0, 0, 1, 1, 2);
    out[1] = StencilAt(r, c, 1, 0, 2, 0, 3);
    StencilRowInterior(r, c, 2, nx - 2, out);
    out[nx - 2] = StencilAt(r, c, nx - 2, nx - 3, nx - 1, nx - 4, nx - 1);
    out[nx - 1] = StencilAt(r, c, nx - 1, nx - 2, nx - 1, nx - 3, nx - 2);
  }
}

INTERSLICE_SIMD_CLONES
double DotProduct(const float* __restrict a, const float* __restrict b,
                  int64_t n) {
  double lanes[kReductionLanes] = {};
  int64_t i = 0;
  for (; i + kReductionLanes <= n; i += kReductionLanes) {
    for (int l = 0; l < kReductionLanes; ++l) {
      lanes[l] += static_cast<double>(a[i + l]) * static_cast<double>(b[i + l]);
    }
  }
  double tail = 0;
  for (; i < n; ++i) tail += static_cast<double>(a[i]) * b[i];
  return SumLanes(lanes) + tail;
}

double OrderedSum(const std::vector<double>& partials) {
  double sum = 0;
  for (double p : partials) sum += p;
  return sum;
}

}  // namespace solver_internal

void ApplyCurvatureOperator(const float* in, float* out, const Index3& size,
                            const CurvatureWeights& weights, int threads) {
  using namespace solver_internal;
  const StencilCoefficients c = StencilCoefficients::From(weights);
  const int64_t plane = size[0] * size[1];
  tbb::task_arena arena(threads > 0 ? threads : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, size[2]),
                      [&](const tbb::blocked_range<int64_t>& range) {
                        for (int64_t k = range.begin(); k != range.end(); ++k) {
                          ApplyOperatorSlice(in, size, k, c, out + k * plane);
                        }
                      });
  });
}

double CurvatureEnergy(const float* f, const Index3& size,
                       const CurvatureWeights& w) {
  using solver_internal::Mirror;
  const int64_t nx = size[0], ny = size[1], nz = size[2];
  auto at = [&](int64_t i, int64_t j, int64_t k) -> double {
    return f[Mirror(i, nx) + nx * (Mirror(j, ny) + ny * Mirror(k, nz))];
  };
  double energy = 0;
  for (int64_t k = 0; k < nz; ++k) {
    for (int64_t j = 0; j < ny; ++j) {
      for (int64_t i = 0; i < nx; ++i) {
        const double v = at(i, j, k);
        const double fxx = at(i + 1, j, k) - 2 * v + at(i - 1, j, k);
        const double fyy = at(i, j + 1, k) - 2 * v + at(i, j - 1, k);
        const double fzz = at(i, j, k + 1) - 2 * v + at(i, j, k - 1);
        const double fxy = (at(i + 1, j + 1, k) + at(i - 1, j - 1, k) -
                            at(i + 1, j - 1, k) - at(i - 1, j + 1, k)) /
                           4;
        const double fxz = (at(i + 1, j, k + 1) + at(i - 1, j, k - 1) -
                            at(i + 1, j, k - 1) - at(i - 1, j, k + 1)) /
                           4;
        const double fyz = (at(i, j + 1, k + 1) + at(i, j - 1, k - 1) -
                            at(i, j + 1, k - 1) - at(i, j - 1, k + 1)) /
                           4;
        energy += w.xx * fxx * fxx + w.yy * fyy * fyy + w.zz * fzz * fzz +
                  2 * (w.xy * fxy * fxy + w.xz * fxz * fxz + w.yz * fyz * fyz);
      }
    }
  }
  return energy;
}

}  // namespace interslice
