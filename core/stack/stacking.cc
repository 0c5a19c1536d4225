#include "core/stack/stacking.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
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

namespace {

// The same tolerance as the DICOM reader's uniformity check.
constexpr double kSpacingAbsoluteTolerance = 0.01;  // mm
constexpr double kSpacingRelativeTolerance = 0.01;
// More output slices than this is a planning error, not a memory question
// (it would overflow the index arithmetic long before).
constexpr double kMaxOutputSlices = 1e9;

double Median(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  const size_t mid = values.size() / 2;
  return values.size() % 2 == 1 ? values[mid]
                                : 0.5 * (values[mid - 1] + values[mid]);
}

}  // namespace

StackPlan UniformStackPlan(int64_t slices, double slice_spacing_mm,
                           int factor) {
  StackPlan plan;
  plan.factor = factor;
  plan.spacing_mm = slice_spacing_mm / factor;
  plan.nodes.resize(std::max<int64_t>(slices, 1));
  for (size_t s = 0; s < plan.nodes.size(); ++s) {
    plan.nodes[s] = static_cast<int64_t>(s) * factor;
  }
  plan.output_slices = plan.nodes.back() + 1;
  plan.min_gap_mm = plan.max_gap_mm = plan.median_gap_mm = slice_spacing_mm;
  return plan;
}

absl::StatusOr<StackPlan> PlanStack(const std::vector<double>& positions_mm,
                                    double inplane_spacing_mm,
                                    const ZResolution& resolution,
                                    double single_slice_spacing_mm) {
  const size_t n = positions_mm.size();
  if (n == 0) return absl::InvalidArgumentError("no slices to stack");
  for (size_t s = 0; s < n; ++s) {
    if (!std::isfinite(positions_mm[s])) {
      return absl::InvalidArgumentError("slice positions must be finite");
    }
    if (s > 0 && !(positions_mm[s] > positions_mm[s - 1])) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "slice positions must increase strictly (slice %d at %g mm, slice "
          "%d at %g mm)",
          s - 1, positions_mm[s - 1], s, positions_mm[s]));
    }
  }
  if (n == 1) {
    INTERSLICE_ASSIGN_OR_RETURN(
        const int factor,
        ChooseInsertionFactor(single_slice_spacing_mm, inplane_spacing_mm,
                              resolution));
    return UniformStackPlan(1, single_slice_spacing_mm, factor);
  }
  std::vector<double> gaps(n - 1);
  for (size_t s = 0; s + 1 < n; ++s) {
    gaps[s] = positions_mm[s + 1] - positions_mm[s];
  }
  const double median = Median(gaps);
  INTERSLICE_ASSIGN_OR_RETURN(
      const int factor,
      ChooseInsertionFactor(median, inplane_spacing_mm, resolution));
  StackPlan plan = UniformStackPlan(static_cast<int64_t>(n), median, factor);
  plan.min_gap_mm = *std::min_element(gaps.begin(), gaps.end());
  plan.max_gap_mm = *std::max_element(gaps.begin(), gaps.end());
  const double tolerance =
      std::max(kSpacingAbsoluteTolerance, kSpacingRelativeTolerance * median);
  plan.uniform = plan.max_gap_mm - median <= tolerance &&
                 median - plan.min_gap_mm <= tolerance;

  const double h = plan.spacing_mm;
  if ((positions_mm.back() - positions_mm.front()) / h > kMaxOutputSlices) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "slices span %g mm; at %g mm output spacing that is more than %g "
        "output slices",
        positions_mm.back() - positions_mm.front(), h, kMaxOutputSlices));
  }
  // A uniform series keeps nodes s * N (today's factor-based grid, which
  // rounding reproduces anyway since every deviation is below h / 2).
  if (!plan.uniform) {
    for (size_t s = 1; s < n; ++s) {
      plan.nodes[s] = static_cast<int64_t>(
          std::llround((positions_mm[s] - positions_mm[0]) / h));
      if (plan.nodes[s] <= plan.nodes[s - 1]) {
        return absl::InvalidArgumentError(absl::StrFormat(
            "slices %d and %d (%.3f mm apart) land on the same output slice "
            "at %.4g mm spacing; ask for a smaller --spacing or a larger "
            "--factor",
            s - 1, s, positions_mm[s] - positions_mm[s - 1], h));
      }
    }
  }
  plan.output_slices = plan.nodes.back() + 1;
  for (size_t s = 0; s < n; ++s) {
    plan.max_snap_mm = std::max(
        plan.max_snap_mm,
        std::abs(positions_mm[s] - positions_mm[0] - plan.nodes[s] * h));
  }
  return plan;
}

absl::StatusOr<StackedField> StackLinear(const Volume<float>& slice_maps,
                                         const StackPlan& plan,
                                         int64_t max_voxels,
                                         const ComputeContext& context) {
  if (absl::Status s = slice_maps.grid.Validate(); !s.ok()) return s;
  if (static_cast<int64_t>(slice_maps.data.size()) !=
      slice_maps.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "slice maps: data size does not match grid");
  }
  const int64_t nz = slice_maps.grid.size[2];
  if (static_cast<int64_t>(plan.nodes.size()) != nz || plan.nodes[0] != 0 ||
      plan.output_slices != plan.nodes.back() + 1 || !(plan.spacing_mm > 0) ||
      !std::isfinite(plan.spacing_mm)) {
    return absl::InvalidArgumentError(
        absl::StrFormat("stack plan for %d slices does not match %d slice maps",
                        plan.nodes.size(), nz));
  }
  for (int64_t s = 1; s < nz; ++s) {
    if (plan.nodes[s] <= plan.nodes[s - 1]) {
      return absl::InvalidArgumentError(
          "stack plan: output nodes must increase strictly");
    }
  }
  const int64_t out_nz = plan.output_slices;
  const int64_t plane = slice_maps.grid.SliceVoxelCount();
  if (out_nz > max_voxels / plane) {
    return absl::ResourceExhaustedError(absl::StrFormat(
        "refined grid of %d x %d x %d voxels exceeds the limit of %d voxels",
        slice_maps.grid.size[0], slice_maps.grid.size[1], out_nz, max_voxels));
  }

  StackedField out;
  out.factor = plan.factor;
  out.field.grid = slice_maps.grid;
  out.field.grid.size[2] = out_nz;
  out.field.grid.spacing[2] = plan.spacing_mm;
  out.field.data.resize(out_nz * plane);
  out.fixed_slices.assign(out_nz, 0);
  for (int64_t s = 0; s < nz; ++s) out.fixed_slices[plan.nodes[s]] = 1;
  // interval[k]: the original slice at or below output slice k.
  std::vector<int64_t> interval(out_nz);
  for (int64_t s = 0; s < nz; ++s) {
    const int64_t end = s + 1 < nz ? plan.nodes[s + 1] : out_nz;
    for (int64_t k = plan.nodes[s]; k < end; ++k) interval[k] = s;
  }

  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<int64_t>(0, out_nz), [&](const auto& range) {
          for (int64_t k = range.begin(); k != range.end(); ++k) {
            const int64_t lower = interval[k];
            const int64_t offset = k - plan.nodes[lower];
            float* dst = out.field.data.data() + k * plane;
            const float* a = slice_maps.data.data() + lower * plane;
            if (offset == 0) {
              std::copy(a, a + plane, dst);
              continue;
            }
            const float* b = a + plane;
            // Computed as in the factor-only version so that a uniform
            // series gives bit-identical voxels.
            const float t = static_cast<float>(offset) /
                            (plan.nodes[lower + 1] - plan.nodes[lower]);
            for (int64_t n = 0; n < plane; ++n) {
              dst[n] = (1.0f - t) * a[n] + t * b[n];
            }
          }
        });
  });
  return out;
}

absl::StatusOr<StackedField> StackLinear(const Volume<float>& slice_maps,
                                         int factor, int64_t max_voxels,
                                         const ComputeContext& context) {
  if (factor < 1) {
    return absl::InvalidArgumentError("insertion factor must be >= 1");
  }
  if (absl::Status s = slice_maps.grid.Validate(); !s.ok()) return s;
  return StackLinear(slice_maps,
                     UniformStackPlan(slice_maps.grid.size[2],
                                      slice_maps.grid.spacing[2], factor),
                     max_voxels, context);
}

}  // namespace interslice
