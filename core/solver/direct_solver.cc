// The exact minimiser of the curvature energy with fixed slices.
//
// With mirror boundaries every term of A is a symmetric stencil in x and in
// y, so the 2D DCT-II (FFTW REDFT10) in x and y diagonalises it. For in-plane
// frequency (p, q), theta_p = pi p / X, theta_q = pi q / Y:
//   A(p,q) = sigma I + tau P_z + wzz L_z^2          (along z, Z' x Z')
//   sigma  = wxx (2 - 2 cos theta_p)^2 + wyy (2 - 2 cos theta_q)^2
//            + 2 wxy sin^2 theta_p sin^2 theta_q
//   tau    = 2 (wxz sin^2 theta_p + wyz sin^2 theta_q)
// with L_z^2 the mirrored [1 -4 6 -4 1] and P_z the mirrored
// [-1/4 0 1/2 0 -1/4] (DESIGN.md section 1, here with general weights).
// Moving the fixed slices to the right-hand side leaves a symmetric positive
// definite pentadiagonal system in the free slices for every frequency,
// solved by banded LDL^T in double. A fidelity term lambda |f - g|^2 on the
// free voxels adds lambda to the diagonal of every system and lambda g^ (the
// DCT of g) to its right-hand side. Cost: one 2D DCT per slice (forward on
// fixed slices, inverse on free ones) plus X*Y pentadiagonal solves.
#include "core/solver/direct_solver.h"

#include <fftw3.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <memory>
#include <mutex>

#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "tbb/blocked_range.h"
#include "tbb/enumerable_thread_specific.h"
#include "tbb/parallel_for.h"

namespace interslice::solver_internal {
namespace {

// FFTW's planner is not thread-safe; execution of an existing plan on new
// arrays (fftwf_execute_r2r) is.
std::mutex& FftwPlannerMutex() {
  static std::mutex mutex;
  return mutex;
}

struct FftwFloatBuffer {
  explicit FftwFloatBuffer(size_t n)
      : data(static_cast<float*>(fftwf_malloc(sizeof(float) * n))) {}
  ~FftwFloatBuffer() { fftwf_free(data); }
  FftwFloatBuffer(const FftwFloatBuffer&) = delete;
  FftwFloatBuffer& operator=(const FftwFloatBuffer&) = delete;
  float* data;
};

// A 2D real-to-real plan of one kind in both dimensions, over one slice
// (ny rows of nx floats), in place.
class SlicePlan {
 public:
  SlicePlan(int64_t nx, int64_t ny, fftw_r2r_kind kind) {
    FftwFloatBuffer probe(nx * ny);
    std::lock_guard<std::mutex> lock(FftwPlannerMutex());
    plan_ =
        fftwf_plan_r2r_2d(static_cast<int>(ny), static_cast<int>(nx),
                          probe.data, probe.data, kind, kind, FFTW_ESTIMATE);
  }
  ~SlicePlan() {
    std::lock_guard<std::mutex> lock(FftwPlannerMutex());
    if (plan_ != nullptr) fftwf_destroy_plan(plan_);
  }
  SlicePlan(const SlicePlan&) = delete;
  SlicePlan& operator=(const SlicePlan&) = delete;
  bool ok() const { return plan_ != nullptr; }
  // `data` must come from fftwf_malloc (same alignment as the plan's array).
  void Execute(float* data) const { fftwf_execute_r2r(plan_, data, data); }

 private:
  fftwf_plan plan_ = nullptr;
};

// A free row's coupling to one other slice, split by operator term so that
// the per-frequency value is cI * sigma + cP * tau + cL * wzz.
struct Coupling {
  int64_t column = 0;  // free position (band) or fixed position (rhs)
  double identity = 0, pz = 0, lz2 = 0;
};

struct FreeRow {
  Coupling band[3];             // offsets 0, +1, +2 in the free ordering
  std::vector<Coupling> fixed;  // couplings to fixed slices (moved to rhs)
};

// Folds the mirrored z stencils into per-free-row couplings.
std::vector<FreeRow> BuildRows(const std::vector<uint8_t>& fixed,
                               const std::vector<int64_t>& position) {
  const int64_t nz = static_cast<int64_t>(fixed.size());
  static constexpr double kPz[5] = {-0.25, 0, 0.5, 0, -0.25};
  static constexpr double kLz2[5] = {1, -4, 6, -4, 1};
  std::vector<FreeRow> rows;
  for (int64_t k = 0; k < nz; ++k) {
    if (fixed[k]) continue;
    FreeRow row;
    const int64_t u = position[k];
    for (int o = 0; o < 3; ++o) row.band[o].column = u + o;
    for (int m = -2; m <= 2; ++m) {
      const int64_t t = Mirror(k + m, nz);
      const double ci = m == 0 ? 1.0 : 0.0;
      const double cp = kPz[m + 2], cl = kLz2[m + 2];
      if (fixed[t]) {
        auto it = std::find_if(
            row.fixed.begin(), row.fixed.end(),
            [&](const Coupling& c) { return c.column == position[t]; });
        if (it == row.fixed.end()) {
          row.fixed.push_back({position[t], 0, 0, 0});
          it = row.fixed.end() - 1;
        }
        it->identity += ci;
        it->pz += cp;
        it->lz2 += cl;
        continue;
      }
      const int64_t offset = position[t] - u;
      if (offset < 0) continue;  // the symmetric lower band is implied
      row.band[offset].identity += ci;
      row.band[offset].pz += cp;
      row.band[offset].lz2 += cl;
    }
    rows.push_back(std::move(row));
  }
  return rows;
}

constexpr int kLanes = 16;  // frequencies p solved together (SIMD across p)

struct BandWorkspace {
  explicit BandWorkspace(int64_t n)
      : d(n * kLanes), l1(n * kLanes), l2(n * kLanes), y(n * kLanes) {}
  std::vector<double> d, l1, l2, y;
};

}  // namespace

absl::Status DirectSolve(Volume<float>& field,
                         const std::vector<uint8_t>& fixed,
                         const CurvatureWeights& w,
                         const StencilCoefficients& stencil,
                         const std::vector<double>& fidelity,
                         const ComputeContext& context, SolverResult& result) {
  const Index3 size = field.grid.size;
  const int64_t nx = size[0], ny = size[1], nz = size[2];
  const int64_t plane = nx * ny;
  float* f = field.data.data();

  const FieldStatistics before = MeasureField(f, size, fixed, stencil);
  result.initial_energy = before.energy;
  result.initial_residual = before.residual_norm;

  std::vector<int64_t> position(nz), fixed_slices, free_slices;
  for (int64_t k = 0; k < nz; ++k) {
    if (fixed[k]) {
      position[k] = static_cast<int64_t>(fixed_slices.size());
      fixed_slices.push_back(k);
    } else {
      position[k] = static_cast<int64_t>(free_slices.size());
      free_slices.push_back(k);
    }
  }
  const int64_t n_free = static_cast<int64_t>(free_slices.size());
  if (n_free == 0) {
    result.energy = before.energy;
    result.relative_residual = 0;
    result.converged = true;
    return absl::OkStatus();
  }
  const std::vector<FreeRow> rows = BuildRows(fixed, position);

  const SlicePlan forward(nx, ny, FFTW_REDFT10);
  const SlicePlan inverse(nx, ny, FFTW_REDFT01);
  if (!forward.ok() || !inverse.ok()) {
    return absl::InternalError("FFTW could not plan the 2D DCT");
  }
  tbb::enumerable_thread_specific<std::unique_ptr<FftwFloatBuffer>> buffers(
      [plane] { return std::make_unique<FftwFloatBuffer>(plane); });

  // 1. DCT-II of the fixed slices (into a separate buffer: the fixed slices of
  //    the field are never written, so they stay bit-identical).
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  std::vector<float> fixed_coefficients(fixed_slices.size() * plane);
  tbb::parallel_for(int64_t{0}, static_cast<int64_t>(fixed_slices.size()),
                    [&](int64_t s) {
                      float* buffer = buffers.local()->data;
                      const float* src = f + fixed_slices[s] * plane;
                      std::copy(src, src + plane, buffer);
                      forward.Execute(buffer);
                      std::copy(buffer, buffer + plane,
                                fixed_coefficients.data() + s * plane);
                    });
  // With a fidelity term, the free slices (g) are transformed in place: each
  // (q, p) block of them is read by the forward pass of its own systems
  // before the back substitution overwrites it with the solution.
  std::vector<double> lambda(n_free, 0.0);
  bool any_fidelity = false;
  if (!fidelity.empty()) {
    for (int64_t u = 0; u < n_free; ++u) {
      lambda[u] = fidelity[free_slices[u]];
      any_fidelity = any_fidelity || lambda[u] > 0;
    }
  }
  if (any_fidelity) {
    tbb::parallel_for(int64_t{0}, n_free, [&](int64_t u) {
      float* buffer = buffers.local()->data;
      float* slice = f + free_slices[u] * plane;
      std::copy(slice, slice + plane, buffer);
      forward.Execute(buffer);
      std::copy(buffer, buffer + plane, slice);
    });
  }
  context.Report({.stage = "solve", .fraction = 0.2});

  // 2. One pentadiagonal solve per frequency, kLanes frequencies at a time.
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  std::vector<double> lambda_x(nx), sin2_x(nx), lambda_y(ny), sin2_y(ny);
  for (int64_t p = 0; p < nx; ++p) {
    const double theta = M_PI * p / nx;
    lambda_x[p] = 2 - 2 * std::cos(theta);
    sin2_x[p] = std::sin(theta) * std::sin(theta);
  }
  for (int64_t q = 0; q < ny; ++q) {
    const double theta = M_PI * q / ny;
    lambda_y[q] = 2 - 2 * std::cos(theta);
    sin2_y[q] = std::sin(theta) * std::sin(theta);
  }
  tbb::enumerable_thread_specific<BandWorkspace> workspaces(
      [n_free] { return BandWorkspace(n_free); });
  std::atomic<bool> not_positive_definite{false};
  tbb::parallel_for(int64_t{0}, ny, [&](int64_t q) {
    BandWorkspace& ws = workspaces.local();
    for (int64_t p0 = 0; p0 < nx; p0 += kLanes) {
      const int lanes = static_cast<int>(std::min<int64_t>(kLanes, nx - p0));
      double sigma[kLanes], tau[kLanes];
      for (int l = 0; l < lanes; ++l) {
        const int64_t p = p0 + l;
        sigma[l] = w.xx * lambda_x[p] * lambda_x[p] +
                   w.yy * lambda_y[q] * lambda_y[q] +
                   2 * w.xy * sin2_x[p] * sin2_y[q];
        tau[l] = 2 * (w.xz * sin2_x[p] + w.yz * sin2_y[q]);
      }
      auto value = [&](const Coupling& c, int l) {
        return c.identity * sigma[l] + c.pz * tau[l] + c.lz2 * w.zz;
      };
      // Factor A_FF = L D L^T (unit lower band L with two subdiagonals) and
      // run the forward substitution on b = -A_FC c_fixed at the same time.
      for (int64_t u = 0; u < n_free; ++u) {
        const FreeRow& row = rows[u];
        double* d = &ws.d[u * kLanes];
        double* l1 = &ws.l1[u * kLanes];
        double* l2 = &ws.l2[u * kLanes];
        double* y = &ws.y[u * kLanes];
        for (int l = 0; l < lanes; ++l) {
          double rhs =
              lambda[u] > 0
                  ? lambda[u] * f[free_slices[u] * plane + q * nx + p0 + l]
                  : 0.0;
          for (const Coupling& c : row.fixed) {
            rhs -= value(c, l) *
                   fixed_coefficients[c.column * plane + q * nx + p0 + l];
          }
          // Entries A[u][u], A[u][u-1] (= A[u-1][u]), A[u][u-2].
          double a = value(row.band[0], l) + lambda[u];
          double l1_prev = 0, l2_prevprev = 0;
          if (u >= 1) {
            const double d1 = ws.d[(u - 1) * kLanes + l];
            const double a_u_um1 = value(rows[u - 1].band[1], l);
            double c_term = 0;
            if (u >= 2) {
              const double d2 = ws.d[(u - 2) * kLanes + l];
              l2_prevprev = value(rows[u - 2].band[2], l) / d2;
              // L[u][u-2] * L[u-1][u-2] * d[u-2]
              c_term = l2_prevprev * ws.l1[(u - 1) * kLanes + l] * d2;
              a -= l2_prevprev * l2_prevprev * d2;
              rhs -= l2_prevprev * ws.y[(u - 2) * kLanes + l];
            }
            l1_prev = (a_u_um1 - c_term) / d1;
            a -= l1_prev * l1_prev * d1;
            rhs -= l1_prev * ws.y[(u - 1) * kLanes + l];
          }
          d[l] = a;
          l1[l] = l1_prev;      // L[u][u-1]
          l2[l] = l2_prevprev;  // L[u][u-2]
          y[l] = rhs;
          if (!(a > 0)) not_positive_definite.store(true);
        }
      }
      // Back substitution: x = L^-T (D^-1 y), written into the free slices.
      for (int64_t u = n_free - 1; u >= 0; --u) {
        float* out = f + free_slices[u] * plane + q * nx + p0;
        for (int l = 0; l < lanes; ++l) {
          double x = ws.y[u * kLanes + l] / ws.d[u * kLanes + l];
          if (u + 1 < n_free) {
            x -= ws.l1[(u + 1) * kLanes + l] * ws.y[(u + 1) * kLanes + l];
          }
          if (u + 2 < n_free) {
            x -= ws.l2[(u + 2) * kLanes + l] * ws.y[(u + 2) * kLanes + l];
          }
          ws.y[u * kLanes + l] = x;  // y now holds the solution from u on
          out[l] = static_cast<float>(x);
        }
      }
    }
  });
  if (not_positive_definite.load()) {
    return absl::InternalError(
        "direct solver: a frequency system was not positive definite");
  }
  context.Report({.stage = "solve", .fraction = 0.7});

  // 3. Inverse DCT of the free slices; REDFT10 then REDFT01 scales by 4XY.
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  const float scale = 1.0f / static_cast<float>(4 * plane);
  tbb::parallel_for(int64_t{0}, n_free, [&](int64_t u) {
    float* buffer = buffers.local()->data;
    float* slice = f + free_slices[u] * plane;
    std::copy(slice, slice + plane, buffer);
    inverse.Execute(buffer);
    for (int64_t n = 0; n < plane; ++n) slice[n] = buffer[n] * scale;
  });

  const FieldStatistics after = MeasureField(f, size, fixed, stencil);
  result.energy = after.energy;
  result.relative_residual =
      before.residual_norm > 0 ? after.residual_norm / before.residual_norm : 0;
  result.converged = true;
  context.Report({.stage = "solve", .fraction = 1.0});
  return absl::OkStatus();
}

}  // namespace interslice::solver_internal
