#include "core/labels/label_fill.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <mutex>
#include <numeric>
#include <set>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "core/common/status_macros.h"
#include "core/morph/morph.h"
#include "core/sdf/signed_distance.h"
#include "tbb/blocked_range.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

constexpr float kNoField = -std::numeric_limits<float>::infinity();

// Half-open in-plane box of a label on the input grid.
struct PlaneBox {
  int64_t i0 = 0, i1 = 0, j0 = 0, j1 = 0;
};

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

// The median of the gaps between consecutive key slices, in slices (>= 1).
double MedianGap(const std::vector<int64_t>& keys) {
  if (keys.size() < 2) return 1;
  std::vector<int64_t> gaps;
  for (size_t s = 1; s < keys.size(); ++s)
    gaps.push_back(keys[s] - keys[s - 1]);
  std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2, gaps.end());
  return static_cast<double>(gaps[gaps.size() / 2]);
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

// One label's work: its inputs, and its field on its box of the output grid
// (output slices [z0, z1)) once computed.
struct LabelJob {
  int label = 0;
  std::vector<int64_t> key;  // key slices (input indices)
  LabelFillInfo info;
  std::vector<std::string> warnings;
  PlaneBox box;
  int64_t z0 = 0, z1 = 0;
  Volume<float> field;  // empty when the label is left out
};

// The 2D signed distance maps of `label` on its key slices `key`, in the
// in-plane box `box` (one map per key slice, in order): the label's 0/1
// mask at the 0.5 level (core/sdf). The z spacing of the stack (used only by
// the end caps of core/sdf) is the median key gap.
absl::StatusOr<Volume<float>> KeySliceDistanceMaps(
    const LabelVolume& input, int label, const std::vector<int64_t>& key,
    const PlaneBox& box, const FillOptions& options,
    const ComputeContext& context) {
  const Grid& in_grid = input.grid;
  const int64_t bw = box.i1 - box.i0, bh = box.j1 - box.j0;
  const int64_t bplane = bw * bh;
  Volume<float> mask;
  mask.grid.size = {bw, bh, static_cast<int64_t>(key.size())};
  mask.grid.spacing = {in_grid.spacing[0], in_grid.spacing[1],
                       in_grid.spacing[2] * MedianGap(key)};
  mask.data.assign(mask.grid.VoxelCount(), 0.0f);
  for (size_t s = 0; s < key.size(); ++s) {
    for (int64_t j = 0; j < bh; ++j) {
      const uint16_t* row =
          input.data.data() + in_grid.LinearIndex(box.i0, box.j0 + j, key[s]);
      float* dst = mask.data.data() + s * bplane + j * bw;
      for (int64_t i = 0; i < bw; ++i) dst[i] = row[i] == label ? 1.0f : 0.0f;
    }
  }
  ContourOptions contour;
  contour.lower = 0.5f;
  contour.band_radius_mm = options.band_radius_mm;
  INTERSLICE_ASSIGN_OR_RETURN(Volume<float> maps,
                              ComputeSliceDistanceMaps(mask, contour, context));
  mask = Volume<float>();
  // [seg-io hook] Key slices drawn as polygons (RTSTRUCT): the exact
  // distance to the polygons replaces the raster's within the band.
  if (options.contours != nullptr) {
    INTERSLICE_RETURN_IF_ERROR(OverlayPolygonDistances(
        *options.contours, label, key, box.i0, box.j0,
        EffectiveBandRadius(contour, in_grid.spacing[0], in_grid.spacing[1]),
        maps, context));
  }
  return maps;
}

// Candidates of FillMethod::kAuto, in tie-break order.
enum class Candidate { kLinear, kRefined, kMorph, kBlend, kCopy };
constexpr Candidate kCandidates[] = {Candidate::kLinear, Candidate::kRefined,
                                     Candidate::kMorph, Candidate::kBlend,
                                     Candidate::kCopy};
constexpr int kCandidateCount = 5;
// Below this pooled Dice of every candidate at the doubled gap the
// validation says nothing (see ComputeLabelField).
constexpr double kUninformativeDice = 0.1;

const char* CandidateName(Candidate c) {
  switch (c) {
    case Candidate::kLinear:
      return "linear";
    case Candidate::kRefined:
      return "direct";
    case Candidate::kMorph:
      return "morph";
    case Candidate::kBlend:
      return "blend";
    case Candidate::kCopy:
      return "copy";
  }
  return "?";
}

// The nearest-slice copy of a stacked field: every free slice takes the
// map of its nearest fixed slice (ties: the lower one), so `copy` > 0 is
// exactly the drawn pixels of that key slice. `stacked` holds the maps on
// its fixed slices.
void NearestFixedCopy(const Volume<float>& stacked,
                      const std::vector<uint8_t>& fixed, Volume<float>& copy) {
  copy = stacked;
  const int64_t nz = stacked.grid.size[2];
  const int64_t plane = stacked.grid.SliceVoxelCount();
  int64_t below = -1;
  for (int64_t z = 0; z < nz; ++z) {
    if (fixed[z]) {
      below = z;
      continue;
    }
    int64_t above = z + 1;
    while (above < nz && !fixed[above]) ++above;
    int64_t from = below;
    if (below < 0 || (above < nz && above - z < z - below)) from = above;
    if (from < 0 || from >= nz) continue;
    std::copy(stacked.data.begin() + from * plane,
              stacked.data.begin() + (from + 1) * plane,
              copy.data.begin() + z * plane);
  }
}

// The morph's options for a label's box. MorphOptions' defaults register
// whole 512 x 512 slices at a quarter of their resolution (128 pixels) in 4
// levels; a label's box is often a few dozen pixels, where a quarter would
// leave the registration too few pixels to follow the label, and where the
// pyramid's coarse levels have nothing left to register while each demons
// iteration costs ~0.3 ms of ITK overhead whatever the size (about 20 ms a
// registration in 4 levels of 25 iterations on a 24 x 24 box, 7 ms in one).
// So: downsampled only while the shorter side keeps >= 32 pixels, and as
// many levels as keep >= 8 pixels on the coarsest along the longer side (1
// to 4).
MorphOptions LabelMorphOptions(int64_t box_width, int64_t box_height) {
  MorphOptions morph;
  const int64_t shorter = std::min(box_width, box_height);
  morph.downsample =
      static_cast<int>(std::clamp<int64_t>(shorter / 32, 1, morph.downsample));
  // Levels by the longer side: a structure moving along a narrow box moves
  // along its long side (core/morph still keeps >= 4 pixels on the shorter).
  const int64_t registered = std::max(box_width, box_height) / morph.downsample;
  int levels = 1;
  while (levels < morph.levels && (registered >> levels) >= 8) ++levels;
  morph.levels = levels;
  return morph;
}

// The morph of a label's key-slice maps onto `plan` (StackMorph, then its
// component filter: no component of the label where no key slice has one).
absl::StatusOr<StackedField> MorphLabel(const Volume<float>& maps,
                                        const StackPlan& plan,
                                        int64_t max_voxels,
                                        const ComputeContext& context) {
  INTERSLICE_ASSIGN_OR_RETURN(
      MorphedField morphed,
      StackMorph(maps, plan,
                 LabelMorphOptions(maps.grid.size[0], maps.grid.size[1]),
                 max_voxels, context));
  INTERSLICE_RETURN_IF_ERROR(
      RemoveUnsupportedComponents(morphed.stacked.field,
                                  morphed.stacked.fixed_slices,
                                  MorphOptions().component_margin_mm, context)
          .status());
  return std::move(morphed.stacked);
}

// Validation of the candidates for one label at `m` times its key gap: in
// m folds r = 0 .. m-1, the key slices s with s mod m = r (and the first and
// last) are kept, the other inner ones held out; each candidate fills the
// held-out slices from the kept ones (on the grid of the key slices) and is
// compared with the drawn mask there. m = 2 holds out every other key slice
// (each one once, predicted across a gap twice the label's own); m = 4
// keeps every 4th (each inner key slice held out 3 times, at 1/4, 1/2 and
// 3/4 of a gap 4 times the label's own, as drop-k withholds slices). At most
// kMaxHeldOutPerLevel held-out slices are scored, in a few runs spread over
// the folds (see below); the morph of each is the fill's own morph from the
// fold's kept key slices (the cubic trajectory through its gap, whose
// tangents come from the kept gaps on either side). Returns the Dice
// pooled over the scored slices per candidate (kCandidates order; the
// morph's -1 without auto_morph), or empty when the label has fewer than
// m + 2 key slices (m = 2: 3). With `slice_dice`, also each scored slice's
// own Dice per candidate (kCandidates order; 1 where neither the drawing nor
// the candidate has a pixel; the morph's -1 without auto_morph), for the
// evaluation of selection rules (LabelFillInfo::validation_slice_dice).
absl::StatusOr<std::vector<double>> ValidateCandidates(
    const LabelVolume& input, int label, const std::vector<int64_t>& key,
    const PlaneBox& box, const Volume<float>& maps, const FillOptions& options,
    int m, const ComputeContext& context,
    std::vector<std::vector<double>>* slice_dice = nullptr) {
  const size_t n = key.size();
  const size_t needed = m == 2 ? 3 : static_cast<size_t>(m) + 2;
  if (n < needed) return std::vector<double>();
  const int64_t bw = box.i1 - box.i0, bh = box.j1 - box.j0;
  const int64_t bplane = bw * bh;
  // The validation grid holds only the slices at multiples of g, the
  // greatest common divisor of the key gaps (every key slice is one of
  // them): g times fewer voxels for the solver than the input grid. For
  // the refinement to approximate the same continuous energy as on the
  // input grid, its weights are those of a z step g times the input's
  // (CurvatureWeights in mm units with the z spacing scaled). Linear
  // stacking, the copy and the morph (t measured in output slices) are the
  // same on either grid.
  int64_t g = 0;
  for (size_t s = 1; s < n; ++s) g = std::gcd(g, key[s] - key[s - 1]);
  g = std::max<int64_t>(1, g);
  const bool with_morph = options.auto_morph;
  // The held-out slices (fold, key index) of all folds, and the sample of
  // at most kMaxHeldOutPerLevel of them that is scored. Each registration
  // costs ~10 ms of ITK overhead whatever the box, and the morph of a
  // scored slice needs its own kept gap and the kept gaps on either side
  // registered (see below), so the sample is made of a few runs spread
  // evenly over the folds, each run the held-out slices of consecutive kept
  // gaps of one fold (at least kRunSlices slices): neighbouring slices of a
  // run share their registrations. m = 2: 4 runs of 2 slices (one per gap),
  // 4 registrations a run; m = 4: 3 runs of one gap's 3 slices, 3 a run.
  constexpr size_t kMaxHeldOutPerLevel = 8;
  constexpr size_t kRunSlices = 2;
  // Units: the held-out slices of one kept gap of one fold, in fold order.
  struct HeldGap {
    int fold = 0;
    std::vector<size_t> slices;
  };
  std::vector<HeldGap> held_gaps;
  size_t all_held = 0;
  for (int fold = 0; fold < m; ++fold) {
    bool new_gap = true;
    for (size_t s = 1; s + 1 < n; ++s) {
      if (static_cast<int>(s % m) == fold) {
        new_gap = true;  // a kept key slice ends the gap
        continue;
      }
      ++all_held;
      if (new_gap) held_gaps.push_back({fold, {}});
      held_gaps.back().slices.push_back(s);
      new_gap = false;
    }
  }
  std::vector<std::vector<size_t>> held_of(m);
  if (all_held <= kMaxHeldOutPerLevel) {
    for (const HeldGap& gap : held_gaps) {
      held_of[gap.fold].insert(held_of[gap.fold].end(), gap.slices.begin(),
                               gap.slices.end());
    }
  } else {
    const size_t per_gap = (all_held + held_gaps.size() - 1) / held_gaps.size();
    const size_t per_run = std::max(kRunSlices, per_gap);
    const size_t runs = (kMaxHeldOutPerLevel + per_run - 1) / per_run;
    std::vector<bool> taken(held_gaps.size(), false);
    size_t scored = 0;
    for (size_t r = 0; r < runs && scored < kMaxHeldOutPerLevel; ++r) {
      size_t u = (2 * r + 1) * held_gaps.size() / (2 * runs);
      size_t in_run = 0;
      while (u < held_gaps.size() && !taken[u] && in_run < kRunSlices &&
             scored < kMaxHeldOutPerLevel) {
        taken[u] = true;
        for (size_t s : held_gaps[u].slices) {
          if (scored == kMaxHeldOutPerLevel) break;
          held_of[held_gaps[u].fold].push_back(s);
          ++scored;
          ++in_run;
        }
        if (u + 1 == held_gaps.size() ||
            held_gaps[u + 1].fold != held_gaps[u].fold) {
          break;
        }
        ++u;
      }
    }
    for (std::vector<size_t>& fold_slices : held_of) {
      std::sort(fold_slices.begin(), fold_slices.end());
    }
  }
  std::vector<double> both(kCandidateCount, 0), predicted(kCandidateCount, 0);
  double drawn = 0;
  for (int fold = 0; fold < m; ++fold) {
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    const std::vector<size_t>& held = held_of[fold];
    if (held.empty()) continue;
    std::vector<size_t> kept;
    for (size_t s = 0; s < n; ++s) {
      if (s == 0 || s + 1 == n || static_cast<int>(s % m) == fold) {
        kept.push_back(s);
      }
    }
    Volume<float> sub;
    sub.grid = maps.grid;
    sub.grid.size[2] = static_cast<int64_t>(kept.size());
    sub.data.resize(sub.grid.VoxelCount());
    StackPlan plan;
    plan.factor = 1;
    plan.spacing_mm = input.grid.spacing[2];
    for (size_t c = 0; c < kept.size(); ++c) {
      std::copy(maps.data.begin() + kept[c] * bplane,
                maps.data.begin() + (kept[c] + 1) * bplane,
                sub.data.begin() + c * bplane);
      plan.nodes.push_back((key[kept[c]] - key.front()) / g);
    }
    plan.output_slices = plan.nodes.back() + 1;
    INTERSLICE_ASSIGN_OR_RETURN(
        StackedField linear,
        StackLinear(sub, plan, options.max_output_voxels, context));
    sub = Volume<float>();
    // The morph of each scored slice as the fill computes it: on the cubic
    // trajectory through the kept key slices, whose gap around the slice
    // takes its Catmull-Rom tangents from the kept gaps on either side. So
    // the gaps each scored slice needs (its own and its neighbours) are
    // registered, each once: every run of consecutive needed gaps is morphed
    // as one stack, which gives a scored slice what the whole fold's morph
    // would.
    std::vector<std::vector<float>> morph(held.size());
    if (with_morph) {
      const size_t kept_gaps = kept.size() - 1;
      std::vector<size_t> gap_of(held.size());
      std::vector<bool> needed(kept_gaps, false);
      for (size_t h = 0; h < held.size(); ++h) {
        const size_t gap = static_cast<size_t>(
            std::upper_bound(kept.begin(), kept.end(), held[h]) - kept.begin() -
            1);
        gap_of[h] = gap;
        for (size_t n = gap == 0 ? 0 : gap - 1;
             n <= std::min(kept_gaps - 1, gap + 1); ++n) {
          needed[n] = true;
        }
      }
      for (size_t first = 0; first < kept_gaps;) {
        if (!needed[first]) {
          ++first;
          continue;
        }
        size_t last = first;  // the run's gaps: first .. last
        while (last + 1 < kept_gaps && needed[last + 1]) ++last;
        const size_t count = last - first + 2;  // its kept key slices
        Volume<float> run;
        run.grid = maps.grid;
        run.grid.size[2] = static_cast<int64_t>(count);
        run.data.resize(count * bplane);
        StackPlan run_plan;
        run_plan.factor = 1;
        run_plan.spacing_mm = input.grid.spacing[2];
        for (size_t c = 0; c < count; ++c) {
          const size_t ks = kept[first + c];
          std::copy(maps.data.begin() + ks * bplane,
                    maps.data.begin() + (ks + 1) * bplane,
                    run.data.begin() + c * bplane);
          run_plan.nodes.push_back((key[ks] - key[kept[first]]) / g);
        }
        run_plan.output_slices = run_plan.nodes.back() + 1;
        INTERSLICE_ASSIGN_OR_RETURN(
            StackedField morphed,
            MorphLabel(run, run_plan, options.max_output_voxels, context));
        for (size_t h = 0; h < held.size(); ++h) {
          if (gap_of[h] < first || gap_of[h] > last) continue;
          const int64_t z = (key[held[h]] - key[kept[first]]) / g;
          morph[h].assign(morphed.field.data.begin() + z * bplane,
                          morphed.field.data.begin() + (z + 1) * bplane);
        }
        first = last + 1;
      }
    }
    Volume<float> refined = linear.field;
    SolverOptions solver = options.solver;
    solver.method = SolverMethod::kDirect;
    if (solver.units == EnergyUnits::kVoxel) {
      refined.grid.spacing = {1, 1, static_cast<double>(g)};
    } else {
      refined.grid.spacing = {input.grid.spacing[0], input.grid.spacing[1],
                              input.grid.spacing[2] * g};
    }
    solver.units = EnergyUnits::kMillimetre;
    INTERSLICE_RETURN_IF_ERROR(
        Solve(refined, linear.fixed_slices, solver, context).status());
    Volume<float> copy;
    NearestFixedCopy(linear.field, linear.fixed_slices, copy);

    // Pooled Dice: 2 |A and B| / (|A| + |B|) summed over the held-out
    // slices of every fold.
    for (size_t h = 0; h < held.size(); ++h) {
      const size_t s = held[h];
      const int64_t z = (key[s] - key.front()) / g;
      const float* lin = linear.field.data.data() + z * bplane;
      const float* ref = refined.data.data() + z * bplane;
      const float* cpy = copy.data.data() + z * bplane;
      const float* mor = with_morph ? morph[h].data() : nullptr;
      std::vector<double> slice_both(kCandidateCount, 0),
          slice_predicted(kCandidateCount, 0);
      double slice_drawn = 0;
      for (int64_t j = 0; j < bh; ++j) {
        const uint16_t* row =
            input.data.data() +
            input.grid.LinearIndex(box.i0, box.j0 + j, key[s]);
        for (int64_t i = 0; i < bw; ++i) {
          const int64_t p = j * bw + i;
          const bool truth = row[i] == label;
          slice_drawn += truth;
          const float values[kCandidateCount] = {
              lin[p], ref[p], mor != nullptr ? mor[p] : -1.0f,
              0.5f * (lin[p] + cpy[p]), cpy[p]};
          for (int c = 0; c < kCandidateCount; ++c) {
            const bool in = values[c] > 0;
            slice_predicted[c] += in;
            slice_both[c] += in && truth;
          }
        }
      }
      drawn += slice_drawn;
      std::vector<double> one(kCandidateCount, 0);
      for (int c = 0; c < kCandidateCount; ++c) {
        predicted[c] += slice_predicted[c];
        both[c] += slice_both[c];
        const double sum = slice_predicted[c] + slice_drawn;
        one[c] = sum > 0 ? 2 * slice_both[c] / sum : 1;
      }
      if (!with_morph) one[static_cast<int>(Candidate::kMorph)] = -1;
      if (slice_dice != nullptr) slice_dice->push_back(std::move(one));
    }
  }
  std::vector<double> dice(kCandidateCount, 0);
  for (int c = 0; c < kCandidateCount; ++c) {
    const double sum = predicted[c] + drawn;
    dice[c] = sum > 0 ? 2 * both[c] / sum : 1;
  }
  if (!with_morph) dice[static_cast<int>(Candidate::kMorph)] = -1;
  return dice;
}

// Computes `job`'s field (see FillMethod) on its box of the output grid.
absl::Status ComputeLabelField(const LabelVolume& input, const Grid& out_grid,
                               int factor, const FillOptions& options,
                               const ComputeContext& context, LabelJob& job) {
  const Grid& in_grid = input.grid;
  const int64_t nx = in_grid.size[0], ny = in_grid.size[1];
  const int64_t plane = in_grid.SliceVoxelCount();
  const int label = job.label;
  LabelFillInfo& info = job.info;
  info.label = label;
  info.key_slices = job.key;
  const std::vector<int64_t>& key = job.key;
  if (key.empty()) {
    job.warnings.push_back(absl::StrFormat(
        "label %d is not drawn on any key slice: left out", label));
    return absl::OkStatus();
  }
  // The box: drawn pixels on the key slices, grown by the margin.
  PlaneBox box{nx, 0, ny, 0};
  std::vector<bool> drawn_on(key.size(), false);
  for (size_t s = 0; s < key.size(); ++s) {
    const uint16_t* slice = input.data.data() + key[s] * plane;
    for (int64_t j = 0; j < ny; ++j) {
      const uint16_t* row = slice + nx * j;
      for (int64_t i = 0; i < nx; ++i) {
        if (row[i] != label) continue;
        drawn_on[s] = true;
        box.i0 = std::min(box.i0, i);
        box.i1 = std::max(box.i1, i + 1);
        box.j0 = std::min(box.j0, j);
        box.j1 = std::max(box.j1, j + 1);
      }
    }
    if (drawn_on[s]) ++info.drawn_slices;
  }
  if (info.drawn_slices == 1) {
    const int64_t k = key[std::find(drawn_on.begin(), drawn_on.end(), true) -
                          drawn_on.begin()];
    job.warnings.push_back(absl::StrFormat(
        "label %d is drawn on slice %d only: kept as drawn%s", label, k,
        key.size() > 1 ? ", closing off toward the neighbouring key slices"
                       : ""));
  }
  const int64_t m = options.margin_pixels;
  box.i0 = std::max<int64_t>(0, box.i0 - m);
  box.j0 = std::max<int64_t>(0, box.j0 - m);
  box.i1 = std::min(nx, box.i1 + m);
  box.j1 = std::min(ny, box.j1 + m);

  INTERSLICE_ASSIGN_OR_RETURN(
      Volume<float> maps,
      KeySliceDistanceMaps(input, label, key, box, options, context));

  // Which candidate (FillMethod::kAuto) or the solver's method.
  SolverMethod refine = options.solver.method;
  Candidate chosen = Candidate::kRefined;
  if (options.method == FillMethod::kAuto && info.drawn_slices <= 2) {
    // Too few drawn key slices for a validation that says anything: the
    // held-out slice would be predicted from a drawn-and-empty end. Measured
    // on the real series of docs/eval/segmentations.md (labels drawn on one
    // key slice: copy Dice .50 against <= .30 for any interpolation; on two:
    // the morph or the refinement best, copy and linear behind).
    chosen = info.drawn_slices <= 1 ? Candidate::kCopy
             : options.auto_morph   ? Candidate::kMorph
                                    : Candidate::kRefined;
    refine = chosen == Candidate::kRefined ? SolverMethod::kDirect
                                           : SolverMethod::kLinear;
  } else if (options.method == FillMethod::kAuto) {
    std::vector<std::vector<double>> slices2, slices4;
    INTERSLICE_ASSIGN_OR_RETURN(
        std::vector<double> dice2,
        ValidateCandidates(input, label, key, box, maps, options, 2, context,
                           &slices2));
    std::vector<double> dice4;
    if (options.selection == AutoSelection::kGapTrend && !dice2.empty()) {
      INTERSLICE_ASSIGN_OR_RETURN(
          dice4, ValidateCandidates(input, label, key, box, maps, options, 4,
                                    context, &slices4));
    }
    chosen = Candidate::kLinear;
    if (!dice2.empty()) {
      // The score that predicts the Dice at the label's own gap g: at the
      // doubled gap, or (kGapTrend, when the label has enough key slices)
      // extrapolated from the quadrupled and the doubled gap by a power law
      // of the error e = 1 - Dice in the gap, e(g) = e(2g) 2^-p with
      // e(4g) = e(2g) 2^p, p clamped to [0, 2]: halving the gap never makes
      // a candidate worse, nor better than an interpolation error of second
      // order (a smooth surface between key slices) would.
      std::vector<double> score = dice2;
      if (!dice4.empty()) {
        for (int c = 0; c < kCandidateCount; ++c) {
          if (dice2[c] < 0) continue;
          const double e2 = 1 - dice2[c], e4 = 1 - dice4[c];
          const double p =
              e2 <= 0 || e4 <= e2 ? 0.0 : std::min(2.0, std::log2(e4 / e2));
          score[c] = 1 - e2 * std::exp2(-p);
        }
      }
      double best_score = -1e300, best_dice2 = 0;
      for (int c = 0; c < kCandidateCount; ++c) {
        if (dice2[c] < 0) continue;  // not a candidate (auto_morph off)
        best_dice2 = std::max(best_dice2, dice2[c]);
        if (score[c] > best_score) {
          best_score = score[c];
          chosen = kCandidates[c];
        }
      }
      // No candidate predicts anything at the doubled gap (a thin or small
      // structure that moves more than its size over two key gaps: nothing
      // overlaps): the validation cannot rank them. As for a label drawn on
      // two key slices, the morph, which follows the motion (measured on the
      // ribs of the TotalSegmentator series, docs/eval/segmentations.md:
      // morph Dice .54-.83 where linear stacking gave .11-.35), else the
      // copy.
      if (best_dice2 < kUninformativeDice) {
        chosen = options.auto_morph ? Candidate::kMorph : Candidate::kCopy;
      }
      static constexpr Candidate kReport[] = {
          Candidate::kCopy, Candidate::kLinear, Candidate::kBlend,
          Candidate::kRefined, Candidate::kMorph};
      for (Candidate c : kReport) {
        const int index = static_cast<int>(c);
        info.validation_dice.emplace_back(CandidateName(c), dice2[index]);
        if (!dice4.empty()) {
          info.validation_dice_4g.emplace_back(CandidateName(c), dice4[index]);
        }
        info.validation_score.emplace_back(CandidateName(c), score[index]);
      }
      // Each scored slice's Dice, in the report's candidate order.
      for (const auto& [level, all] :
           {std::pair{&info.validation_slice_dice, &slices2},
            std::pair{&info.validation_slice_dice_4g, &slices4}}) {
        for (const std::vector<double>& one : *all) {
          std::vector<double> ordered;
          for (Candidate c : kReport) {
            ordered.push_back(one[static_cast<int>(c)]);
          }
          level->push_back(std::move(ordered));
        }
      }
    }
    refine = chosen == Candidate::kRefined ? SolverMethod::kDirect
                                           : SolverMethod::kLinear;
  }
  // (A label on one key slice has no gap to register: stacked as linear.)
  const bool morph =
      key.size() >= 2 && (options.method == FillMethod::kAuto
                              ? chosen == Candidate::kMorph
                              : options.solver.method == SolverMethod::kMorph);

  StackPlan plan;
  plan.factor = factor;
  plan.spacing_mm = out_grid.spacing[2];
  for (int64_t k : key) plan.nodes.push_back((k - key.front()) * factor);
  plan.output_slices = plan.nodes.back() + 1;
  StackedField stacked;
  if (morph) {
    INTERSLICE_ASSIGN_OR_RETURN(
        stacked, MorphLabel(maps, plan, options.max_output_voxels, context));
  } else {
    INTERSLICE_ASSIGN_OR_RETURN(
        stacked, StackLinear(maps, plan, options.max_output_voxels, context));
  }
  maps = Volume<float>();
  const bool any_free =
      std::any_of(stacked.fixed_slices.begin(), stacked.fixed_slices.end(),
                  [](uint8_t f) { return f == 0; });
  if (morph) {
    info.solver.method = SolverMethod::kMorph;
    info.solver.relative_residual = 1;
  } else if (refine != SolverMethod::kLinear && any_free) {
    SolverOptions solver = options.solver;
    solver.method = refine;
    INTERSLICE_ASSIGN_OR_RETURN(
        info.solver,
        Solve(stacked.field, stacked.fixed_slices, solver, context));
  } else {
    info.solver.method = SolverMethod::kLinear;
    info.solver.relative_residual = 1;
  }
  if (options.method == FillMethod::kAuto) {
    info.method = CandidateName(chosen);
    if (chosen == Candidate::kCopy || chosen == Candidate::kBlend) {
      Volume<float> copy;
      NearestFixedCopy(stacked.field, stacked.fixed_slices, copy);
      if (chosen == Candidate::kBlend) {
        for (size_t v = 0; v < copy.data.size(); ++v) {
          copy.data[v] = 0.5f * (copy.data[v] + stacked.field.data[v]);
        }
      }
      stacked.field.data = std::move(copy.data);
    }
  } else {
    info.method = std::string(SolverMethodName(options.solver.method));
  }
  job.box = box;
  job.z0 = key.front() * factor;
  job.z1 = job.z0 + plan.output_slices;
  job.field = std::move(stacked.field);
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<FillResult> FillBetweenSlices(const LabelVolume& input,
                                             const FillOptions& options,
                                             const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateLabels(input));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  const Grid& in_grid = input.grid;
  const int64_t nx = in_grid.size[0], ny = in_grid.size[1],
                nz = in_grid.size[2];
  if (options.margin_pixels < 1) {
    return absl::InvalidArgumentError("fill: margin_pixels must be >= 1");
  }
  if (options.solver.max_iterations < 0 || !(options.solver.tolerance >= 0)) {
    return absl::InvalidArgumentError(
        "fill: solver iterations and tolerance must be >= 0");
  }

  // Which labels.
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
  std::vector<bool> filled(65536, false);
  for (int l : labels) filled[l] = true;

  if (options.key_slices.has_value()) {
    std::vector<int64_t> keys = *options.key_slices;
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
  }

  // Output grid.
  int factor = 1;
  if (options.z_resolution.factor.has_value() ||
      options.z_resolution.spacing_mm.has_value()) {
    INTERSLICE_ASSIGN_OR_RETURN(
        factor,
        ChooseInsertionFactor(in_grid.spacing[2],
                              std::min(in_grid.spacing[0], in_grid.spacing[1]),
                              options.z_resolution));
  }
  const int64_t out_nz = (nz - 1) * factor + 1;
  const int64_t plane = in_grid.SliceVoxelCount();
  if (out_nz > options.max_output_voxels / plane) {
    return absl::ResourceExhaustedError(absl::StrFormat(
        "the filled grid of %d x %d x %d voxels exceeds the limit of %d voxels",
        nx, ny, out_nz, options.max_output_voxels));
  }
  Grid out_grid = in_grid;
  out_grid.size[2] = out_nz;
  out_grid.spacing[2] = in_grid.spacing[2] / factor;

  FillResult result;
  result.factor = factor;

  // The context's threads. Besides the labels themselves, the scans of the
  // whole volume before and after them run on these threads, one slice, one
  // label or one block of slices per task, each writing only its own
  // results (integer counts and bounds per block, the same totals for any
  // split): the same result for any thread count.
  const int threads = context.threads > 0
                          ? context.threads
                          : tbb::this_task_arena::max_concurrency();
  tbb::task_arena arena(threads);
  auto for_each_index = [&](int64_t count, const auto& body) {
    if (threads <= 1) {
      for (int64_t t = 0; t < count; ++t) body(t);
      return;
    }
    arena.execute([&] {
      tbb::parallel_for(tbb::blocked_range<int64_t>(0, count, 1),
                        [&](const tbb::blocked_range<int64_t>& range) {
                          for (int64_t t = range.begin(); t != range.end();
                               ++t) {
                            body(t);
                          }
                        });
    });
  };
  // [0, count) in at most `threads` contiguous blocks: body(begin, end,
  // block). Per-block accumulators stay at threads x labels, not slices x
  // labels.
  const auto blocks_of = [&](int64_t count) {
    return std::max<int64_t>(1, std::min<int64_t>(count, threads));
  };
  auto for_each_block = [&](int64_t count, const auto& body) {
    const int64_t blocks = blocks_of(count);
    for_each_index(blocks, [&](int64_t b) {
      body(b * count / blocks, (b + 1) * count / blocks, b);
    });
  };

  // Key slices per label; the annotated slices are what the default rule
  // sees as "drawn": every slice holding a filled label.
  std::vector<int64_t> annotated;
  if (!options.key_slices.has_value()) {
    std::vector<uint8_t> holds_filled(nz, 0);
    for_each_index(nz, [&](int64_t k) {
      const uint16_t* s = input.data.data() + k * plane;
      holds_filled[k] =
          std::any_of(s, s + plane, [&](uint16_t v) { return filled[v]; });
    });
    for (int64_t k = 0; k < nz; ++k) {
      if (holds_filled[k]) annotated.push_back(k);
    }
  }
  std::vector<std::vector<int64_t>> keys(labels.size());
  for_each_index(static_cast<int64_t>(labels.size()), [&](int64_t n) {
    keys[n] =
        KeySlicesForLabel(input, labels[n], annotated, options.key_slices);
  });
  std::set<int64_t> all_keys;
  for (size_t n = 0; n < labels.size(); ++n) {
    all_keys.insert(keys[n].begin(), keys[n].end());
  }
  // is_key[n][k]: slice k is a key slice of labels[n].
  std::vector<std::vector<bool>> is_key(labels.size(),
                                        std::vector<bool>(nz, false));
  for (size_t n = 0; n < labels.size(); ++n) {
    for (int64_t k : keys[n]) is_key[n][k] = true;
  }
  std::vector<int> label_index(65536, -1);
  for (size_t n = 0; n < labels.size(); ++n) label_index[labels[n]] = n;

  // Running best and second-best field value and the best label (ties: the
  // earlier, i.e. smaller, label keeps the voxel: labels run in ascending
  // order and only a strictly larger value replaces the best).
  const int64_t out_voxels = out_grid.VoxelCount();
  // The second best is needed only for the meshing fields.
  std::vector<float> best(out_voxels, kNoField);
  std::vector<float> second(options.keep_fields ? out_voxels : 0, kNoField);
  const bool track_second = options.keep_fields;
  std::vector<uint16_t> best_label(out_voxels, 0);

  struct Region {
    PlaneBox box;
    int64_t z0 = 0, z1 = 0;  // output slices [z0, z1)
    Volume<float> field;     // kept only for meshing
  };
  std::vector<Region> regions(labels.size());
  std::vector<LabelJob> jobs(labels.size());
  for (size_t n = 0; n < labels.size(); ++n) {
    jobs[n].label = labels[n];
    jobs[n].key = keys[n];
  }
  // Merges label n into the running best / second best and keeps what the
  // result needs; the field itself only for meshing.
  auto merge = [&](size_t n) {
    LabelJob& job = jobs[n];
    result.warnings.insert(result.warnings.end(), job.warnings.begin(),
                           job.warnings.end());
    if (job.field.data.empty()) {
      result.per_label.push_back(std::move(job.info));
      return;
    }
    Region& region = regions[n];
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
            best_label[dst + i] = static_cast<uint16_t>(label);
          } else if (track_second && v > second[dst + i]) {
            second[dst + i] = v;
          }
        }
      }
    }
    if (options.keep_fields) {
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
  };

  // Labels run concurrently, each single-threaded, and are merged strictly
  // in ascending label order as soon as every smaller label is done: the
  // same result for any thread count. Fields computed ahead of a smaller
  // label wait in memory until it is merged.
  if (threads <= 1 || labels.size() <= 1) {
    for (size_t n = 0; n < labels.size(); ++n) {
      INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
      INTERSLICE_RETURN_IF_ERROR(ComputeLabelField(input, out_grid, factor,
                                                   options, context, jobs[n]));
      merge(n);
    }
  } else {
    ComputeContext inner;
    inner.threads = 1;
    inner.cancel = context.cancel;
    std::mutex mu;
    std::vector<uint8_t> done(labels.size(), 0);
    size_t next_merge = 0;
    absl::Status first_error;
    size_t error_label = labels.size();
    std::atomic<bool> stop{false};
    // Largest labels first (estimated work: in-plane bounding box of the
    // drawn pixels times the span of the key slices), so the longest job
    // does not start last; workers take the next label in that order.
    std::vector<int64_t> work(labels.size(), 0);
    {
      // Per block of slices, then the union over the blocks.
      std::vector<std::vector<PlaneBox>> block_extent(blocks_of(nz));
      for_each_block(nz, [&](int64_t k0, int64_t k1, int64_t block) {
        std::vector<PlaneBox>& extent = block_extent[block];
        extent.assign(labels.size(), PlaneBox{nx, 0, ny, 0});
        for (int64_t k = k0; k < k1; ++k) {
          for (int64_t j = 0; j < ny; ++j) {
            const uint16_t* row = input.data.data() + (k * ny + j) * nx;
            for (int64_t i = 0; i < nx; ++i) {
              const int n = row[i] == 0 ? -1 : label_index[row[i]];
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
      std::vector<PlaneBox> extent(labels.size(), PlaneBox{nx, 0, ny, 0});
      for (const std::vector<PlaneBox>& block : block_extent) {
        for (size_t n = 0; n < labels.size(); ++n) {
          const PlaneBox& s = block[n];
          PlaneBox& e = extent[n];
          e.i0 = std::min(e.i0, s.i0);
          e.i1 = std::max(e.i1, s.i1);
          e.j0 = std::min(e.j0, s.j0);
          e.j1 = std::max(e.j1, s.j1);
        }
      }
      for (size_t n = 0; n < labels.size(); ++n) {
        const PlaneBox& e = extent[n];
        if (keys[n].empty() || e.i1 <= e.i0) continue;
        work[n] = (e.i1 - e.i0) * (e.j1 - e.j0) *
                  (keys[n].back() - keys[n].front() + 1);
      }
    }
    std::vector<size_t> order(labels.size());
    for (size_t n = 0; n < order.size(); ++n) order[n] = n;
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return work[a] > work[b]; });
    std::atomic<size_t> next{0};
    arena.execute([&] {
      tbb::parallel_for(
          tbb::blocked_range<int>(0, threads, 1),
          [&](const tbb::blocked_range<int>& workers) {
            for (int w = workers.begin(); w != workers.end(); ++w) {
              for (size_t q = next.fetch_add(1); q < order.size();
                   q = next.fetch_add(1)) {
                const size_t n = order[q];
                if (stop.load(std::memory_order_relaxed)) return;
                absl::Status s = context.CheckCancelled();
                if (s.ok()) {
                  s = ComputeLabelField(input, out_grid, factor, options, inner,
                                        jobs[n]);
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
                while (next_merge < labels.size() && done[next_merge]) {
                  merge(next_merge);
                  ++next_merge;
                }
              }
            }
          },
          tbb::simple_partitioner());
    });
    if (!first_error.ok()) return first_error;
    if (next_merge != labels.size()) {
      return absl::InternalError("fill: not every label was merged");
    }
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // Combine, close gaps, restore key slices and count, one output slice at a
  // time on the context's threads: every step reads and writes only its own
  // slice (and the input), and the counts are integer sums, so the result
  // does not depend on the thread count.
  LabelVolume& out = result.labels;
  out.grid = out_grid;
  out.data.assign(out_voxels, 0);
  const std::vector<int64_t> annotated_keys(all_keys.begin(), all_keys.end());
  // bracket[z]: for an output slice strictly between two consecutive
  // annotated key slices ka < kb (input indices), ka; otherwise -1.
  std::vector<int64_t> bracket(out_nz, -1);
  std::vector<int64_t> next_key(out_nz, -1);
  for (size_t a = 0; a + 1 < annotated_keys.size(); ++a) {
    for (int64_t z = annotated_keys[a] * factor + 1;
         z < annotated_keys[a + 1] * factor; ++z) {
      bracket[z] = annotated_keys[a];
      next_key[z] = annotated_keys[a + 1];
    }
  }
  struct Counts {
    int64_t gap_closed = 0, restored = 0;
    std::vector<int64_t> per_label;
  };
  std::vector<Counts> counts(blocks_of(out_nz));
  auto finish_slice = [&](int64_t z, Counts& c) {
    uint16_t* o = out.data.data() + z * plane;
    const float* b = best.data() + z * plane;
    const uint16_t* bl = best_label.data() + z * plane;
    // The largest positive field wins.
    for (int64_t p = 0; p < plane; ++p) {
      if (b[p] > 0) o[p] = bl[p];
    }
    // Gap closing between annotated slices labelled on both sides.
    if (bracket[z] >= 0) {
      const uint16_t* la = input.data.data() + bracket[z] * plane;
      const uint16_t* lb = input.data.data() + next_key[z] * plane;
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
        if (in != 0 && (!filled[in] || is_key[label_index[in]][k])) {
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
      if (o[p] != 0 && filled[o[p]]) ++c.per_label[label_index[o[p]]];
    }
  };
  for_each_block(out_nz, [&](int64_t z0, int64_t z1, int64_t block) {
    Counts& c = counts[block];
    c.per_label.assign(labels.size(), 0);
    for (int64_t z = z0; z < z1; ++z) finish_slice(z, c);
  });
  for (const Counts& c : counts) {
    result.gap_voxels_closed += c.gap_closed;
    result.key_voxels_restored += c.restored;
    for (size_t n = 0; n < labels.size(); ++n) {
      result.per_label[n].output_voxels += c.per_label[n];
    }
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  if (options.keep_fields) {
    for (size_t n = 0; n < labels.size(); ++n) {
      Region& region = regions[n];
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
            const float other =
                best_label[v] == labels[n] ? second[v] : best[v];
            if (other != kNoField) {
              row[i] = std::min(row[i], 0.5f * (row[i] - other));
            }
          }
        }
      }
      result.per_label[n].field = std::move(region.field);
    }
  }
  return result;
}

}  // namespace interslice
