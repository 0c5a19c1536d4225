#include "core/stack/stacking.h"

#include <cmath>

#include "absl/strings/str_format.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {

absl::StatusOr<int> ChooseInsertionFactor(double slice_spacing_mm,
                                          double inplane_spacing_mm,
                                          const ZResolution& resolution) {
  if (resolution.factor.has_value() && resolution.spacing_mm.has_value()) {
    return absl::InvalidArgumentError(
        "give either an insertion factor or an output spacing, not both");
  }
  if (!(slice_spacing_mm > 0) || !std::isfinite(slice_spacing_mm)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "slice spacing is %g mm; it must be positive", slice_spacing_mm));
  }
  constexpr int kMaxFactor = 1024;
  if (resolution.factor.has_value()) {
    const int n = *resolution.factor;
    if (n < 1 || n > kMaxFactor) {
      return absl::InvalidArgumentError(
          absl::StrFormat("insertion factor is %d; it must be between 1 and %d",
                          n, kMaxFactor));
    }
    return n;
  }
  double target = inplane_spacing_mm;
  if (resolution.spacing_mm.has_value()) {
    target = *resolution.spacing_mm;
    if (!(target > 0) || !std::isfinite(target)) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "output spacing is %g mm; it must be positive", target));
    }
  } else if (!(target > 0) || !std::isfinite(target)) {
    return absl::InvalidArgumentError("in-plane spacing must be positive");
  }
  const double ratio = slice_spacing_mm / target;
  if (ratio > kMaxFactor) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "output spacing %g mm would insert more than %d slices per gap of "
        "%g mm",
        target, kMaxFactor, slice_spacing_mm));
  }
  return std::max(1, static_cast<int>(std::lround(ratio)));
}

absl::StatusOr<StackedField> StackLinear(const Volume<float>& slice_maps,
                                         int factor, int64_t max_voxels,
                                         const ComputeContext& context) {
  if (absl::Status s = slice_maps.grid.Validate(); !s.ok()) return s;
  if (static_cast<int64_t>(slice_maps.data.size()) !=
      slice_maps.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "slice maps: data size does not match grid");
  }
  if (factor < 1) {
    return absl::InvalidArgumentError("insertion factor must be >= 1");
  }
  const int64_t nz = slice_maps.grid.size[2];
  const int64_t out_nz = (nz - 1) * factor + 1;
  const int64_t plane = slice_maps.grid.SliceVoxelCount();
  if (out_nz > max_voxels / plane) {
    return absl::ResourceExhaustedError(absl::StrFormat(
        "refined grid of %d x %d x %d voxels exceeds the limit of %d voxels",
        slice_maps.grid.size[0], slice_maps.grid.size[1], out_nz, max_voxels));
  }

  StackedField out;
  out.factor = factor;
  out.field.grid = slice_maps.grid;
  out.field.grid.size[2] = out_nz;
  out.field.grid.spacing[2] = slice_maps.grid.spacing[2] / factor;
  out.field.data.resize(out_nz * plane);
  out.fixed_slices.assign(out_nz, 0);
  for (int64_t s = 0; s < nz; ++s) out.fixed_slices[s * factor] = 1;

  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<int64_t>(0, out_nz), [&](const auto& range) {
          for (int64_t k = range.begin(); k != range.end(); ++k) {
            const int64_t lower = k / factor;
            const int64_t offset = k % factor;
            float* dst = out.field.data.data() + k * plane;
            const float* a = slice_maps.data.data() + lower * plane;
            if (offset == 0) {
              std::copy(a, a + plane, dst);
              continue;
            }
            const float* b = a + plane;
            const float t = static_cast<float>(offset) / factor;
            for (int64_t n = 0; n < plane; ++n) {
              dst[n] = (1.0f - t) * a[n] + t * b[n];
            }
          }
        });
  });
  return out;
}

}  // namespace interslice
