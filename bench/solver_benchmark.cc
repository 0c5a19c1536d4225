// Solver kernels at the sizes the issues name: operator apply, one CG
// iteration and the direct solve, float fields.
#include <benchmark/benchmark.h>

#include <chrono>
#include <cmath>
#include <random>
#include <vector>

#include "core/solver/solver.h"

namespace interslice {
namespace {

// A smooth field (sum of a sphere's distance and a gentle wave) with every
// `factor`-th slice fixed and linear stacking between them.
struct Problem {
  Volume<float> field;
  std::vector<uint8_t> fixed;
};

Problem MakeProblem(int64_t n, int factor) {
  Problem p;
  p.field.grid.size = {n, n, n};
  p.field.data.resize(n * n * n);
  const double c = (n - 1) / 2.0;
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        const double r = std::sqrt((i - c) * (i - c) + (j - c) * (j - c) +
                                   (k - c) * (k - c));
        p.field.at(i, j, k) =
            static_cast<float>(0.35 * n - r + 2 * std::sin(0.2 * i));
      }
  p.fixed.assign(n, 0);
  for (int64_t k = 0; k < n; k += factor) p.fixed[k] = 1;
  p.fixed[n - 1] = 1;
  // Linear stacking between fixed slices.
  const int64_t plane = n * n;
  int64_t previous = 0;
  for (int64_t k = 1; k < n; ++k) {
    if (!p.fixed[k]) continue;
    for (int64_t m = previous + 1; m < k; ++m) {
      const float t = static_cast<float>(m - previous) / (k - previous);
      for (int64_t q = 0; q < plane; ++q) {
        p.field.data[m * plane + q] =
            (1 - t) * p.field.data[previous * plane + q] +
            t * p.field.data[k * plane + q];
      }
    }
    previous = k;
  }
  return p;
}

void BM_OperatorApply(benchmark::State& state) {
  const int64_t n = state.range(0);
  const Problem p = MakeProblem(n, 4);
  std::vector<float> out(p.field.data.size());
  for (auto _ : state) {
    ApplyCurvatureOperator(p.field.data.data(), out.data(), p.field.grid.size,
                           CurvatureWeights{});
    benchmark::DoNotOptimize(out.data());
  }
  const double voxels = static_cast<double>(n * n * n);
  state.counters["voxels_per_s"] =
      benchmark::Counter(voxels, benchmark::Counter::kIsIterationInvariantRate);
  // One float read and one float write per voxel at best.
  state.counters["bytes_per_s"] = benchmark::Counter(
      8 * voxels, benchmark::Counter::kIsIterationInvariantRate);
}
BENCHMARK(BM_OperatorApply)
    ->Arg(128)
    ->Arg(256)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

// One CG iteration: (time of setup + 10 iterations - time of setup) / 10,
// measured back to back on the same problem so setup cost cancels.
void BM_ConjugateGradientIteration(benchmark::State& state) {
  const int64_t n = state.range(0);
  const Problem p = MakeProblem(n, 4);
  constexpr int kIterations = 10;
  for (auto _ : state) {
    Volume<float> a = p.field, b = p.field;
    SolverOptions zero;
    zero.max_iterations = 0;
    SolverOptions ten;
    ten.max_iterations = kIterations;
    const auto t0 = std::chrono::steady_clock::now();
    benchmark::DoNotOptimize(Solve(a, p.fixed, zero, {}));
    const auto t1 = std::chrono::steady_clock::now();
    benchmark::DoNotOptimize(Solve(b, p.fixed, ten, {}));
    const auto t2 = std::chrono::steady_clock::now();
    const double per_iteration =
        (std::chrono::duration<double>(t2 - t1).count() -
         std::chrono::duration<double>(t1 - t0).count()) /
        kIterations;
    state.SetIterationTime(std::max(per_iteration, 1e-9));
  }
  state.counters["voxels"] = static_cast<double>(n * n * n);
}
BENCHMARK(BM_ConjugateGradientIteration)
    ->Arg(128)
    ->Arg(256)
    ->Unit(benchmark::kMillisecond)
    ->UseManualTime()
    ->Iterations(3);

void BM_DirectSolve(benchmark::State& state) {
  const int64_t n = state.range(0);
  const Problem p = MakeProblem(n, 4);
  SolverOptions options;
  options.method = SolverMethod::kDirect;
  double residual = 0;
  for (auto _ : state) {
    state.PauseTiming();
    Volume<float> field = p.field;
    state.ResumeTiming();
    const auto result = Solve(field, p.fixed, options, {});
    residual = result->relative_residual;
  }
  state.counters["relative_residual"] = residual;
}
BENCHMARK(BM_DirectSolve)
    ->Arg(128)
    ->Arg(256)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime()
    ->Iterations(3);

}  // namespace
}  // namespace interslice
