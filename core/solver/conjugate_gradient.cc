// Solve(): validation, the statistics shared by every method, and the
// paper's projected conjugate gradient (section 4 and Appendix).
#include <algorithm>
#include <cmath>
#include <tuple>
#include <utility>
#include <vector>

#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/solver/curvature_operator.h"
#include "core/solver/direct_solver.h"
#include "core/solver/solver.h"
#include "tbb/blocked_range.h"
#include "tbb/enumerable_thread_specific.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace solver_internal {

FieldStatistics MeasureField(const float* f, const Index3& size,
                             const std::vector<uint8_t>& fixed,
                             const StencilCoefficients& c) {
  const int64_t plane = size[0] * size[1];
  std::vector<double> energy(size[2]), residual(size[2]);
  tbb::enumerable_thread_specific<std::vector<float>> scratch(
      [plane] { return std::vector<float>(plane); });
  tbb::parallel_for(tbb::blocked_range<int64_t>(0, size[2]),
                    [&](const tbb::blocked_range<int64_t>& range) {
                      std::vector<float>& af = scratch.local();
                      for (int64_t k = range.begin(); k != range.end(); ++k) {
                        ApplyOperatorSlice(f, size, k, c, af.data());
                        energy[k] = DotProduct(f + k * plane, af.data(), plane);
                        residual[k] =
                            fixed[k] ? 0.0
                                     : DotProduct(af.data(), af.data(), plane);
                      }
                    });
  return {OrderedSum(energy), std::sqrt(OrderedSum(residual))};
}

}  // namespace solver_internal

namespace {

using solver_internal::DotProduct;
using solver_internal::FieldStatistics;

// r -= alpha q; returns r . r (lane order, see DotProduct).
INTERSLICE_SIMD_CLONES
double UpdateResidual(float* __restrict r, const float* __restrict q,
                      float alpha, int64_t n) {
  constexpr int kLanes = solver_internal::kReductionLanes;
  double lanes[kLanes] = {};
  int64_t i = 0;
  for (; i + kLanes <= n; i += kLanes) {
    for (int l = 0; l < kLanes; ++l) {
      r[i + l] -= alpha * q[i + l];
      lanes[l] += static_cast<double>(r[i + l]) * r[i + l];
    }
  }
  double tail = 0;
  for (; i < n; ++i) {
    r[i] -= alpha * q[i];
    tail += static_cast<double>(r[i]) * r[i];
  }
  return solver_internal::SumLanes(lanes) + tail;
}

// f += alpha d; d = r + beta d. The solution update rides on the direction
// pass, which reads d anyway: one read of d per iteration instead of two
// (44 bytes of traffic per voxel and iteration instead of 48).
INTERSLICE_SIMD_CLONES
void UpdateSolutionAndDirection(float* __restrict f, float* __restrict d,
                                const float* __restrict r, float alpha,
                                float beta, int64_t n) {
  for (int64_t i = 0; i < n; ++i) {
    f[i] += alpha * d[i];
    d[i] = r[i] + beta * d[i];
  }
}
using solver_internal::MeasureField;
using solver_internal::OrderedSum;
using solver_internal::StencilCoefficients;

// Projected CG on the free slices (paper section 4; Shewchuk's formulation).
// Vectors are float with double reductions; per-slice partial sums keep the
// result independent of the thread count.
absl::Status ConjugateGradient(Volume<float>& field,
                               const std::vector<uint8_t>& fixed,
                               const SolverOptions& options,
                               const StencilCoefficients& c,
                               const ComputeContext& context,
                               SolverResult& result) {
  const Index3 size = field.grid.size;
  const int64_t plane = size[0] * size[1];
  const int64_t nz = size[2];
  float* f = field.data.data();
  // Three full-size vectors (f, r, d), not four: q = A d is never stored.
  // Each pass that needs a slice of A d recomputes it into a per-thread
  // slice buffer (ApplyOperatorSlice is deterministic, so both passes see the
  // same values and the iterates are bitwise those of the stored-q
  // formulation). The extra stencil application costs arithmetic, not
  // memory traffic: q is no longer written and read back (8 of ~44 bytes
  // per voxel and iteration), and the job's peak memory drops by one output
  // volume (docs/speed/whole-job-notes.md).
  std::vector<float> r(field.data.size()), d(field.data.size());
  tbb::enumerable_thread_specific<std::vector<float>> scratch(
      [plane] { return std::vector<float>(plane); });
  std::vector<double> partial(nz), partial2(nz);

  auto for_slices = [&](auto&& body) {
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, nz),
                      [&](const tbb::blocked_range<int64_t>& range) {
                        for (int64_t k = range.begin(); k != range.end(); ++k)
                          body(k);
                      });
  };

  // r = -P A f, d = r, from the field itself; returns {E(f), r.r}. Starts
  // CG, and restarts it when the recursive residual (which drifts from the
  // true one in float) claims the tolerance is met.
  auto reset_residual = [&]() -> std::pair<double, double> {
    for_slices([&](int64_t k) {
      float* qk = scratch.local().data();
      solver_internal::ApplyOperatorSlice(f, size, k, c, qk);
      const float* fk = f + k * plane;
      float* rk = r.data() + k * plane;
      float* dk = d.data() + k * plane;
      const double e = DotProduct(fk, qk, plane);
      double rr_k = 0;
      if (fixed[k]) {
        std::fill(rk, rk + plane, 0.0f);
        std::fill(dk, dk + plane, 0.0f);
      } else {
        for (int64_t n = 0; n < plane; ++n) {
          rk[n] = -qk[n];
          dk[n] = rk[n];
        }
        rr_k = DotProduct(rk, rk, plane);
      }
      partial[k] = e;
      partial2[k] = rr_k;
    });
    return {OrderedSum(partial), OrderedSum(partial2)};
  };
  auto [energy, rr] = reset_residual();
  const double rr0 = rr;
  // True relative residual at the last restart: restarts stop once they no
  // longer halve it (the float floor, see docs/DESIGN.md).
  double last_true_relative = 1.0;
  result.initial_energy = energy;
  result.initial_residual = std::sqrt(rr0);
  result.relative_residual = rr0 > 0 ? 1.0 : 0.0;
  result.energy = energy;
  if (rr0 == 0) {
    result.converged = true;
    return absl::OkStatus();
  }

  for (int it = 1; it <= options.max_iterations; ++it) {
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    // d . q with q = A d, slice by slice while the slice is in cache.
    for_slices([&](int64_t k) {
      if (fixed[k]) {
        partial[k] = 0;  // d is zero there, and q is not needed there.
        return;
      }
      float* qk = scratch.local().data();
      solver_internal::ApplyOperatorSlice(d.data(), size, k, c, qk);
      partial[k] = DotProduct(d.data() + k * plane, qk, plane);
    });
    const double dq = OrderedSum(partial);
    if (!(dq > 0)) break;  // d == 0 to working precision: nothing left to do.
    const double alpha = rr / dq;
    const float alpha_f = static_cast<float>(alpha);
    // r -= alpha q (q recomputed, as above); r . r.
    for_slices([&](int64_t k) {
      if (fixed[k]) {
        partial[k] = 0;
        return;
      }
      float* qk = scratch.local().data();
      solver_internal::ApplyOperatorSlice(d.data(), size, k, c, qk);
      partial[k] = UpdateResidual(r.data() + k * plane, qk, alpha_f, plane);
    });
    const double rr_next = OrderedSum(partial);
    // Along a CG step E drops by alpha r.r (d.r = r.r for CG directions).
    energy -= alpha * rr;
    const double beta = rr_next / rr;
    const float beta_f = static_cast<float>(beta);
    // f += alpha d (the old d); d = r + beta d.
    for_slices([&](int64_t k) {
      if (fixed[k]) return;
      UpdateSolutionAndDirection(f + k * plane, d.data() + k * plane,
                                 r.data() + k * plane, alpha_f, beta_f, plane);
    });
    rr = rr_next;
    result.iterations = it;
    result.relative_residual = std::sqrt(rr / rr0);
    result.energy = energy;
    context.Report(
        {.stage = "solve",
         .fraction = static_cast<double>(it) / options.max_iterations,
         .iteration = it,
         .relative_residual = result.relative_residual,
         .energy = energy});
    if (options.tolerance > 0 &&
        result.relative_residual <= options.tolerance) {
      // Check against the true residual before stopping; if it is above the
      // tolerance, restart CG from the current field (residual replacement).
      std::tie(energy, rr) = reset_residual();
      const double true_relative = std::sqrt(rr / rr0);
      result.relative_residual = true_relative;
      result.energy = energy;
      if (true_relative <= options.tolerance) {
        result.converged = true;
        break;
      }
      if (true_relative > 0.5 * last_true_relative) break;  // float floor
      last_true_relative = true_relative;
      continue;
    }
    if (rr == 0) {
      result.converged = true;
      break;
    }
  }
  // The recursive residual and energy drift in float; report measured ones.
  const FieldStatistics final_stats = MeasureField(f, size, fixed, c);
  result.energy = final_stats.energy;
  result.relative_residual =
      final_stats.residual_norm / result.initial_residual;
  if (options.tolerance > 0) {
    result.converged = result.relative_residual <= options.tolerance;
  }
  return absl::OkStatus();
}

absl::Status ValidateSolveInputs(const Volume<float>& field,
                                 const std::vector<uint8_t>& fixed,
                                 const SolverOptions& options) {
  INTERSLICE_RETURN_IF_ERROR(field.grid.Validate());
  if (static_cast<int64_t>(field.data.size()) != field.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "field data size does not match its grid");
  }
  if (static_cast<int64_t>(fixed.size()) != field.grid.size[2]) {
    return absl::InvalidArgumentError(
        absl::StrFormat("fixed-slice mask has %d entries for %d slices",
                        fixed.size(), field.grid.size[2]));
  }
  if (std::none_of(fixed.begin(), fixed.end(), [](uint8_t v) { return v; })) {
    return absl::InvalidArgumentError(
        "at least one original (fixed) slice is needed");
  }
  if (options.max_iterations < 0) {
    return absl::InvalidArgumentError("iterations must be >= 0");
  }
  if (!(options.tolerance >= 0) || !std::isfinite(options.tolerance)) {
    return absl::InvalidArgumentError("tolerance must be >= 0 and finite");
  }
  if (!(options.fidelity >= 0) || !std::isfinite(options.fidelity)) {
    return absl::InvalidArgumentError("fidelity must be >= 0 and finite");
  }
  if (options.fidelity > 0 && options.method != SolverMethod::kDirect &&
      options.method != SolverMethod::kMorph) {
    return absl::InvalidArgumentError(
        "a fidelity term needs the direct solver");
  }
  return absl::OkStatus();
}

// Per-slice fidelity weights (solver.h, SolverOptions::fidelity_taper).
std::vector<double> FidelityWeights(const std::vector<uint8_t>& fixed,
                                    double fidelity, bool taper) {
  const int64_t nz = static_cast<int64_t>(fixed.size());
  std::vector<double> w(nz, 0.0);
  int64_t previous = -1;
  for (int64_t k = 0; k < nz; ++k) {
    if (fixed[k]) {
      previous = k;
      continue;
    }
    int64_t next = k + 1;
    while (next < nz && !fixed[next]) ++next;
    if (!taper || previous < 0 || next >= nz) {
      w[k] = fidelity;
      continue;
    }
    const double t = 2.0 *
                     static_cast<double>(std::min(k - previous, next - k)) /
                     static_cast<double>(next - previous);
    w[k] = fidelity * t * t;
  }
  return w;
}

}  // namespace

absl::StatusOr<SolverResult> Solve(Volume<float>& field,
                                   const std::vector<uint8_t>& fixed_slices,
                                   const SolverOptions& options,
                                   const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateSolveInputs(field, fixed_slices, options));
  for (float v : field.data) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError("field holds a non-finite value");
    }
  }
  const StencilCoefficients c = StencilCoefficients::From(
      CurvatureWeights::For(options.units, field.grid.spacing));
  SolverResult result;
  result.method = options.method;
  absl::Status status;
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    switch (options.method) {
      case SolverMethod::kLinear: {
        const FieldStatistics s =
            MeasureField(field.data.data(), field.grid.size, fixed_slices, c);
        result.initial_energy = result.energy = s.energy;
        result.initial_residual = s.residual_norm;
        result.relative_residual = s.residual_norm > 0 ? 1.0 : 0.0;
        result.converged = s.residual_norm == 0;
        break;
      }
      case SolverMethod::kConjugateGradient:
        status =
            ConjugateGradient(field, fixed_slices, options, c, context, result);
        break;
      case SolverMethod::kDirect:
      case SolverMethod::kMorph: {
        std::vector<double> fidelity;
        if (options.fidelity > 0) {
          fidelity = FidelityWeights(fixed_slices, options.fidelity,
                                     options.fidelity_taper);
        }
        status = solver_internal::DirectSolve(
            field, fixed_slices,
            CurvatureWeights::For(options.units, field.grid.spacing), c,
            fidelity, context, result);
        break;
      }
    }
  });
  if (!status.ok()) return status;
  return result;
}

}  // namespace interslice
