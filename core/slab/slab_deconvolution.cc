#include "core/slab/slab_deconvolution.h"

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_format.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

// Row s of A = P U: the slab average around slice s of the linear
// interpolation of the slice values, as weights on slices.
using Row = std::vector<std::pair<int64_t, double>>;

std::vector<Row> SlabRows(int64_t slices, int factor, double spacing_mm,
                          double thickness_mm) {
  const int64_t fine = (slices - 1) * factor + 1;
  const double h = spacing_mm / factor;        // fine sample spacing, mm
  const double half = 0.5 * thickness_mm / h;  // box half-width, fine units
  std::vector<Row> rows(slices);
  for (int64_t s = 0; s < slices; ++s) {
    const double centre = static_cast<double>(s * factor);
    std::vector<double> weight(slices, 0.0);
    double total = 0;
    const int64_t k0 = std::max<int64_t>(0, std::floor(centre - half - 0.5));
    const int64_t k1 =
        std::min<int64_t>(fine - 1, std::ceil(centre + half + 0.5));
    for (int64_t k = k0; k <= k1; ++k) {
      // Length of fine cell [k - 1/2, k + 1/2] inside the box.
      const double overlap =
          std::min(k + 0.5, centre + half) - std::max(k - 0.5, centre - half);
      if (overlap <= 0) continue;
      total += overlap;
      const int64_t q = std::min<int64_t>(k / factor, slices - 1);
      const double f =
          q == slices - 1 ? 0.0 : static_cast<double>(k - q * factor) / factor;
      weight[q] += overlap * (1 - f);
      if (f > 0) weight[q + 1] += overlap * f;
    }
    for (int64_t q = 0; q < slices; ++q)
      if (weight[q] != 0) rows[s].emplace_back(q, weight[q] / total);
  }
  return rows;
}

}  // namespace

absl::StatusOr<SlabDeconvolution> DeconvolveSlabs(
    const Volume<float>& slices, const SlabDeconvolutionOptions& options,
    const ComputeContext& context) {
  const Index3 n = slices.grid.size;
  if (n[0] < 1 || n[1] < 1 || n[2] < 1 ||
      static_cast<int64_t>(slices.data.size()) != slices.grid.VoxelCount())
    return absl::InvalidArgumentError("slab deconvolution: empty stack");
  const double dz = slices.grid.spacing[2];
  if (!(options.slab_thickness_mm > 0) ||
      !std::isfinite(options.slab_thickness_mm))
    return absl::InvalidArgumentError(
        "slab deconvolution: slab thickness must be > 0 mm");
  if (options.factor < 1)
    return absl::InvalidArgumentError(
        "slab deconvolution: factor must be >= 1");
  if (!(options.tolerance > 0) || !std::isfinite(options.tolerance))
    return absl::InvalidArgumentError(
        "slab deconvolution: tolerance must be > 0");
  if (options.max_iterations < 0)
    return absl::InvalidArgumentError(
        "slab deconvolution: max_iterations must be >= 0");
  if (n[2] > 1 && (!(dz > 0) || !std::isfinite(dz)))
    return absl::InvalidArgumentError(
        "slab deconvolution: slice spacing must be > 0");
  if (n[2] > 1 && options.slab_thickness_mm > 2 * dz + 1e-9)
    return absl::InvalidArgumentError(absl::StrFormat(
        "slab deconvolution: slab thickness %g mm is more than two slice "
        "gaps (%g mm)",
        options.slab_thickness_mm, dz));
  SlabDeconvolution out;
  out.slices = slices;
  if (n[2] == 1 || options.max_iterations == 0) return out;

  const std::vector<Row> rows =
      SlabRows(n[2], options.factor, dz, options.slab_thickness_mm);
  const int64_t plane = n[0] * n[1];
  const int64_t nz = n[2];
  const float* input = slices.data.data();
  float* c = out.slices.data.data();
  std::vector<float> residual(slices.data.size());
  // Per-chunk sums of squares in a fixed partition: thread-count independent.
  constexpr int64_t kChunk = 4096;
  const int64_t chunks = (plane + kChunk - 1) / kChunk;
  std::vector<double> chunk_sq(chunks);
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  // R = S - A C for every pixel; returns RMS(R).
  auto compute_residual = [&]() {
    arena.execute([&] {
      tbb::parallel_for(int64_t{0}, chunks, [&](int64_t b) {
        const int64_t v0 = b * kChunk, v1 = std::min(plane, v0 + kChunk);
        double sq = 0;
        for (int64_t s = 0; s < nz; ++s)
          for (int64_t v = v0; v < v1; ++v) {
            double ac = 0;
            for (const auto& [q, w] : rows[s]) ac += w * c[q * plane + v];
            const double r = input[s * plane + v] - ac;
            residual[s * plane + v] = static_cast<float>(r);
            sq += r * r;
          }
        chunk_sq[b] = sq;
      });
    });
    double sq = 0;
    for (double x : chunk_sq) sq += x;
    return std::sqrt(sq / static_cast<double>(plane * nz));
  };
  out.initial_rms = compute_residual();
  out.final_rms = out.initial_rms;
  while (out.iterations < options.max_iterations &&
         out.final_rms >= options.tolerance) {
    if (absl::Status s = context.CheckCancelled(); !s.ok()) return s;
    for (size_t i = 0; i < residual.size(); ++i) c[i] += residual[i];
    ++out.iterations;
    out.final_rms = compute_residual();
  }
  return out;
}

}  // namespace interslice
