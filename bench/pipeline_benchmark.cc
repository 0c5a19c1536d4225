// End to end: the shipped thick CT phantom (28 slices of 5 mm) -> isotropic
// 0.45 mm grid, at 300 HU, per method; per-stage seconds as counters.
#include <benchmark/benchmark.h>

#include <filesystem>
#include <string>

#include "bench/bench_paths.h"
#include "core/pipeline/pipeline.h"

namespace interslice {
namespace {

void BM_EndToEndPhantom(benchmark::State& state) {
  const std::string series =
      std::string(BenchSourceDir()) + "/data/ct-head-phantom-thick";
  if (!std::filesystem::exists(series)) {
    state.SkipWithError("data/ct-head-phantom-thick is absent");
    return;
  }
  const auto out = std::filesystem::temp_directory_path() / "interslice_bench";
  JobSpec spec;
  spec.inputs = {series};
  spec.lower_threshold = 300;
  spec.solver.method = static_cast<SolverMethod>(state.range(0));
  spec.output_dir = out.string();
  spec.volume_formats = {"nii"};
  spec.mesh_formats = {"stl"};
  JobReport last;
  for (auto _ : state) {
    auto report = RunJob(spec, {});
    if (!report.ok()) {
      state.SkipWithError(std::string(report.status().message()).c_str());
      return;
    }
    last = *report;
  }
  for (const StageTiming& s : last.stages)
    state.counters[s.stage + "_s"] = s.seconds;
  state.counters["peak_rss_MiB"] = PeakRssBytes() / 1048576.0;
  state.counters["voxels"] = static_cast<double>(last.output_grid.VoxelCount());
  state.SetLabel(std::string(SolverMethodName(spec.solver.method)));
  std::filesystem::remove_all(out);
}
BENCHMARK(BM_EndToEndPhantom)
    ->Arg(static_cast<int>(SolverMethod::kLinear))
    ->Arg(static_cast<int>(SolverMethod::kConjugateGradient))
    ->Arg(static_cast<int>(SolverMethod::kDirect))
    ->Unit(benchmark::kSecond)
    ->UseRealTime()
    ->Iterations(1);

}  // namespace
}  // namespace interslice
