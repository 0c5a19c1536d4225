// Solver kernels at the sizes the issues name: operator apply, one CG
// iteration and the direct solve, float fields.
#include <benchmark/benchmark.h>

#include <chrono>
#include <cmath>
#include <random>
#include <vector>

#include "core/solver/solver.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/partitioner.h"

namespace interslice {
namespace {

// A smooth field (sum of a sphere's distance and a gentle wave) with every
// `factor`-th slice fixed and linear stacking between them.
struct Problem {
  Volume<float> field;
  std::vector<uint8_t> fixed;
};

// n x n x n voxels, except n = 512: 512 x 512 x 300 (a typical CT output).
Problem MakeProblem(int64_t n, int factor) {
  const int64_t nz = n == 512 ? 300 : n;
  Problem p;
  p.field.grid.size = {n, n, nz};
  p.field.data.resize(n * n * nz);
  const double c = (n - 1) / 2.0;
  for (int64_t k = 0; k < nz; ++k)
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < n; ++i) {
        const double r = std::sqrt((i - c) * (i - c) + (j - c) * (j - c) +
                                   (k - c) * (k - c));
        p.field.at(i, j, k) =
            static_cast<float>(0.35 * n - r + 2 * std::sin(0.2 * i));
      }
  p.fixed.assign(nz, 0);
  for (int64_t k = 0; k < nz; k += factor) p.fixed[k] = 1;
  p.fixed[nz - 1] = 1;
  // Linear stacking between fixed slices.
  const int64_t plane = n * n;
  int64_t previous = 0;
  for (int64_t k = 1; k < nz; ++k) {
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
  const double voxels = static_cast<double>(p.field.grid.VoxelCount());
  state.counters["voxels_per_s"] =
      benchmark::Counter(voxels, benchmark::Counter::kIsIterationInvariantRate);
  // One float read and one float write per voxel at best.
  state.counters["bytes_per_s"] = benchmark::Counter(
      8 * voxels, benchmark::Counter::kIsIterationInvariantRate);
}
BENCHMARK(BM_OperatorApply)
    ->Arg(128)
    ->Arg(256)
    ->Arg(512)
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
  state.counters["voxels"] = static_cast<double>(p.field.grid.VoxelCount());
}
BENCHMARK(BM_ConjugateGradientIteration)
    ->Arg(128)
    ->Arg(256)
    ->Arg(512)
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

// Direct solve vs CG run until it reaches the same true relative residual
// as the direct solve (and, separately, CG to 1e-6 or its float floor):
// seconds of each and their ratio, on one problem with every 8th slice fixed.
void BM_DirectVersusCgToSameResidual(benchmark::State& state) {
  const int64_t n = state.range(0);
  const Problem p = MakeProblem(n, 8);
  for (auto _ : state) {
    Volume<float> direct_field = p.field;
    SolverOptions direct;
    direct.method = SolverMethod::kDirect;
    const auto t0 = std::chrono::steady_clock::now();
    const auto direct_result = Solve(direct_field, p.fixed, direct, {});
    const auto t1 = std::chrono::steady_clock::now();

    Volume<float> cg_field = p.field;
    SolverOptions cg;
    cg.max_iterations = 20000;
    cg.tolerance = direct_result->relative_residual;
    const auto cg_result = Solve(cg_field, p.fixed, cg, {});
    const auto t2 = std::chrono::steady_clock::now();

    Volume<float> tight_field = p.field;
    SolverOptions tight;
    tight.max_iterations = 20000;
    tight.tolerance = 1e-6;
    const auto tight_result = Solve(tight_field, p.fixed, tight, {});
    const auto t3 = std::chrono::steady_clock::now();

    const double direct_s = std::chrono::duration<double>(t1 - t0).count();
    const double cg_s = std::chrono::duration<double>(t2 - t1).count();
    state.SetIterationTime(direct_s);
    state.counters["direct_s"] = direct_s;
    state.counters["direct_rel_residual"] = direct_result->relative_residual;
    state.counters["cg_same_residual_s"] = cg_s;
    state.counters["cg_same_residual_iters"] = cg_result->iterations;
    state.counters["cg_same_residual_reached"] = cg_result->relative_residual;
    state.counters["ratio_cg_over_direct"] = cg_s / direct_s;
    state.counters["cg_1e-6_s"] =
        std::chrono::duration<double>(t3 - t2).count();
    state.counters["cg_1e-6_iters"] = tight_result->iterations;
    state.counters["cg_1e-6_reached"] = tight_result->relative_residual;
  }
}
BENCHMARK(BM_DirectVersusCgToSameResidual)
    ->Arg(128)
    ->Arg(256)
    ->Unit(benchmark::kSecond)
    ->UseManualTime()
    ->Iterations(1);

// Scaling: a whole solve (15 CG iterations as in the paper, or the direct
// solver) from 64^3 up; n = 512 means 512 x 512 x 300. The paper's setting is
// 64^3 with 15 iterations (26 s on an SGI O2 in 2001).
void BM_SolveScaling(benchmark::State& state) {
  const int64_t n = state.range(0);
  const auto method = static_cast<SolverMethod>(state.range(1));
  const Problem p = MakeProblem(n, 4);
  SolverOptions options;
  options.method = method;
  options.max_iterations = 15;
  for (auto _ : state) {
    state.PauseTiming();
    Volume<float> field = p.field;
    state.ResumeTiming();
    benchmark::DoNotOptimize(Solve(field, p.fixed, options, {}));
  }
  state.counters["voxels"] = static_cast<double>(p.field.grid.VoxelCount());
  state.counters["ns_per_voxel"] =
      benchmark::Counter(static_cast<double>(p.field.grid.VoxelCount()),
                         benchmark::Counter::kIsIterationInvariantRate |
                             benchmark::Counter::kInvert);
  state.SetLabel(std::string(SolverMethodName(method)));
}
BENCHMARK(BM_SolveScaling)
    ->ArgsProduct({{64, 128, 256, 512, 768},
                   {static_cast<int>(SolverMethod::kConjugateGradient),
                    static_cast<int>(SolverMethod::kDirect)}})
    ->Unit(benchmark::kSecond)
    ->UseRealTime()
    ->Iterations(1);

}  // namespace
}  // namespace interslice

namespace interslice {
namespace {

// STREAM-style triad a = b + s * c on float arrays of 3 x 256 MiB, run on all
// cores like the solver: the memory-bandwidth limit the CG iteration is
// measured against (12 bytes per element moved; write-allocate not counted,
// as in STREAM).
void BM_StreamTriad(benchmark::State& state) {
  const int64_t n = int64_t{1} << 26;  // 64 Mi floats = 256 MiB per array
  std::vector<float> a(n), b(n, 1.0f), c(n, 2.0f);
  const float s = 3.0f;
  for (auto _ : state) {
    tbb::parallel_for(
        tbb::blocked_range<int64_t>(0, n, 1 << 16),
        [&](const tbb::blocked_range<int64_t>& r) {
          float* __restrict pa = a.data();
          const float* __restrict pb = b.data();
          const float* __restrict pc = c.data();
          for (int64_t i = r.begin(); i != r.end(); ++i) {
            pa[i] = pb[i] + s * pc[i];
          }
        },
        tbb::static_partitioner());
    benchmark::DoNotOptimize(a.data());
    benchmark::ClobberMemory();
  }
  state.counters["bytes_per_s"] = benchmark::Counter(
      12.0 * n, benchmark::Counter::kIsIterationInvariantRate);
}
BENCHMARK(BM_StreamTriad)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime()
    ->MinTime(1.0);

}  // namespace
}  // namespace interslice
