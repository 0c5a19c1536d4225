// Compression of a distance-field-like float volume (the .nii.gz / .nrrd
// writers' cost): independent gzip members (libdeflate level 1) vs one
// member (zlib Z_RLE runs joined by sync flushes), on 1 and all threads.
#include <benchmark/benchmark.h>
#include <fcntl.h>
#include <unistd.h>

#include <cmath>
#include <cstddef>
#include <filesystem>
#include <span>
#include <vector>

#include "core/volume_io/parallel_gzip.h"

namespace interslice::volume_io_internal {
namespace {

// Signed distance to a sphere on a 512x512x150 grid (0.45 mm): smooth, with
// float rounding noise in the low mantissa bits, like a solved field.
const std::vector<float>& Field() {
  static const std::vector<float> field = [] {
    const int nx = 512, ny = 512, nz = 150;
    std::vector<float> f(static_cast<size_t>(nx) * ny * nz);
    size_t n = 0;
    for (int z = 0; z < nz; ++z) {
      for (int y = 0; y < ny; ++y) {
        for (int x = 0; x < nx; ++x) {
          const double dx = 0.45 * (x - 256), dy = 0.45 * (y - 240),
                       dz = 0.45 * (z - 75);
          f[n++] =
              static_cast<float>(80.0 - std::sqrt(dx * dx + dy * dy + dz * dz) +
                                 0.01 * std::sin(0.7 * x + 0.3 * y));
        }
      }
    }
    return f;
  }();
  return field;
}

void BM_GzipFloatVolume(benchmark::State& state) {
  const std::vector<float>& field = Field();
  GzipOptions options;
  options.single_member = state.range(0) != 0;
  const ComputeContext context{.threads = static_cast<int>(state.range(1))};
  const auto path =
      std::filesystem::temp_directory_path() / "interslice_gzip_bench.gz";
  for (auto _ : state) {
    const int fd = open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    const absl::Status status = WriteParallelGzip(
        fd, {std::as_bytes(std::span(field))}, options, context);
    close(fd);
    if (!status.ok()) {
      state.SkipWithError(std::string(status.message()).c_str());
      return;
    }
  }
  const double raw = static_cast<double>(field.size() * sizeof(float));
  state.counters["ratio"] = std::filesystem::file_size(path) / raw;
  state.SetBytesProcessed(static_cast<int64_t>(state.iterations() * raw));
  state.SetLabel(options.single_member ? "single member (zlib RLE)"
                                       : "members (libdeflate 1)");
  std::filesystem::remove(path);
}
BENCHMARK(BM_GzipFloatVolume)
    ->ArgsProduct({{0, 1}, {1, 0}})
    ->Unit(benchmark::kSecond)
    ->UseRealTime()
    ->Iterations(1)
    ->Repetitions(3)
    ->ReportAggregatesOnly(true);

}  // namespace
}  // namespace interslice::volume_io_internal
