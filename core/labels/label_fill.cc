#include "core/labels/label_fill.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <mutex>
#include <optional>
#include <set>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status_macros.h"
#include "core/labels/label_fill_internal.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {

namespace label_fill_internal {

double MedianGap(const std::vector<int64_t>& keys) {
  if (keys.size() < 2) return 1;
  std::vector<int64_t> gaps;
  for (size_t s = 1; s < keys.size(); ++s)
    gaps.push_back(keys[s] - keys[s - 1]);
  std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2, gaps.end());
  return static_cast<double>(gaps[gaps.size() / 2]);
}

}  // namespace label_fill_internal

namespace {

using label_fill_internal::MedianGap;

absl::Status ValidateLabels(const LabelVolume& labels) {
  INTERSLICE_RETURN_IF_ERROR(labels.grid.Validate());
  if (static_cast<int64_t>(labels.data.size()) != labels.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        absl::StrFormat("label map holds %d values but its grid has %d voxels",
                        labels.data.size(), labels.grid.VoxelCount()));
  }
  return absl::OkStatus();
}

bool SliceHasLabel(const LabelVolume& labels, int64_t k, int label) {
  const int64_t plane = labels.grid.SliceVoxelCount();
  const uint16_t* s = labels.data.data() + k * plane;
  return std::find(s, s + plane, static_cast<uint16_t>(label)) != s + plane;
}

}  // namespace

std::string_view FillMethodName(FillMethod method) {
  return method == FillMethod::kAuto ? "auto" : "solver";
}

absl::StatusOr<LabelVolume> LabelVolumeFromFloat(const Volume<float>& volume) {
  INTERSLICE_RETURN_IF_ERROR(volume.grid.Validate());
  if (static_cast<int64_t>(volume.data.size()) != volume.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "label map: data size does not match grid");
  }
  LabelVolume out;
  out.grid = volume.grid;
  out.data.resize(volume.data.size());
  for (size_t n = 0; n < volume.data.size(); ++n) {
    const float v = volume.data[n];
    if (!(v >= 0 && v <= 65535) || v != std::floor(v)) {
      const int64_t plane = volume.grid.SliceVoxelCount();
      const int64_t k = static_cast<int64_t>(n) / plane;
      const int64_t r = static_cast<int64_t>(n) % plane;
      return absl::InvalidArgumentError(absl::StrFormat(
          "label map: voxel (%d, %d, %d) holds %g; labels must be integers "
          "0..65535 (0 = background)",
          r % volume.grid.size[0], r / volume.grid.size[0], k, v));
    }
    out.data[n] = static_cast<uint16_t>(v);
  }
  return out;
}

absl::Status CheckSameGrid(const Grid& grid, const Grid& reference,
                           const std::string& what) {
  if (grid.size != reference.size) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s is %d x %d x %d voxels but the reference series is %d x %d x %d",
        what, grid.size[0], grid.size[1], grid.size[2], reference.size[0],
        reference.size[1], reference.size[2]));
  }
  static constexpr const char* kAxis[] = {"x", "y", "z"};
  for (int a = 0; a < 3; ++a) {
    if (std::abs(grid.spacing[a] - reference.spacing[a]) >
        1e-3 * reference.spacing[a]) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s has %s spacing %g mm but the reference series %g mm", what,
          kAxis[a], grid.spacing[a], reference.spacing[a]));
    }
  }
  const double min_spacing = std::min(
      {reference.spacing[0], reference.spacing[1], reference.spacing[2]});
  double origin_error = 0;
  for (int a = 0; a < 3; ++a) {
    origin_error =
        std::max(origin_error, std::abs(grid.origin[a] - reference.origin[a]));
  }
  if (origin_error > 0.01 + 0.01 * min_spacing) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s has origin (%.3f, %.3f, %.3f) mm (LPS) but the reference series "
        "(%.3f, %.3f, %.3f) mm",
        what, grid.origin[0], grid.origin[1], grid.origin[2],
        reference.origin[0], reference.origin[1], reference.origin[2]));
  }
  for (int e = 0; e < 9; ++e) {
    if (std::abs(grid.direction[e] - reference.direction[e]) > 1e-3) {
      return absl::InvalidArgumentError(
          absl::StrFormat("%s has direction [%s] but the reference series [%s]",
                          what, absl::StrJoin(grid.direction, ", "),
                          absl::StrJoin(reference.direction, ", ")));
    }
  }
  return absl::OkStatus();
}

std::vector<int> LabelsPresent(const LabelVolume& labels) {
  std::vector<uint8_t> seen(65536, 0);
  for (uint16_t v : labels.data) seen[v] = 1;
  std::vector<int> out;
  for (int v = 1; v < 65536; ++v) {
    if (seen[v]) out.push_back(v);
  }
  return out;
}

std::vector<int64_t> DrawnSlices(const LabelVolume& labels, int label) {
  std::vector<int64_t> out;
  for (int64_t k = 0; k < labels.grid.size[2]; ++k) {
    if (SliceHasLabel(labels, k, label)) out.push_back(k);
  }
  return out;
}

std::vector<int64_t> KeySlicesForLabel(
    const LabelVolume& labels, int label, const std::vector<int64_t>& annotated,
    const std::optional<std::vector<int64_t>>& explicit_keys) {
  std::vector<int64_t> drawn;
  if (explicit_keys.has_value()) {
    std::vector<int64_t> keys = *explicit_keys;
    std::sort(keys.begin(), keys.end());
    for (int64_t k : keys) {
      if (SliceHasLabel(labels, k, label)) drawn.push_back(k);
    }
    if (drawn.empty()) return {};
    // The explicit keys from the one before the first drawn slice to the one
    // after the last: every key slice inside counts (drawn or drawn-empty).
    auto first = std::lower_bound(keys.begin(), keys.end(), drawn.front());
    auto last = std::upper_bound(keys.begin(), keys.end(), drawn.back());
    if (first != keys.begin()) --first;
    if (last != keys.end()) ++last;
    return std::vector<int64_t>(first, last);
  }
  drawn = DrawnSlices(labels, label);
  if (drawn.empty()) return {};
  const int64_t nz = labels.grid.size[2];
  int64_t below = -1, above = -1;
  if (drawn.size() > 1) {
    // The label's own rhythm: the next slice it would have been drawn on.
    const auto gap = static_cast<int64_t>(MedianGap(drawn));
    if (drawn.front() - gap >= 0) below = drawn.front() - gap;
    if (drawn.back() + gap < nz) above = drawn.back() + gap;
  } else {
    // One drawn slice: the nearest slices where anything else was drawn.
    auto it =
        std::lower_bound(annotated.begin(), annotated.end(), drawn.front());
    if (it != annotated.begin()) below = *(it - 1);
    it = std::upper_bound(annotated.begin(), annotated.end(), drawn.back());
    if (it != annotated.end()) above = *it;
  }
  std::vector<int64_t> out;
  if (below >= 0) out.push_back(below);
  out.insert(out.end(), drawn.begin(), drawn.end());
  if (above >= 0) out.push_back(above);
  return out;
}

namespace {

using label_fill_internal::ComputeLabelField;
using label_fill_internal::kNoField;
using label_fill_internal::LabelJob;
using label_fill_internal::PlaneBox;

absl::Status ValidateFillOptions(const FillOptions& options) {
  if (options.margin_pixels < 1) {
    return absl::InvalidArgumentError("fill: margin_pixels must be >= 1");
  }
  if (options.solver.max_iterations < 0 || !(options.solver.tolerance >= 0)) {
    return absl::InvalidArgumentError(
        "fill: solver iterations and tolerance must be >= 0");
  }
  return absl::OkStatus();
}

// The labels to fill (FillOptions::labels, or every label present), sorted.
absl::StatusOr<std::vector<int>> LabelsToFill(const LabelVolume& input,
                                              const FillOptions& options) {
  const std::vector<int> present = LabelsPresent(input);
  if (present.empty()) {
    return absl::InvalidArgumentError(
        "the segmentation is empty: no voxel holds a label");
  }
  std::vector<int> labels = options.labels;
  if (labels.empty()) labels = present;
  std::sort(labels.begin(), labels.end());
  for (size_t n = 0; n < labels.size(); ++n) {
    if (labels[n] < 1 || labels[n] > 65535) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "label %d is out of range (labels are 1..65535)", labels[n]));
    }
    if (n > 0 && labels[n] == labels[n - 1]) {
      return absl::InvalidArgumentError(
          absl::StrFormat("label %d is listed twice", labels[n]));
    }
    if (!std::binary_search(present.begin(), present.end(), labels[n])) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "label %d is not drawn anywhere in the segmentation (present: %s)",
          labels[n], absl::StrJoin(present, ",")));
    }
  }
  return labels;
}

// FillOptions::key_slices, if given: not empty, inside the series' nz
// slices, no slice twice.
absl::Status ValidateExplicitKeySlices(
    const std::optional<std::vector<int64_t>>& key_slices, int64_t nz) {
  if (!key_slices.has_value()) return absl::OkStatus();
  std::vector<int64_t> keys = *key_slices;
  std::sort(keys.begin(), keys.end());
  if (keys.empty()) {
    return absl::InvalidArgumentError("the key slice list is empty");
  }
  for (size_t n = 0; n < keys.size(); ++n) {
    if (keys[n] < 0 || keys[n] >= nz) {
      return absl::InvalidArgumentError(
          absl::StrFormat("key slice %d is outside the series (slices 0..%d)",
                          keys[n], nz - 1));
    }
    if (n > 0 && keys[n] == keys[n - 1]) {
      return absl::InvalidArgumentError(
          absl::StrFormat("key slice %d is listed twice", keys[n]));
    }
  }
  return absl::OkStatus();
}

// The filled grid: the input's, with `factor` output slices per input gap
// (input slice k on output slice k * factor).
struct FillGrid {
  int factor = 1;
  Grid grid;
};

absl::StatusOr<FillGrid> ChooseFillGrid(const Grid& in_grid,
                                        const FillOptions& options) {
  const int64_t nx = in_grid.size[0], ny = in_grid.size[1],
                nz = in_grid.size[2];
  FillGrid out;
  if (options.z_resolution.factor.has_value() ||
      options.z_resolution.spacing_mm.has_value()) {
    INTERSLICE_ASSIGN_OR_RETURN(
        out.factor,
        ChooseInsertionFactor(in_grid.spacing[2],
                              std::min(in_grid.spacing[0], in_grid.spacing[1]),
                              options.z_resolution));
  }
  const int64_t out_nz = (nz - 1) * out.factor + 1;
  const int64_t plane = in_grid.SliceVoxelCount();
  if (out_nz > options.max_output_voxels / plane) {
    return absl::ResourceExhaustedError(absl::StrFormat(
        "the filled grid of %d x %d x %d voxels exceeds the limit of %d voxels",
        nx, ny, out_nz, options.max_output_voxels));
  }
  out.grid = in_grid;
  out.grid.size[2] = out_nz;
  out.grid.spacing[2] = in_grid.spacing[2] / out.factor;
  return out;
}

// The context's threads. Besides the labels themselves, the scans of the
// whole volume before and after them run on these threads, one slice, one
// label or one block of slices per task, each writing only its own
// results (integer counts and bounds per block, the same totals for any
// split): the same result for any thread count.
class FillThreads {
 public:
  explicit FillThreads(int threads) : threads_(threads), arena_(threads) {}

  int threads() const { return threads_; }
  tbb::task_arena& arena() { return arena_; }

  // body(t) for t in [0, count).
  template <typename Body>
  void ForEachIndex(int64_t count, const Body& body) {
    if (threads_ <= 1) {
      for (int64_t t = 0; t < count; ++t) body(t);
      return;
    }
    arena_.execute([&] {
      tbb::parallel_for(tbb::blocked_range<int64_t>(0, count, 1),
                        [&](const tbb::blocked_range<int64_t>& range) {
                          for (int64_t t = range.begin(); t != range.end();
                               ++t) {
                            body(t);
                          }
                        });
    });
  }
  // [0, count) in at most `threads` contiguous blocks: body(begin, end,
  // block). Per-block accumulators stay at threads x labels, not slices x
  // labels.
  int64_t BlocksOf(int64_t count) const {
    return std::max<int64_t>(1, std::min<int64_t>(count, threads_));
  }
  template <typename Body>
  void ForEachBlock(int64_t count, const Body& body) {
    const int64_t blocks = BlocksOf(count);
    ForEachIndex(blocks, [&](int64_t b) {
      body(b * count / blocks, (b + 1) * count / blocks, b);
    });
  }

 private:
  int threads_;
  tbb::task_arena arena_;
};

// The labels being filled, their key slices and lookups by label value.
struct FilledLabels {
  std::vector<int> labels;                                     // ascending
  std::vector<bool> filled = std::vector<bool>(65536, false);  // by value
  std::vector<int> index = std::vector<int>(65536, -1);        // n of labels[n]
  std::vector<std::vector<int64_t>> keys;  // keys[n]: of labels[n]
  // is_key[n][k]: slice k is a key slice of labels[n].
  std::vector<std::vector<bool>> is_key;
  // Every label's key slices together, sorted.
  std::vector<int64_t> annotated_keys;
};

// Key slices per label; the annotated slices are what the default rule
// sees as "drawn": every slice holding a filled label.
FilledLabels KeySlicesOfLabels(const LabelVolume& input,
                               std::vector<int> labels,
                               const FillOptions& options,
                               FillThreads& threads) {
  const int64_t nz = input.grid.size[2];
  const int64_t plane = input.grid.SliceVoxelCount();
  FilledLabels out;
  out.labels = std::move(labels);
  const std::vector<int>& ordered = out.labels;
  for (int l : ordered) out.filled[l] = true;
  std::vector<int64_t> annotated;
  if (!options.key_slices.has_value()) {
    std::vector<uint8_t> holds_filled(nz, 0);
    threads.ForEachIndex(nz, [&](int64_t k) {
      const uint16_t* s = input.data.data() + k * plane;
      holds_filled[k] =
          std::any_of(s, s + plane, [&](uint16_t v) { return out.filled[v]; });
    });
    for (int64_t k = 0; k < nz; ++k) {
      if (holds_filled[k]) annotated.push_back(k);
    }
  }
  out.keys.resize(ordered.size());
  threads.ForEachIndex(static_cast<int64_t>(ordered.size()), [&](int64_t n) {
    out.keys[n] =
        KeySlicesForLabel(input, ordered[n], annotated, options.key_slices);
  });
  std::set<int64_t> all_keys;
  for (size_t n = 0; n < ordered.size(); ++n) {
    all_keys.insert(out.keys[n].begin(), out.keys[n].end());
  }
  out.annotated_keys.assign(all_keys.begin(), all_keys.end());
  out.is_key.assign(ordered.size(), std::vector<bool>(nz, false));
  for (size_t n = 0; n < ordered.size(); ++n) {
    for (int64_t k : out.keys[n]) out.is_key[n][k] = true;
  }
  for (size_t n = 0; n < ordered.size(); ++n) out.index[ordered[n]] = n;
  return out;
}

// A merged label's box of the output grid, and its field for meshing.
struct Region {
  PlaneBox box;
  int64_t z0 = 0, z1 = 0;  // output slices [z0, z1)
  Volume<float> field;     // kept only for meshing
};

// The labels merged so far: running best and second-best field value and
// the best label (ties: the earlier, i.e. smaller, label keeps the voxel:
// labels run in ascending order and only a strictly larger value replaces
// the best).
struct MergedFields {
  std::vector<float> best;
  // The second best is needed only for the meshing fields.
  std::vector<float> second;
  bool track_second = false;
  std::vector<uint16_t> best_label;
  std::vector<Region> regions;  // per label
};

MergedFields NoLabelMerged(int64_t out_voxels, size_t labels,
                           bool keep_fields) {
  MergedFields merged;
  merged.best.assign(out_voxels, kNoField);
  merged.second.assign(keep_fields ? out_voxels : 0, kNoField);
  merged.track_second = keep_fields;
  merged.best_label.assign(out_voxels, 0);
  merged.regions.resize(labels);
  return merged;
}

// Merges label n into the running best / second best and keeps what the
// result needs; the field itself only for meshing.
void MergeLabel(size_t n, const Grid& out_grid, bool keep_fields,
                std::vector<LabelJob>& jobs, MergedFields& merged,
                FillResult& result) {
  LabelJob& job = jobs[n];
  result.warnings.insert(result.warnings.end(), job.warnings.begin(),
                         job.warnings.end());
  if (job.field.data.empty()) {
    result.per_label.push_back(std::move(job.info));
    return;
  }
  std::vector<float>& best = merged.best;
  std::vector<float>& second = merged.second;
  const bool track_second = merged.track_second;
  Region& region = merged.regions[n];
  region.box = job.box;
  region.z0 = job.z0;
  region.z1 = job.z1;
  const PlaneBox& box = job.box;
  const int64_t bw = box.i1 - box.i0, bh = box.j1 - box.j0;
  const int64_t bplane = bw * bh;
  const int label = job.label;
  const float* f = job.field.data.data();
  for (int64_t z = region.z0; z < region.z1; ++z) {
    for (int64_t j = 0; j < bh; ++j) {
      const int64_t dst = out_grid.LinearIndex(box.i0, box.j0 + j, z);
      const float* src = f + (z - region.z0) * bplane + j * bw;
      for (int64_t i = 0; i < bw; ++i) {
        const float v = src[i];
        if (v > best[dst + i]) {
          if (track_second) second[dst + i] = best[dst + i];
          best[dst + i] = v;
          merged.best_label[dst + i] = static_cast<uint16_t>(label);
        } else if (track_second && v > second[dst + i]) {
          second[dst + i] = v;
        }
      }
    }
  }
  if (keep_fields) {
    region.field = std::move(job.field);
    Grid& g = region.field.grid;
    g.spacing = out_grid.spacing;
    g.direction = out_grid.direction;
    g.origin = out_grid.IndexToPhysical({static_cast<double>(box.i0),
                                         static_cast<double>(box.j0),
                                         static_cast<double>(region.z0)});
  }
  job.field = Volume<float>();
  result.per_label.push_back(std::move(job.info));
}

// Estimated work per label: in-plane bounding box of the drawn pixels
// times the span of the key slices.
std::vector<int64_t> EstimateLabelWork(const LabelVolume& input,
                                       const FilledLabels& filled,
                                       FillThreads& threads) {
  const int64_t nx = input.grid.size[0], ny = input.grid.size[1],
                nz = input.grid.size[2];
  const size_t labels = filled.labels.size();
  std::vector<int64_t> work(labels, 0);
  // Per block of slices, then the union over the blocks.
  std::vector<std::vector<PlaneBox>> block_extent(threads.BlocksOf(nz));
  threads.ForEachBlock(nz, [&](int64_t k0, int64_t k1, int64_t block) {
    std::vector<PlaneBox>& extent = block_extent[block];
    extent.assign(labels, PlaneBox{nx, 0, ny, 0});
    for (int64_t k = k0; k < k1; ++k) {
      for (int64_t j = 0; j < ny; ++j) {
        const uint16_t* row = input.data.data() + (k * ny + j) * nx;
        for (int64_t i = 0; i < nx; ++i) {
          const int n = row[i] == 0 ? -1 : filled.index[row[i]];
          if (n < 0) continue;
          PlaneBox& e = extent[n];
          e.i0 = std::min(e.i0, i);
          e.i1 = std::max(e.i1, i + 1);
          e.j0 = std::min(e.j0, j);
          e.j1 = std::max(e.j1, j + 1);
        }
      }
    }
  });
  std::vector<PlaneBox> extent(labels, PlaneBox{nx, 0, ny, 0});
  for (const std::vector<PlaneBox>& block : block_extent) {
    for (size_t n = 0; n < labels; ++n) {
      const PlaneBox& s = block[n];
      PlaneBox& e = extent[n];
      e.i0 = std::min(e.i0, s.i0);
      e.i1 = std::max(e.i1, s.i1);
      e.j0 = std::min(e.j0, s.j0);
      e.j1 = std::max(e.j1, s.j1);
    }
  }
  const std::vector<std::vector<int64_t>>& keys = filled.keys;
  for (size_t n = 0; n < labels; ++n) {
    const PlaneBox& e = extent[n];
    if (keys[n].empty() || e.i1 <= e.i0) continue;
    work[n] =
        (e.i1 - e.i0) * (e.j1 - e.j0) * (keys[n].back() - keys[n].front() + 1);
  }
  return work;
}

// One label after the other on the context's threads, each merged when done.
absl::Status ComputeLabelsInOrder(const LabelVolume& input, const FillGrid& out,
                                  const FillOptions& options,
                                  const ComputeContext& context,
                                  std::vector<LabelJob>& jobs,
                                  MergedFields& merged, FillResult& result) {
  for (size_t n = 0; n < jobs.size(); ++n) {
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    INTERSLICE_RETURN_IF_ERROR(ComputeLabelField(input, out.grid, out.factor,
                                                 options, context, jobs[n]));
    MergeLabel(n, out.grid, options.keep_fields, jobs, merged, result);
  }
  return absl::OkStatus();
}

// The labels concurrently, each single-threaded, merged strictly in
// ascending label order as soon as every smaller label is done. Fields
// computed ahead of a smaller label wait in memory until it is merged.
absl::Status ComputeLabelsConcurrently(
    const LabelVolume& input, const FillGrid& out, const FillOptions& options,
    const ComputeContext& context, const FilledLabels& filled,
    FillThreads& threads, std::vector<LabelJob>& jobs, MergedFields& merged,
    FillResult& result) {
  const size_t labels = jobs.size();
  ComputeContext inner;
  inner.threads = 1;
  inner.cancel = context.cancel;
  std::mutex mu;
  std::vector<uint8_t> done(labels, 0);
  size_t next_merge = 0;
  absl::Status first_error;
  size_t error_label = labels;
  std::atomic<bool> stop{false};
  // Largest labels first (estimated work: in-plane bounding box of the
  // drawn pixels times the span of the key slices), so the longest job
  // does not start last; workers take the next label in that order.
  const std::vector<int64_t> work = EstimateLabelWork(input, filled, threads);
  std::vector<size_t> order(labels);
  for (size_t n = 0; n < order.size(); ++n) order[n] = n;
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return work[a] > work[b]; });
  std::atomic<size_t> next{0};
  threads.arena().execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<int>(0, threads.threads(), 1),
        [&](const tbb::blocked_range<int>& workers) {
          for (int w = workers.begin(); w != workers.end(); ++w) {
            for (size_t q = next.fetch_add(1); q < order.size();
                 q = next.fetch_add(1)) {
              const size_t n = order[q];
              if (stop.load(std::memory_order_relaxed)) return;
              absl::Status s = context.CheckCancelled();
              if (s.ok()) {
                s = ComputeLabelField(input, out.grid, out.factor, options,
                                      inner, jobs[n]);
              }
              std::lock_guard<std::mutex> lock(mu);
              if (!s.ok()) {
                if (n < error_label) {
                  error_label = n;
                  first_error = std::move(s);
                }
                stop.store(true, std::memory_order_relaxed);
                return;
              }
              done[n] = 1;
              while (next_merge < labels && done[next_merge]) {
                MergeLabel(next_merge, out.grid, options.keep_fields, jobs,
                           merged, result);
                ++next_merge;
              }
            }
          }
        },
        tbb::simple_partitioner());
  });
  if (!first_error.ok()) return first_error;
  if (next_merge != labels) {
    return absl::InternalError("fill: not every label was merged");
  }
  return absl::OkStatus();
}

// Per output slice strictly between two consecutive annotated key slices
// ka < kb (input indices): ka and kb; otherwise -1.
struct BracketingKeys {
  std::vector<int64_t> bracket, next_key;
};

BracketingKeys BracketsOfOutputSlices(
    const std::vector<int64_t>& annotated_keys, int factor, int64_t out_nz) {
  BracketingKeys b;
  b.bracket.assign(out_nz, -1);
  b.next_key.assign(out_nz, -1);
  for (size_t a = 0; a + 1 < annotated_keys.size(); ++a) {
    for (int64_t z = annotated_keys[a] * factor + 1;
         z < annotated_keys[a + 1] * factor; ++z) {
      b.bracket[z] = annotated_keys[a];
      b.next_key[z] = annotated_keys[a + 1];
    }
  }
  return b;
}

// What finishing a block of output slices counts.
struct FinishCounts {
  int64_t gap_closed = 0, restored = 0;
  std::vector<int64_t> per_label;
};

// Output slice z of `out`: the combined labels, gap closing and the key
// slices restored, counted into `c`.
void FinishSlice(int64_t z, const LabelVolume& input, int factor,
                 const FilledLabels& filled, const MergedFields& merged,
                 const BracketingKeys& brackets, LabelVolume& out,
                 FinishCounts& c) {
  const int64_t plane = input.grid.SliceVoxelCount();
  const std::vector<bool>& is_filled = filled.filled;
  const std::vector<int>& label_index = filled.index;
  const std::vector<std::vector<bool>>& is_key = filled.is_key;
  uint16_t* o = out.data.data() + z * plane;
  const float* b = merged.best.data() + z * plane;
  const uint16_t* bl = merged.best_label.data() + z * plane;
  // The largest positive field wins.
  for (int64_t p = 0; p < plane; ++p) {
    if (b[p] > 0) o[p] = bl[p];
  }
  // Gap closing between annotated slices labelled on both sides.
  if (brackets.bracket[z] >= 0) {
    const uint16_t* la = input.data.data() + brackets.bracket[z] * plane;
    const uint16_t* lb = input.data.data() + brackets.next_key[z] * plane;
    for (int64_t p = 0; p < plane; ++p) {
      if (o[p] != 0 || b[p] == kNoField) continue;
      if (la[p] != 0 && lb[p] != 0) {
        o[p] = bl[p];
        ++c.gap_closed;
      }
    }
  }
  // Key slices exactly as drawn.
  if (z % factor == 0) {
    const int64_t k = z / factor;
    const uint16_t* drawn = input.data.data() + k * plane;
    for (int64_t p = 0; p < plane; ++p) {
      const uint16_t in = drawn[p];
      uint16_t want = o[p];
      if (in != 0 && (!is_filled[in] || is_key[label_index[in]][k])) {
        want = in;
      } else if (o[p] != 0 && is_key[label_index[o[p]]][k]) {
        want = 0;  // drawn-and-empty for that label
      }
      if (want != o[p]) {
        o[p] = want;
        ++c.restored;
      }
    }
  }
  for (int64_t p = 0; p < plane; ++p) {
    if (o[p] != 0 && is_filled[o[p]]) ++c.per_label[label_index[o[p]]];
  }
}

// Combine, close gaps, restore key slices and count, one output slice at a
// time on the context's threads: every step reads and writes only its own
// slice (and the input), and the counts are integer sums, so the result
// does not depend on the thread count.
void FinishOutputSlices(const LabelVolume& input, const FillGrid& out,
                        const FilledLabels& filled, const MergedFields& merged,
                        FillThreads& threads, FillResult& result) {
  const int64_t out_nz = out.grid.size[2];
  const size_t labels = filled.labels.size();
  LabelVolume& labelled = result.labels;
  labelled.grid = out.grid;
  labelled.data.assign(out.grid.VoxelCount(), 0);
  const BracketingKeys brackets =
      BracketsOfOutputSlices(filled.annotated_keys, out.factor, out_nz);
  std::vector<FinishCounts> counts(threads.BlocksOf(out_nz));
  threads.ForEachBlock(out_nz, [&](int64_t z0, int64_t z1, int64_t block) {
    FinishCounts& c = counts[block];
    c.per_label.assign(labels, 0);
    for (int64_t z = z0; z < z1; ++z) {
      FinishSlice(z, input, out.factor, filled, merged, brackets, labelled, c);
    }
  });
  for (const FinishCounts& c : counts) {
    result.gap_voxels_closed += c.gap_closed;
    result.key_voxels_restored += c.restored;
    for (size_t n = 0; n < labels; ++n) {
      result.per_label[n].output_voxels += c.per_label[n];
    }
  }
}

// FillOptions::keep_fields: each label's field for meshing,
// min(f_L, (f_L - max_{M != L} f_M) / 2) (LabelFillInfo::field).
void KeepMeshingFields(const std::vector<int>& labels, const Grid& out_grid,
                       MergedFields& merged, FillResult& result) {
  for (size_t n = 0; n < labels.size(); ++n) {
    Region& region = merged.regions[n];
    if (region.field.data.empty()) continue;
    const PlaneBox& box = region.box;
    const int64_t bw = box.i1 - box.i0, bh = box.j1 - box.j0;
    float* f = region.field.data.data();
    for (int64_t z = region.z0; z < region.z1; ++z) {
      for (int64_t j = 0; j < bh; ++j) {
        const int64_t src = out_grid.LinearIndex(box.i0, box.j0 + j, z);
        float* row = f + ((z - region.z0) * bh + j) * bw;
        for (int64_t i = 0; i < bw; ++i) {
          const int64_t v = src + i;
          const float other = merged.best_label[v] == labels[n]
                                  ? merged.second[v]
                                  : merged.best[v];
          if (other != kNoField) {
            row[i] = std::min(row[i], 0.5f * (row[i] - other));
          }
        }
      }
    }
    result.per_label[n].field = std::move(region.field);
  }
}

}  // namespace

absl::StatusOr<FillResult> FillBetweenSlices(const LabelVolume& input,
                                             const FillOptions& options,
                                             const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateLabels(input));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  INTERSLICE_RETURN_IF_ERROR(ValidateFillOptions(options));
  INTERSLICE_ASSIGN_OR_RETURN(std::vector<int> labels,
                              LabelsToFill(input, options));
  INTERSLICE_RETURN_IF_ERROR(
      ValidateExplicitKeySlices(options.key_slices, input.grid.size[2]));
  INTERSLICE_ASSIGN_OR_RETURN(const FillGrid out,
                              ChooseFillGrid(input.grid, options));

  FillResult result;
  result.factor = out.factor;
  FillThreads threads(context.threads > 0
                          ? context.threads
                          : tbb::this_task_arena::max_concurrency());
  const FilledLabels filled =
      KeySlicesOfLabels(input, std::move(labels), options, threads);
  const size_t label_count = filled.labels.size();

  MergedFields merged =
      NoLabelMerged(out.grid.VoxelCount(), label_count, options.keep_fields);
  std::vector<LabelJob> jobs(label_count);
  for (size_t n = 0; n < label_count; ++n) {
    jobs[n].label = filled.labels[n];
    jobs[n].key = filled.keys[n];
  }
  // Labels run concurrently, each single-threaded, and are merged strictly
  // in ascending label order as soon as every smaller label is done: the
  // same result for any thread count.
  if (threads.threads() <= 1 || label_count <= 1) {
    INTERSLICE_RETURN_IF_ERROR(ComputeLabelsInOrder(
        input, out, options, context, jobs, merged, result));
  } else {
    INTERSLICE_RETURN_IF_ERROR(ComputeLabelsConcurrently(
        input, out, options, context, filled, threads, jobs, merged, result));
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  FinishOutputSlices(input, out, filled, merged, threads, result);
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  if (options.keep_fields) {
    KeepMeshingFields(filled.labels, out.grid, merged, result);
  }
  return result;
}

}  // namespace interslice
